"""``telerig episodes list|show|plot``: find recorded episodes by task, operator, robot, status, gate,
score and date; show one's manifest; plot its trajectories to a PNG."""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import sys
import typing
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.table import Table

from telerig.config.qa import GATES
from telerig.errors import TelerigError
from telerig.store.annotations_file import read_episode_annotations
from telerig.store.episodes import EpisodeStore
from telerig.store.index import EpisodeIndex, EpisodeOrder, EpisodeRecord, IndexStatus, VerdictRecord
from telerig.store.label_file import read_label
from telerig.store.qa_file import read_qa
from telerig.store.segments_file import read_episode_segments

__all__ = ["SORT_KEYS", "add_arguments", "cmd_list", "cmd_plot", "cmd_show"]

_DEFAULT_ROOT = Path("telerig-data")
#: ``--sort`` keys and the index order they map to (``-`` prefix: descending).
SORT_KEYS: dict[str, str] = {
    "date": "start",
    "duration": "duration",
    "size": "size",
    "score": "quality",
    "task": "task",
    "operator": "operator",
    "status": "status",
}
_STATUSES: tuple[str, ...] = typing.get_args(IndexStatus)
#: Without ``--status`` / ``--all``: the committed episodes, failed quality gates included.
_COMMITTED: tuple[IndexStatus, ...] = ("complete", "repaired", "failed_qa")
_GATE_RESULTS = ("passed", "failed")
_EPOCH = dt.datetime(1970, 1, 1, tzinfo=dt.UTC)


def _console() -> Console:
    # Wide enough for the table when output is piped (rich assumes 80 columns then).
    return Console(highlight=False, width=None if sys.stdout.isatty() else 200)


def add_arguments(subparsers: Any) -> None:
    """Add ``telerig episodes`` and its subcommands to the CLI."""
    episodes = subparsers.add_parser("episodes", help="list, inspect and plot recorded episodes")
    sub = episodes.add_subparsers(title="episode commands")

    ls = sub.add_parser(
        "list",
        help="list episodes, filtered and sorted",
        description="List episodes. Filters combine (all must match); unscored episodes never match a "
        "score filter. Times are UTC unless they carry an offset.",
    )
    ls.add_argument("--data-root", type=Path, default=_DEFAULT_ROOT)
    ls.add_argument(
        "--index",
        default=None,
        help="query this index database as it is (a station's index.sqlite, or postgresql://...) instead "
        "of reading the manifests and qa.json files under --data-root",
    )
    ls.add_argument("--all", action="store_true", help="include incomplete and interrupted episodes")
    ls.add_argument("--task", help="exact task text")
    ls.add_argument("--operator", help="operator id")
    ls.add_argument("--robot", help="robot model of the rig, e.g. ur5e_robotiq85")
    ls.add_argument("--rig", help="rig name")
    ls.add_argument(
        "--status",
        action="append",
        default=None,
        help=f"episode status, repeatable or comma-separated: {', '.join(_STATUSES)} "
        "(default: the committed ones, complete, repaired and failed_qa)",
    )
    ls.add_argument(
        "--gate",
        default=None,
        help="quality gates: 'failed' (any gate failed), 'passed' (checked, none failed), GATE (has a "
        f"verdict of GATE) or GATE=passed|failed; gates: {', '.join(GATES)}",
    )
    ls.add_argument("--min-score", default=None, help="lowest quality score, in [0, 1]")
    ls.add_argument("--max-score", default=None, help="highest quality score, in [0, 1]")
    ls.add_argument("--since", default=None, help="recorded at or after: YYYY-MM-DD or YYYY-MM-DDTHH:MM[:SS]")
    ls.add_argument("--until", default=None, help="recorded before (a bare date includes that day)")
    ls.add_argument(
        "--sort",
        default="date",
        help=f"sort key: {', '.join(SORT_KEYS)} (default: date); descending with a '-' prefix: --sort=-score",
    )
    ls.add_argument("--limit", default=None, help="at most this many episodes")
    ls.add_argument("--json", action="store_true", help="print the episodes as JSON instead of a table")
    ls.set_defaults(handler=cmd_list)

    show = sub.add_parser(
        "show",
        help="show one episode: manifest, quality gates, score, label, segments and their annotations",
    )
    show.add_argument("episode_id", help="episode id or unique prefix")
    show.add_argument("--data-root", type=Path, default=_DEFAULT_ROOT)
    show.add_argument("--json", action="store_true", help="print the raw manifest")
    show.set_defaults(handler=cmd_show)

    plot = sub.add_parser(
        "plot",
        help="write a PNG of an episode: joints requested/sent/measured, gripper, residuals, gate markers",
    )
    plot.add_argument("episode_id", help="episode id or unique prefix")
    plot.add_argument("--data-root", type=Path, default=_DEFAULT_ROOT)
    plot.add_argument("--out", type=Path, default=None, help="the PNG to write (default: ./<episode id>.png)")
    plot.add_argument("--width", default="1600", help="image width in pixels (default 1600)")
    plot.set_defaults(handler=cmd_plot)


