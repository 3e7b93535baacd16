"""``telerig export``: committed episodes into a LeRobot v3, HDF5, robomimic or RLDS dataset."""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any, get_args

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from telerig.config import load_rig
from telerig.config.export import ExportDefaults
from telerig.errors import ExportError, RecordingError
from telerig.export.base import ExportSummary
from telerig.export.frames import read_episode_qa, read_manifest
from telerig.export.run import DEFAULT_KEEP_IDLE_TAIL_S, EpisodeFilter, export, keep_idle_tail
from telerig.qa.report import QaReport
from telerig.record.align import Policy
from telerig.registry import EXPORTERS

__all__ = ["add_arguments"]

_POLICIES: tuple[str, ...] = get_args(Policy)


def add_arguments(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add the ``export`` command."""
    p = sub.add_parser(
        "export",
        help="export committed episodes as a training dataset (LeRobot v3, HDF5, robomimic, RLDS)",
        description="Export committed episodes into a dataset. Re-running with the same --out appends "
        "the episodes the dataset does not hold yet; episodes of another rig are refused. Episodes a "
        "quality gate rejected (the failures partition) are left out unless --include-failures.",
    )
    p.add_argument("--format", required=True, choices=EXPORTERS.names(), help="dataset format")
    p.add_argument("--out", type=Path, required=True, help="dataset directory (created or appended to)")
    p.add_argument(
        "--rig",
        default=None,
        help="rig file or shipped rig whose export: defaults (fps, resample, normalize) and data root "
        "to use; the options below override them",
    )
    p.add_argument(
        "--data-root",
        type=Path,
        default=None,
        help="where the episodes are (default: the rig's, else telerig-data)",
    )
    p.add_argument("--episodes", nargs="+", default=(), metavar="ID", help="only these episode ids")
    p.add_argument("--task", default=None, help="only episodes of this task")
    p.add_argument("--operator", default=None, help="only episodes of this operator")
    p.add_argument("--include-failures", action="store_true", help="also episodes the quality gates rejected")
    p.add_argument(
        "--fps", type=int, default=None, help="dataset rate [Hz] (default: the anchor camera's rate)"
    )
    p.add_argument(
        "--normalize", action="store_true", help="map state and action to [-1, 1] from the robot's limits"
    )
    p.add_argument(
        "--resample",
        nargs="+",
        default=(),
        metavar="STREAM=POLICY",
        help=f"resampling policy per stream name, POLICY one of {', '.join(_POLICIES)} "
        "(default: joint_state/gripper_state linear, commands zoh), e.g. joint_state=nearest",
    )
    p.add_argument(
        "--trim-idle",
        action="store_true",
        help="cut the idle spans the quality gates found (telerig qa); the episodes are untouched",
    )
    p.add_argument(
        "--keep-idle-tail",
        type=float,
        default=DEFAULT_KEEP_IDLE_TAIL_S,
        metavar="S",
        help="with --trim-idle, keep the first S seconds of the idle tail (default "
        f"{DEFAULT_KEEP_IDLE_TAIL_S:g}): a policy learns from them to hold still once the task is done",
    )
    p.add_argument(
        "--option",
        nargs="+",
        default=(),
        metavar="KEY=VALUE",
        help="format option (a field of the format's config), e.g. --option compression=lzf",
    )
    p.set_defaults(handler=_cmd_export)


def _cmd_export(args: argparse.Namespace) -> int:
    if not (math.isfinite(args.keep_idle_tail) and args.keep_idle_tail >= 0.0):
        raise ExportError(f"--keep-idle-tail must be seconds >= 0, got {args.keep_idle_tail}")
    selection = EpisodeFilter(
        ids=tuple(args.episodes),
        task=args.task,
        operator=args.operator,
        include_failures=args.include_failures,
    )
    console = Console(stderr=True)
    with Progress(
        TextColumn("exporting {task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeRemainingColumn(),
        console=console,
        transient=True,
        disable=not sys.stderr.isatty(),
    ) as bar:
        task = bar.add_task(args.format, total=None)

        def progress(done: int, total: int, episode_id: str) -> None:
            bar.update(task, completed=done, total=total, description=f"{args.format} ({episode_id})")

        defaults, data_root = _rig_defaults(args)
        summary = export(
            data_root,
            args.format,
            args.out,
            selection=selection,
            fps=args.fps if args.fps is not None else defaults.fps,
            normalize=args.normalize or defaults.normalize,
            policies={**defaults.resample, **_policies(args.resample)},
            trim=(lambda d: _idle_spans(d, args.keep_idle_tail)) if args.trim_idle else None,
            options=_options(args.option),
            progress=progress,
        )
    _print(summary)
    return 0


def _rig_defaults(args: argparse.Namespace) -> tuple[ExportDefaults, Path]:
    """The rig's ``export:`` section and data root (defaults without ``--rig``)."""
    if args.rig is None:
        return ExportDefaults(), args.data_root or Path("telerig-data")
    rig = load_rig(args.rig)
    return rig.export, args.data_root or Path(rig.recording.data_root)


def _idle_spans(episode_dir: Path, keep_tail_s: float) -> Sequence[tuple[float, float]]:
    record = read_episode_qa(episode_dir)
    if record is None:
        raise ExportError(
            f"episode {episode_dir.name} has no quality record, so its idle spans are unknown; "
            "run `telerig qa` first or export without --trim-idle"
        )
    try:
        spans = QaReport.from_json(record.report).idle_segments
    except RecordingError as exc:
        raise ExportError(
            f"{episode_dir.name}: unreadable quality report ({exc}); re-run telerig qa"
        ) from None
    return keep_idle_tail(spans, read_manifest(episode_dir).duration_s, keep_tail_s) if keep_tail_s else spans


def _policies(items: Sequence[str]) -> dict[str, Policy]:
    out: dict[str, Policy] = {}
    for item in items:
        stream, sep, policy = item.partition("=")
        if not sep or not stream or policy not in _POLICIES:
            raise ExportError(
                f"--resample {item!r}: expected STREAM=POLICY with POLICY one of {', '.join(_POLICIES)}"
            )
        out[stream] = policy  # type: ignore[assignment]  # checked against Policy's values above
    return out


def _options(items: Sequence[str]) -> dict[str, Any]:
    import json

    out: dict[str, Any] = {}
    for item in items:
        key, sep, raw = item.partition("=")
        if not sep or not key or key == "type":
            raise ExportError(f"--option {item!r}: expected KEY=VALUE (a field of the format's config)")
        try:
            out[key] = json.loads(raw)
        except ValueError:
            out[key] = raw
    return out


def _print(summary: ExportSummary) -> None:
    out = Console(width=None if sys.stdout.isatty() else 130)
    skipped = f", {len(summary.skipped)} already in the dataset" if summary.skipped else ""
    rate = f" in {summary.seconds:.1f} s" if summary.seconds else ""
    out.print(
        f"{summary.format}: {len(summary.added)} episodes, {summary.frames} frames written{rate}{skipped}; "
        f"{summary.episodes_total} episodes in {summary.out}",
        highlight=False,
        soft_wrap=True,
    )
