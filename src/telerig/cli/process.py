"""``telerig process``: recorded episodes and plain video folders into an annotated clip dataset."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TaskID, TextColumn, TimeElapsedColumn
from rich.table import Table

from telerig.errors import ProcessError

if TYPE_CHECKING:
    from telerig.config.process import ProcessSettings
    from telerig.process.run import RunSummary, StageEvent

__all__ = ["add_arguments", "default_out"]

_MAX_SHOWN_FAILURES = 10


def add_arguments(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add the ``process`` command."""
    p = sub.add_parser(
        "process",
        help="turn episodes or folders of video into annotated clips (filter ... layout)",
        description="Run the annotation pipeline over PATH_OR_QUERY: a data root (every committed "
        "episode, failures included), an episode directory or id, a query KEY=VALUE[,KEY=VALUE] over the "
        "data root (keys id, task, operator, rig, partition), a video file or a folder of videos "
        "(*.mp4 *.mov *.mkv *.webm, searched recursively). Finished work is skipped on a re-run; a stage "
        "whose version or settings changed is redone with the stages after it. A failing item is "
        "recorded (failures.json) and the batch goes on; the exit code is 1 when any item failed.",
    )
    p.add_argument("target", metavar="PATH_OR_QUERY", help="data root, episode, query, video or folder")
    p.add_argument(
        "--out",
        type=Path,
        default=None,
        help="processed root (default: <data root>/processed, or <folder>/processed for videos)",
    )
    p.add_argument(
        "--stages",
        nargs="+",
        default=None,
        metavar="STAGE",
        help="stages to run, in order (default: filter segment clips annotate layout); also comma-separated",
    )
    p.add_argument("--cluster", default=None, metavar="ADDR", help="Dask scheduler (tcp://HOST:PORT)")
    p.add_argument("--workers", type=int, default=None, help="local worker processes (default: CPU cores)")
    p.add_argument(
        "--rig", default=None, help="rig file or shipped rig (process: settings, data root, index)"
    )
    p.add_argument("--data-root", type=Path, default=None, help="episode store for ids and queries")
    p.add_argument(
        "--index",
        default=None,
        help="index database for the clips (default: the rig's, else <data root>/index.sqlite, else "
        "<out>/index.sqlite)",
    )
    p.set_defaults(handler=_cmd_process)


def default_out(target: str, data_root: Path | None) -> Path:
    """Where ``telerig process TARGET`` writes by default: a ``processed/`` folder beside the inputs."""
    from telerig.process.items import is_data_root

    path = Path(target)
    try:
        if path.is_dir() and is_data_root(path):
            return path / "processed"
        if path.is_dir() and (path / "manifest.json").is_file() and is_data_root(path.parent.parent):
            return path.parent.parent / "processed"
        if path.is_dir():
            return path / "processed"
        if path.is_file():
            return path.parent / "processed"
    except OSError:  # a name too long for the filesystem, a path through a file: not a path
        pass
    if data_root is not None:
        return data_root / "processed"
    raise ProcessError(
        f"{target[:200]!r} is not a file, folder, data root or episode; give a folder of videos, a data "
        "root, or an episode id / query with --data-root"
    )


def _stage_names(raw: Sequence[str] | None) -> list[str]:
    from telerig.process.stage import STAGE_ORDER

    if raw is None:
        return list(STAGE_ORDER)
    names = [n.strip() for item in raw for n in item.split(",") if n.strip()]
    if not names:
        raise ProcessError("--stages: name at least one stage")
    return names


def _settings(args: argparse.Namespace) -> tuple[ProcessSettings, Path | None, str | None]:
    """The rig's ``process:`` settings, data root and index URL (defaults without ``--rig``)."""
    from telerig.config import load_rig
    from telerig.config.process import ProcessSettings

    if args.rig is None:
        root = args.data_root
        if root is None and Path("telerig-data").is_dir():
            root = Path("telerig-data")
        return ProcessSettings(), root, None
    rig = load_rig(args.rig)
    return rig.process, args.data_root or Path(rig.recording.data_root), rig.storage.index