# --- list ----------------------------------------------------------------------------------------


def cmd_list(args: argparse.Namespace) -> int:
    """``telerig episodes list``."""
    query = _list_query(args)  # every value checked before anything is opened
    with _open_index(args) as index:
        records = index.list_episodes(**query)
        verdicts: dict[str, list[VerdictRecord]] = {}
        for v in index.verdicts():
            verdicts.setdefault(v.episode_id, []).append(v)
    if args.json:
        print(json.dumps([_record_json(r, verdicts.get(r.id, [])) for r in records], indent=2))
        return 0
    table = Table(title=f"episodes in {args.index or args.data_root} ({len(records)})")
    for col in ("id", "date (UTC)", "status", "task", "operator", "robots", "duration s", "score", "gates"):
        table.add_column(col, justify="right" if col in ("duration s", "score") else "left")
    table.add_column("size MB", justify="right")
    for r in records:
        table.add_row(
            r.id,
            _date(r.start_ns),
            r.status,
            r.task,
            r.operator,
            ", ".join(r.robots) or "-",
            "-" if r.duration_s is None else f"{r.duration_s:.1f}",
            "-" if r.quality is None else f"{r.quality:.2f}",
            _gates(verdicts.get(r.id, [])),
            f"{r.size_bytes / 1e6:.1f}",
        )
    _console().print(table)
    return 0


def _list_query(args: argparse.Namespace) -> dict[str, Any]:
    """``list_episodes`` keyword arguments from the command line; a bad value is a one-line error."""
    query: dict[str, Any] = {
        "task": args.task,
        "operator": args.operator,
        "robot": args.robot,
        "rig": args.rig,
        "status": _statuses(args.status, everything=args.all),
        "min_quality": _score("--min-score", args.min_score),
        "max_quality": _score("--max-score", args.max_score),
        "since_ns": _time_ns("--since", args.since, end_of_day=False),
        "until_ns": _time_ns("--until", args.until, end_of_day=True),
        "order": _order(args.sort),
        "limit": _limit(args.limit),
    }
    low, high = query["min_quality"], query["max_quality"]
    if low is not None and high is not None and low > high:
        raise TelerigError(f"--min-score {args.min_score} is above --max-score {args.max_score}")
    query["gate"], query["gate_passed"] = _gate(args.gate)
    return query


@contextmanager
def _open_index(args: argparse.Namespace) -> Iterator[EpisodeIndex]:
    """The index to query: ``--index`` as it is, or one rebuilt in memory from the data root."""
    if args.index is not None:
        with EpisodeIndex.open(args.index) as index:
            yield index
        return
    if not args.data_root.is_dir():
        raise TelerigError(f"data root {args.data_root} does not exist; give the one `telerig run` wrote to")
    # The manifests and qa.json files are the source of truth; reading them (as this command always
    # did) also sees drafts a crash left and episodes recorded while no index was written. The
    # in-memory index is never written back, so listing cannot race a recording station's index.
    with EpisodeIndex.open("sqlite://") as index:
        index.rebuild(EpisodeStore(args.data_root))
        yield index


