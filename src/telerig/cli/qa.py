"""``telerig qa [EPISODES...]``: run the quality gates and the score on committed episodes, move the
rejected ones to the failures partition (and passing ones back), record every verdict."""

from __future__ import annotations

import argparse
import re
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn
from rich.table import Table

from telerig.errors import TelerigError

if TYPE_CHECKING:  # imported when the command runs: the gates bring numpy and MuJoCo
    from telerig.qa.checker import QaOutcome
    from telerig.runtime.storage import StationStorage

__all__ = [
    "EXIT_CHECK_FAILED",
    "EXIT_REJECTED",
    "GATES_WAIT_S",
    "add_arguments",
    "cmd_qa",
    "verdict_cell",
    "wait_for_gates",
]

#: Some episode could not be checked (unreadable log, missing model): QA itself failed.
EXIT_CHECK_FAILED = 1
#: With ``--fail-on-reject``: every episode was checked and at least one was rejected.
EXIT_REJECTED = 3
#: Episodes checked in one run up to which each gets its own table of gates.
_DETAILED_UP_TO = 3
#: An episode argument is an id or an id prefix: nothing that could name a path.
_ID_ARG = re.compile(r"^[A-Za-z0-9-]+$")

_EPILOG = f"""\
Which episodes: the ones named (id or unique prefix), else every committed episode not yet checked
(no qa.json, or a check a crash cut short). --recheck checks every committed episode, in episodes/
and failures/, with the thresholds of the current rig file: after a threshold change, episodes move
to failures/ and back. Thresholds come from the rig's qa: section (--rig), the defaults without one.

Each check writes qa.json beside the episode (its manifest never changes) and its verdicts, score
and status (failed_qa) to the index. A rejected episode is moved, never deleted: failures train
recovery policies.

Exit status: 0 when every episode was checked, whatever the verdicts (a rejection is QA doing its
job; a nightly run should not alarm for it); {EXIT_CHECK_FAILED} when some episode could not be checked
(that needs a person); 2 on a usage error; with --fail-on-reject, {EXIT_REJECTED} when all were checked
and at least one was rejected (a pipeline step that must not go on to export).
"""