def _cmd_process(args: argparse.Namespace) -> int:
    from telerig.process.items import discover
    from telerig.process.run import plan, run_pipeline
    from telerig.registry import PROCESS_STAGES

    if args.workers is not None and not 1 <= args.workers <= 256:
        raise ProcessError(f"--workers {args.workers}: give 1 to 256 processes")
    settings, data_root, rig_index = _settings(args)
    names = _stage_names(args.stages)
    stages = []
    for name in names:
        try:
            stages.append(PROCESS_STAGES.get(name)())
        except KeyError as exc:
            raise ProcessError(f"--stages: {exc.args[0]}") from None
    planned = plan(stages, {n: settings.for_stage(n) for n in names})
    out = args.out if args.out is not None else default_out(args.target, data_root)
    found = discover(args.target, data_root=data_root, cache_dir=out / ".cache")
    if not found.items and not found.skipped:
        raise ProcessError(f"{args.target[:200]!r} holds no episode or video to process")
    err = Console(stderr=True)
    err.print(
        f"processing {len(found.items)} items ({', '.join(names)}) into {out}"
        + (f" on {args.cluster}" if args.cluster else ""),
        highlight=False,
        soft_wrap=True,
    )
    with _StageBars(names, len(found.items), err) as bars:
        summary = run_pipeline(
            found.items,
            planned,
            out,
            workers=args.workers if args.workers is not None else settings.workers,
            cluster=args.cluster,
            skipped=found.skipped,
            on_event=bars.update,
        )
    indexed = (
        _index(summary, args.index or rig_index, found.data_root or data_root) if "layout" in names else None
    )
    _print(summary, names, indexed)
    return 1 if summary.failures or summary.skipped_inputs else 0


def _index(summary: RunSummary, url: str | None, data_root: Path | None) -> str | None:
    """Put the clips in the index database; returns where (or ``None`` without an index.json)."""
    from telerig.process.layout import INDEX_FILE, index_clips
    from telerig.store.index import DEFAULT_FILENAME, EpisodeIndex

    if not (summary.work_root / INDEX_FILE).is_file():
        return None
    target = url or str((data_root or summary.work_root) / DEFAULT_FILENAME)
    with EpisodeIndex.open(target) as index:
        n = index_clips(summary.work_root, index)
    return f"{n} clips in {target}"


class _StageBars:
    """One progress bar per stage: items done (partial progress of running items included)."""

    def __init__(self, names: Sequence[str], total: int, console: Console) -> None:
        self._progress = Progress(
            TextColumn("{task.description:>10}"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            console=console,
            transient=False,
            disable=not console.is_terminal,
        )
        self._tasks: dict[str, TaskID] = {}
        self._done: dict[str, int] = dict.fromkeys(names, 0)
        self._running: dict[str, dict[str, float]] = {n: {} for n in names}
        for name in names:
            self._tasks[name] = self._progress.add_task(name, total=total)

    def __enter__(self) -> _StageBars:
        self._progress.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._progress.stop()

    def update(self, event: StageEvent) -> None:
        task = self._tasks.get(event.stage)
        if task is None:
            return
        running = self._running[event.stage]
        if event.done:
            running.pop(event.item_id, None)
            self._done[event.stage] += 1
        else:
            running[event.item_id] = event.fraction
        self._progress.update(task, completed=self._done[event.stage] + sum(running.values()))


def _print(summary: RunSummary, names: Sequence[str], indexed: str | None) -> None:
    out = Console(width=None if sys.stdout.isatty() else 130)
    table = Table(title=f"telerig process: {summary.work_root}")
    for column in ("hours in", "hours kept", "segments", "clips", "clips annotated", "failures", "time"):
        table.add_column(column, justify="right")
    kept = f"{summary.hours_kept:.3f}"
    if summary.hours_in > 0:
        kept += f" ({100 * summary.hours_kept / summary.hours_in:.1f} %)"
    failures = len(summary.failures) + len(summary.skipped_inputs)
    table.add_row(
        f"{summary.hours_in:.3f}",
        kept,
        str(int(summary.total("segments"))),
        str(int(summary.total("clips"))),
        str(int(summary.total("clips_annotated"))),
        str(failures),
        f"{summary.seconds:.1f} s",
    )
    out.print(table)
    stages = Table(title="stages (items)")
    for column in ("stage", "ran", "reused", "empty", "failed"):
        stages.add_column(column, justify="right" if column != "stage" else "left")
    for name in names:
        counts = summary.stage_counts(name)
        stages.add_row(name, *(str(counts[k]) for k in ("ran", "reused", "empty", "failed")))
    out.print(stages)
    shown: list[Any] = [(o.item_id, f.name, f.message) for o in summary.failures if (f := o.failed)]
    shown += [(s.path, "discover", s.reason) for s in summary.skipped_inputs]
    for item, stage, message in shown[:_MAX_SHOWN_FAILURES]:
        out.print(f"failed: {item} ({stage}): {message}", highlight=False, soft_wrap=True)
    if len(shown) > _MAX_SHOWN_FAILURES:
        out.print(f"... {len(shown) - _MAX_SHOWN_FAILURES} more in {summary.work_root / 'failures.json'}")
    if indexed is not None:
        out.print(f"index: {indexed}", highlight=False, soft_wrap=True)