def _statuses(values: list[str] | None, *, everything: bool) -> list[str] | None:
    if not values:
        return None if everything else list(_COMMITTED)
    out: list[str] = []
    for value in values:
        for s in (part.strip() for part in value.split(",")):
            if s not in _STATUSES:
                raise TelerigError(
                    f"--status {s!r} is not an episode status. Available: {', '.join(_STATUSES)}"
                )
            out.append(s)
    return out


def _gate(spec: str | None) -> tuple[str | None, bool | None]:
    if spec is None:
        return None, None
    if spec in _GATE_RESULTS:
        return None, spec == "passed"
    gate, sep, result = spec.partition("=")
    if gate not in GATES:
        raise TelerigError(
            f"--gate {spec!r}: {gate!r} is not a quality gate. "
            f"Available: {', '.join(GATES)}, or passed / failed"
        )
    if sep and result not in _GATE_RESULTS:
        raise TelerigError(f"--gate {spec!r}: the result after '=' must be passed or failed")
    return gate, (result == "passed") if sep else None


def _score(flag: str, text: str | None) -> float | None:
    if text is None:
        return None
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not 0.0 <= value <= 1.0:
        raise TelerigError(f"{flag} {text!r} is not a score: give a number in [0, 1]")
    return value


def _time_ns(flag: str, text: str | None, *, end_of_day: bool) -> int | None:
    if text is None:
        return None
    try:
        moment = dt.datetime.fromisoformat(text)
    except ValueError:
        raise TelerigError(
            f"{flag} {text!r} is not a date: give YYYY-MM-DD or YYYY-MM-DDTHH:MM[:SS] "
            "(UTC unless it has an offset)"
        ) from None
    if moment.tzinfo is None:
        moment = moment.replace(tzinfo=dt.UTC)
    if end_of_day and len(text) == 10:  # a bare date: up to the end of that day
        moment += dt.timedelta(days=1)
    return (moment - _EPOCH) // dt.timedelta(microseconds=1) * 1000


def _order(text: str) -> EpisodeOrder:
    key = text.removeprefix("-")
    if key not in SORT_KEYS:
        raise TelerigError(
            f"--sort {text!r} is not a sort key. "
            f"Available: {', '.join(SORT_KEYS)} ('-' prefix for descending)"
        )
    return typing.cast(EpisodeOrder, ("-" if text.startswith("-") else "") + SORT_KEYS[key])


def _limit(text: str | None) -> int | None:
    if text is None:
        return None
    if not text.isdigit() or int(text) < 1:
        raise TelerigError(f"--limit {text!r} is not a count: give a whole number >= 1")
    return int(text)


def _date(start_ns: int) -> str:
    return dt.datetime.fromtimestamp(start_ns / 1e9, dt.UTC).strftime("%Y-%m-%d %H:%M:%S")


def _gates(verdicts: list[VerdictRecord]) -> str:
    if not verdicts:
        return "-"
    failed = [v.gate for v in verdicts if v.passed is False]
    return "failed: " + ", ".join(failed) if failed else "passed"


def _record_json(r: EpisodeRecord, verdicts: list[VerdictRecord]) -> dict[str, Any]:
    return {
        "id": r.id,
        "start": _date(r.start_ns),
        "start_ns": r.start_ns,
        "status": r.status,
        "task": r.task,
        "operator": r.operator,
        "rig": r.rig,
        "robots": list(r.robots),
        "duration_s": r.duration_s,
        "score": r.quality,
        "gates": {v.gate: v.passed for v in verdicts},
        "size_bytes": r.size_bytes,
        "location": r.location,
    }


# --- show, plot ----------------------------------------------------------------------------------