def add_arguments(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add ``telerig qa``."""
    p = sub.add_parser(
        "qa",
        help="run the quality gates on committed episodes; rejected ones move to failures/",
        description="Run the quality gates and the quality score on committed episodes.",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("episodes", nargs="*", metavar="EPISODE", help="episode id or unique id prefix")
    p.add_argument(
        "--recheck",
        action="store_true",
        help="check every committed episode (episodes/ and failures/) again with the current thresholds",
    )
    p.add_argument(
        "--rig",
        default=None,
        help="rig file or shipped rig whose qa: thresholds, data root and index to use (default: the "
        "default thresholds, telerig-data, its index.sqlite)",
    )
    p.add_argument("--data-root", type=Path, default=None, help="data root (default: the rig's)")
    p.add_argument(
        "--fail-on-reject",
        action="store_true",
        help=f"exit {EXIT_REJECTED} when any episode is rejected",
    )
    p.set_defaults(handler=cmd_qa)


def cmd_qa(args: argparse.Namespace) -> int:
    """Check the chosen episodes; print their verdicts; see the epilog for the exit status."""
    from telerig.config.qa import QaThresholds
    from telerig.qa.checker import check_episode, task_median, unchecked
    from telerig.store.episodes import EpisodeStore
    from telerig.store.index import EpisodeIndex

    console = Console(width=None if sys.stdout.isatty() else 130)
    for name in args.episodes:
        if not _ID_ARG.match(name):
            raise TelerigError(f"{name!r} is not an episode id or id prefix (ep-YYYYMMDD-HHMMSS-xxxx)")
    thresholds, root, index_target = QaThresholds(), args.data_root, None
    if args.rig is not None:
        from telerig.config import load_rig

        rig = load_rig(args.rig)
        thresholds, index_target = rig.qa, rig.storage.index
        root = root or Path(rig.recording.data_root)
    root = Path(root or "telerig-data")
    if not root.is_dir():
        raise TelerigError(f"data root {root} does not exist; give the one `telerig run` wrote to")
    store = EpisodeStore(root)
    if args.episodes:
        ids = list(dict.fromkeys(store.find(name).id for name in args.episodes))
    elif args.recheck:
        ids = [s.id for s in store.list(include_failures=True)]
    else:
        ids = [s.id for s in unchecked(store)]
    if not ids:
        console.print(f"no committed episodes to check in {root} (--recheck checks them all again)")
        return 0
    outcomes: list[QaOutcome] = []
    errors: list[tuple[str, str]] = []
    with EpisodeIndex.open(index_target or root) as index:
        medians: dict[str, float | None] = {}
        with Progress(
            TextColumn("{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeRemainingColumn(),
            console=console,
            transient=True,
            disable=len(ids) < 2,
        ) as progress:
            bar = progress.add_task("checking episodes", total=len(ids))
            for episode_id in ids:
                progress.update(bar, description=f"checking {episode_id}")
                try:
                    task = store.find(episode_id).task
                    if task not in medians:
                        medians[task] = task_median(index, task)
                    outcome = check_episode(
                        store, episode_id, thresholds, index=index, task_median_s=medians[task]
                    )
                except TelerigError as exc:
                    errors.append((episode_id, str(exc)))
                    progress.console.print(f"[red]{episode_id}: not checked: {exc}[/]", highlight=False)
                else:
                    outcomes.append(outcome)
                    if outcome.moved:
                        where = "failures" if outcome.partition == "failures" else "episodes (passed now)"
                        progress.console.print(f"{episode_id} → {where}", highlight=False)
                progress.advance(bar)
    _print(console, outcomes)
    rejected = sum(1 for o in outcomes if not o.passed)
    console.print(
        f"{len(outcomes)} checked, {len(outcomes) - rejected} passed, {rejected} rejected"
        + (f", [red]{len(errors)} not checked[/]" if errors else "")
        + f" (thresholds {'of rig ' + repr(args.rig) if args.rig else 'by default'})",
        highlight=False,
    )
    if errors:
        return EXIT_CHECK_FAILED
    return EXIT_REJECTED if args.fail_on_reject and rejected else 0


def _print(console: Console, checked: Sequence[QaOutcome]) -> None:
    if len(checked) <= _DETAILED_UP_TO:
        for o in checked:
            console.print(_gate_table(o))
        return
    table = Table(title="quality gates")
    for col in ("episode", "verdict", "score", "where", "failed gates"):
        table.add_column(col)
    for o in checked:
        table.add_row(
            o.episode_id,
            _verdict(o.passed),
            "-" if o.score is None else f"{o.score:.2f}",
            o.partition + (" (moved)" if o.moved else ""),
            ", ".join(v.gate for v in o.report.verdicts if v.passed is False) or "-",
        )
    console.print(table)


def _gate_table(outcome: QaOutcome) -> Table:
    score = "-" if outcome.score is None else f"{outcome.score:.2f}"
    table = Table(
        title=f"{outcome.episode_id}: {_verdict(outcome.passed)}, score {score}, in {outcome.partition}/",
    )
    for col in ("gate", "verdict", "value", "threshold", "detail"):
        table.add_column(col, justify="right" if col in ("value", "threshold") else "left")
    for v in outcome.report.verdicts:
        table.add_row(
            v.gate, _verdict(v.passed), _number(v.value, v.unit), _number(v.threshold, v.unit), v.detail
        )
    return table


def _verdict(passed: bool | None) -> str:
    if passed is None:
        return "[dim]n/a[/]"
    return "[green]pass[/]" if passed else "[bold red]FAIL[/]"


def _number(value: float | None, unit: str) -> str:
    return "-" if value is None else f"{value:.4g} {unit}".strip()


# --- telerig run: the verdicts of the episodes it recorded -----------------------------------------

#: How long `telerig run` waits at its end for the gates of its last episodes [s].
GATES_WAIT_S = 120.0


def wait_for_gates(
    storage: StationStorage, episode_ids: Sequence[str], progress: Progress, timeout_s: float = GATES_WAIT_S
) -> dict[str, QaOutcome | None]:
    """The gates' outcome of each episode the station submitted to them, waiting up to ``timeout_s``
    [s] in all with a progress line; ``None`` for one that was not checked (``telerig qa`` does it)."""
    import time

    submitted = [e for e in episode_ids if e in storage.qa_checks]
    if not submitted:
        return {}
    deadline = time.monotonic() + timeout_s
    task = progress.add_task("quality gates", total=len(submitted))
    out: dict[str, QaOutcome | None] = {}
    for episode_id in submitted:
        out[episode_id] = storage.qa_outcome(episode_id, max(0.0, deadline - time.monotonic()))
        progress.advance(task)
    progress.remove_task(task)
    return out


def verdict_cell(outcome: QaOutcome | None, submitted: bool) -> str:
    """One cell of `telerig run`'s episode table: the verdict, score and failed gates."""
    if outcome is None:
        return "[yellow]not checked: run telerig qa[/]" if submitted else "-"
    score = "" if outcome.score is None else f", score {outcome.score:.2f}"
    if outcome.passed:
        return f"[green]pass[/]{score}"
    failed = ", ".join(v.gate for v in outcome.report.verdicts if v.passed is False)
    return f"[bold red]FAIL[/] {failed}{score} → failures/"