def cmd_show(args: argparse.Namespace) -> int:
    """``telerig episodes show``: the manifest summary, then the sidecars beside it (gates and score,
    label, segments and their annotations). A damaged sidecar is named in one line on stderr (exit
    status 2, as other one-line errors) after everything else is shown."""
    found = EpisodeStore(args.data_root).find(args.episode_id, include_unfinished=True)
    manifest = EpisodeStore(args.data_root).get(found.id, include_unfinished=True)
    if args.json:
        print(json.dumps(manifest.model_dump(mode="json"), indent=2))
        return 0
    console = _console()
    console.print(f"[bold]{manifest.id}[/]  {manifest.status}  {manifest.task!r} by {manifest.operator}")
    duration = "-" if manifest.duration_s is None else f"{manifest.duration_s:.2f} s"
    console.print(f"rig {manifest.rig}, {duration}, {found.path}")
    table = Table(title="files")
    for col in ("file", "bytes", "sha256"):
        table.add_column(col)
    for f in manifest.files:
        table.add_row(f.path, str(f.size), f.sha256[:16])
    console.print(table)
    problems: list[str] = []
    _show_quality(console, found.path, problems)
    _show_segments(console, found.path, problems)
    for line in problems:
        print(f"error: {line}", file=sys.stderr)
    return 2 if problems else 0


def _show_quality(console: Console, episode_dir: Path, problems: list[str]) -> None:
    """Gates, score and label lines (from ``qa.json`` and ``label.json``)."""
    try:
        qa = read_qa(episode_dir)
    except TelerigError as exc:
        problems.append(str(exc))
        qa = None
    if qa is None:
        console.print("gates: not run")
    else:
        verdicts = ", ".join(f"{v.gate} {_verdict(v.passed)}" for v in qa.verdicts) or "-"
        console.print(f"gates: {'passed' if qa.passed else 'failed'} ({verdicts})")
        score = qa.score_total
        console.print(f"score: {'-' if score is None else f'{score:.3f}'}")
        for reason in qa.reasons:
            console.print(f"  {reason}", markup=False)
    try:
        label = read_label(episode_dir)
    except TelerigError as exc:
        problems.append(str(exc))
        label = None
    console.print(
        "label: -" if label is None else f"label: {label.outcome} (by {label.by or '?'})", markup=False
    )


def _verdict(passed: bool | None) -> str:
    return "n/a" if passed is None else ("ok" if passed else "FAILED")


def _show_segments(console: Console, episode_dir: Path, problems: list[str]) -> None:
    """The segments table (``segments.json``) with each segment's description where annotated."""
    try:
        record = read_episode_segments(episode_dir)
        notes = read_episode_annotations(episode_dir) if record is not None else None
    except TelerigError as exc:
        problems.append(str(exc))
        return
    if record is None:
        console.print("segments: none (run `telerig process` on the episode)")
        return
    if record.empty or not record.segments:
        console.print(f"segments: none found in {record.video}")
        return
    described = {} if notes is None else notes.segments
    table = Table(title=f"segments of {record.video} (times on the video, s)")
    for col in ("label", "start", "end", "confidence", "source", "status", "annotation"):
        table.add_column(col)
    for seg in record.segments:
        note = described.get(seg.id)
        text = "-" if note is None else note.description + (" (offline)" if note.offline else "")
        table.add_row(
            seg.label,
            f"{seg.start_s:.2f}",
            f"{seg.end_s:.2f}",
            f"{seg.confidence:.2f}",
            seg.source,
            seg.status,
            text,
        )
    console.print(table)


def cmd_plot(args: argparse.Namespace) -> int:
    """``telerig episodes plot``."""
    from telerig.qa.plot import plot_episode

    if not args.width.isdigit() or not 200 <= int(args.width) <= 20_000:
        raise TelerigError(f"--width {args.width!r} is not an image width: give pixels in 200..20000")
    if not args.data_root.is_dir():
        raise TelerigError(f"data root {args.data_root} does not exist; give the one `telerig run` wrote to")
    found = EpisodeStore(args.data_root).find(args.episode_id, include_unfinished=True)
    out = args.out if args.out is not None else Path(f"{found.id}.png")
    if out.suffix.lower() != ".png":
        raise TelerigError(f"--out {out} must name a .png file")
    summary = plot_episode(found.path, out, width_px=int(args.width))
    failed = sorted({gate for gate, _, bad in summary.gate_events if bad})
    markers = f", {len(summary.gate_events)} gate marker(s)" + (
        f" (failed: {', '.join(failed)})" if failed else ""
    )
    _console().print(
        f"wrote {summary.path} ({summary.width_px}x{summary.height_px} px): {len(summary.panels)} subplot(s)"
        + (markers if summary.gate_events else "")
    )
    return 0
