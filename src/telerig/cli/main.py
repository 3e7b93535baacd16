"""The ``telerig`` command."""

from __future__ import annotations

import argparse
import logging
import math
import os
import signal
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from rich.console import Console
from rich.progress import BarColumn, Progress, TaskID, TextColumn, TimeRemainingColumn
from rich.table import Table

from telerig.cli.broker import add_arguments as add_broker_arguments
from telerig.cli.device import add_arguments as add_device_arguments
from telerig.cli.episodes import add_arguments as add_episodes_arguments
from telerig.cli.export import add_arguments as add_export_arguments
from telerig.cli.process import add_arguments as add_process_arguments
from telerig.cli.qa import GATES_WAIT_S, verdict_cell, wait_for_gates
from telerig.cli.qa import add_arguments as add_qa_arguments
from telerig.cli.retarget import add_arguments as add_retarget_arguments
from telerig.cli.safety import add_arguments as add_safety_arguments
from telerig.cli.serve import add_arguments as add_serve_arguments
from telerig.cli.session import add_arguments as add_session_arguments
from telerig.cli.task import add_arguments as add_task_arguments
from telerig.cli.train import add_arguments as add_train_arguments
from telerig.cli.view import add_arguments as add_view_arguments
from telerig.cli.voice import add_arguments as add_voice_arguments
from telerig.config.schema import RigConfig, SessionCommand
from telerig.errors import TelerigError
from telerig.runtime.process_settings import Terminated, raise_terminated
from telerig.store.repair import add_repair_arguments, cmd_repair

if TYPE_CHECKING:
    from telerig.qa.checker import QaOutcome
    from telerig.runtime.rig import EpisodeResult, RigRuntime

__all__ = ["main"]

# Wide enough for the summary tables when output is piped (rich assumes 80 columns then).
console = Console(width=None if sys.stdout.isatty() else 130)
err_console = Console(stderr=True, width=None if sys.stderr.isatty() else 200)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    parser = _parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.WARNING,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    if not hasattr(args, "handler"):
        parser.print_help()
        return 2
    try:
        code: int = args.handler(args)
        return code
    except TelerigError as exc:
        err_console.print(f"[bold red]telerig: error:[/] {exc}", highlight=False, soft_wrap=True)
        return 2
    except KeyboardInterrupt as exc:
        what = "terminated (SIGTERM)" if isinstance(exc, Terminated) else "interrupted"
        err_console.print(f"telerig: {what}; robots stopped, earlier episodes intact")
        return 143 if isinstance(exc, Terminated) else 130


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="telerig", description="Teleoperation and robot-data platform.")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(title="commands")

    demo = sub.add_parser("demo", help="run the demo rig: scripted VR operator, simulated UR5e, 3 episodes")
    _add_run_args(demo, default_rig="demo")
    demo.add_argument(
        "--no-replay",
        dest="replay",
        action="store_false",
        help="script every episode (by default the last one replays the first one's recorded device stream)",
    )
    demo.set_defaults(handler=_cmd_run)

    run = sub.add_parser("run", help="run a rig file and record episodes")
    run.add_argument("rig", help="rig file path or shipped rig name")
    _add_run_args(run, default_rig=None)
    run.add_argument(
        "--station",
        default=None,
        help="station of the rig to run on this host (default: the first, which coordinates the session; "
        "any other follows it and records its own devices, robots and cameras)",
    )
    run.add_argument(
        "--broker",
        default=None,
        help="broker URL to use instead of the rig's, e.g. mqtt://coordinator-host:1883",
    )
    run.add_argument(
        "--credentials",
        type=Path,
        default=None,
        help="bus login file of this station (the coordinator's `telerig run` writes "
        "DATA_ROOT/.bus-RIG-station-ID.json for each following station)",
    )
    run.set_defaults(handler=_cmd_run, replay=False)

    cal = sub.add_parser(
        "calibrate", help="calibrate an operator: hold both hands straight forward, level, and still"
    )
    cal.add_argument("--operator", required=True, help="operator name; the profile is stored under it")
    cal.add_argument("--rig", default="demo", help="rig file path or shipped rig name")
    cal.add_argument("--device", default=None, help="device id in the rig (default: the first device)")
    cal.add_argument("--duration", type=float, default=30.0, help="seconds to hold still (default 30)")
    cal.add_argument("--data-root", type=Path, default=None, help="where profiles go (default: from the rig)")
    cal.set_defaults(handler=_cmd_calibrate)

    add_session_arguments(sub)
    add_voice_arguments(sub)  # telerig say, telerig voice

    rep = sub.add_parser("repair", help="recover episodes interrupted by a crash (left in .incoming)")
    add_repair_arguments(rep)
    rep.set_defaults(handler=cmd_repair)

    rig = sub.add_parser("rig", help="inspect rig files")
    rig_sub = rig.add_subparsers(title="rig commands")
    check = rig_sub.add_parser("check", help="validate a rig file")
    check.add_argument("rig")
    check.set_defaults(handler=_cmd_rig_check)
    rig_list = rig_sub.add_parser("list", help="list the shipped example rigs")
    rig_list.set_defaults(handler=_cmd_rig_list)

    add_episodes_arguments(sub)
    add_retarget_arguments(sub)
    add_safety_arguments(sub)
    add_broker_arguments(sub)
    add_device_arguments(sub)
    add_export_arguments(sub)
    add_process_arguments(sub)
    add_serve_arguments(sub)
    add_qa_arguments(sub)
    add_view_arguments(sub)
    add_train_arguments(sub)
    add_task_arguments(sub)
    return parser


def _add_run_args(p: argparse.ArgumentParser, *, default_rig: str | None) -> None:
    if default_rig is not None:
        p.add_argument("--rig", default=default_rig, help="rig file path or shipped rig name")
    p.add_argument(
        "--episodes",
        type=int,
        default=None,
        help="number of episodes to keep (default: from the rig); `telerig session stop` ends the running "
        "episode and the run goes on, a discarded or restarted one is recorded again, `telerig session end` "
        "ends the run",
    )
    p.add_argument("--duration", type=float, default=None, help="seconds per episode (default: from the rig)")
    p.add_argument("--data-root", type=Path, default=None, help="where episodes go (default: from the rig)")


def _cmd_run(args: argparse.Namespace) -> int:
    from telerig.cli.bus_options import operator_login, public_address, run_broker_url
    from telerig.config import load_rig
    from telerig.runtime.process_settings import control_process
    from telerig.runtime.rig import RigRuntime

    # A service manager's SIGTERM stops the rig like Ctrl-C: robots hold, the episode is kept.
    signal.signal(signal.SIGTERM, raise_terminated)
    os.environ.setdefault("MUJOCO_GL", "osmesa")
    os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
    config = load_rig(args.rig)
    broker_url = run_broker_url(getattr(args, "broker", None), getattr(args, "credentials", None), config)
    station = getattr(args, "station", None)
    if station is not None and station != config.stations[0].id:
        return _follow_session(config, args)
    episodes = args.episodes if args.episodes is not None else config.recording.episodes
    duration = args.duration if args.duration is not None else config.recording.episode_duration_s
    if episodes < 1 or duration <= 0:
        raise TelerigError("--episodes must be >= 1 and --duration > 0")
    results: list[EpisodeResult] = []
    console.print(
        f"[bold]telerig[/] rig [cyan]{config.name}[/]: {episodes} episode(s) of {duration:g} s "
        f"→ {args.data_root or config.recording.data_root}"
    )
    with Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        TextColumn("{task.completed:.1f}/{task.total:.0f} s"),
        TimeRemainingColumn(),
        console=console,
        transient=False,
    ) as progress:
        start = progress.add_task("starting broker, robots and nodes", total=duration)
        with (
            control_process(realtime_priority=config.runtime.realtime_priority),
            RigRuntime(config, data_root=args.data_root, broker_url=broker_url) as runtime,
            operator_login(runtime.broker.embedded, runtime.store.root, config) as login,
        ):
            progress.remove_task(start)
            progress.console.print(
                f"broker [cyan]{public_address(runtime.broker.url or '')}[/]"
                + ("" if login is None else f"; operators' login in {login} (telerig safety/session use it)"),
                highlight=False,
            )
            i = 0
            while i < episodes:
                label = f"episode {i + 1}/{episodes}"
                committed = [r for r in results if r.status == "complete"]
                if args.replay and episodes > 1 and i == episodes - 1 and committed:
                    label += f" (replaying {_replay_first_episode(runtime, committed[0])})"
                task = progress.add_task(label, total=duration)

                def report(elapsed: float, total: float, task_id: TaskID = task) -> None:
                    progress.update(task_id, completed=elapsed)

                result = runtime.run_episode(duration, progress=report)
                results.append(result)
                progress.update(task, description=f"{label} {_outcome(result)}")
                if not run_goes_on(result.command):
                    break
                if result.command not in _RECORDED_AGAIN:
                    i += 1
            gates = wait_for_gates(runtime.storage, [r.episode_id for r in results], progress)
    _print_summary(results, gates)
    return 0


#: Episodes the operator threw away to record again: they do not count towards ``--episodes``.
_RECORDED_AGAIN = frozenset({SessionCommand.RESTART_EPISODE, SessionCommand.DISCARD_EPISODE})


def run_goes_on(command: SessionCommand | None) -> bool:
    """Whether ``telerig run`` records the next episode after one that ``command`` ended.

    ``telerig session stop`` / ``discard`` (and restart, reset-and-next) end only the running
    episode; ``telerig session end`` and the stop-collection button end the session.
    """
    return command not in (SessionCommand.END_SESSION, SessionCommand.STOP_COLLECTION)


def _follow_session(config: RigConfig, args: argparse.Namespace) -> int:
    """Run a following station: record every episode the coordinator starts until Ctrl-C (or --episodes)."""
    from telerig.cli.bus_options import run_broker_url
    from telerig.runtime.process_settings import control_process
    from telerig.runtime.rig import RigRuntime

    results: list[EpisodeResult] = []
    limit = args.episodes
    console.print(
        f"[bold]telerig[/] rig [cyan]{config.name}[/], station [cyan]{args.station}[/]: following the "
        f"session coordinator → {args.data_root or config.recording.data_root} (Ctrl-C to stop)"
    )
    with (
        control_process(realtime_priority=config.runtime.realtime_priority),
        RigRuntime(
            config,
            data_root=args.data_root,
            station=args.station,
            broker_url=run_broker_url(args.broker, args.credentials, config),
        ) as runtime,
        Progress(
            TextColumn("{task.description}"),
            TextColumn("{task.completed:.1f} s"),
            console=console,
            transient=False,
        ) as progress,
    ):
        waiting = progress.add_task("waiting for the coordinator to start an episode", total=None)
        while limit is None or len(results) < limit:

            def report(elapsed: float, total: float, task_id: TaskID = waiting) -> None:
                progress.update(task_id, description="recording", completed=elapsed)

            result = runtime.follow_episode(timeout_s=1.0, progress=report)
            if result is None:
                continue
            progress.update(waiting, description=f"episode {result.episode_id} {_outcome(result)}")
            results.append(result)
            if not run_goes_on(result.command):
                break
            waiting = progress.add_task("waiting for the coordinator to start an episode", total=None)
        gates = wait_for_gates(runtime.storage, [r.episode_id for r in results], progress)
    _print_summary(results, gates)
    return 0


def _outcome(result: EpisodeResult) -> str:
    text = "[green]committed[/]" if result.status == "complete" else "[yellow]discarded[/]"
    return text if result.command is None else f"{text} (operator: {result.command.value})"


def _replay_first_episode(runtime: RigRuntime, first: EpisodeResult) -> str:
    """Swap every device for a replay of its stream recorded in ``first``; returns a description."""
    # Its quality gates may move it to failures/ (a replay reads its log as it starts): let them finish.
    runtime.storage.qa_outcome(first.episode_id, GATES_WAIT_S)
    replayed = runtime.replay_devices(first)
    return ", ".join(f"{device_id} from {first.episode_id}" for device_id in replayed) or "nothing"


def _print_summary(eps: Sequence[EpisodeResult], gates: Mapping[str, QaOutcome | None] | None = None) -> None:
    if not eps:
        return
    table = Table(title="streams (all episodes)")
    for col in ("stream", "expected Hz", "measured Hz", "messages", "drops", "max gap ms"):
        table.add_column(col, justify="left" if col == "stream" else "right")
    names = [s.name for s in eps[0].streams]
    for name in names:
        rows = [s for r in eps for s in r.streams if s.name == name]
        expected = rows[0].expected_hz
        measured = sum(s.measured_hz for s in rows) / len(rows)
        table.add_row(
            name.split("/", 3)[-1],  # telerig/v1/<rig>/ is the same for every row
            f"{expected:.0f}" if expected else "-",
            f"{measured:.1f}",
            str(sum(s.messages for s in rows)),
            str(sum(s.drops for s in rows)),
            f"{max(s.max_gap_ms for s in rows):.1f}",
        )
    console.print(table)
    lat = Table(title="input-to-actuation latency (device capture → driver apply)")
    for col in ("episode", "commands", "p50 ms", "p99 ms", "max ms"):
        lat.add_column(col, justify="right")
    for r in eps:
        lat.add_row(
            r.episode_id,
            str(r.latency.count),
            _ms(r.latency.p50_ms),
            _ms(r.latency.p99_ms),
            _ms(r.latency.max_ms),
        )
    console.print(lat)
    written = Table(title="episodes written")
    for col in ("id", "status", "duration s", "video frames", "quality gates", "path"):
        written.add_column(col)
    gates = gates or {}
    for r in eps:
        frames = ", ".join(f"{k}: {v}" for k, v in r.camera_frames.items()) or "-"
        verdict = verdict_cell(gates.get(r.episode_id), r.episode_id in gates)
        written.add_row(r.episode_id, r.status, f"{r.duration_s:.1f}", frames, verdict, str(r.path))
    console.print(written)


def _ms(value: float) -> str:
    return "-" if math.isnan(value) else f"{value:.2f}"


def _cmd_calibrate(args: argparse.Namespace) -> int:
    from telerig.calibrate import calibrate_from_device, save_profile
    from telerig.config import load_rig

    config = load_rig(args.rig)
    devices = {d.id: d for d in config.devices}
    device_id = args.device or next(iter(devices), None)
    if device_id not in devices:
        raise TelerigError(
            f"--device {device_id!r} is not in rig {config.name!r}. Available: {', '.join(devices)}"
        )
    data_root = args.data_root or config.recording.data_root
    console.print(
        f"calibrating operator [cyan]{args.operator}[/] with {device_id}: hold both hands straight forward, "
        f"level and still for {args.duration:g} s"
    )
    with Progress(
        TextColumn("{task.description}"), BarColumn(), TimeRemainingColumn(), console=console
    ) as bar:
        task = bar.add_task("holding", total=args.duration)
        profile = calibrate_from_device(
            devices[device_id].build(),
            args.duration,
            operator=args.operator,
            progress=lambda elapsed, total: bar.update(task, completed=min(elapsed, total)),
        )
    path = save_profile(profile, data_root=data_root)
    console.print(
        f"[green]ok[/] arm length {profile.arm_length_m:.2f} m ({profile.arm_length_source}), scale "
        f"{profile.scale:.2f}, rotation {tuple(round(c, 3) for c in profile.rotation)} → {path}"
    )
    return 0


def _cmd_rig_check(args: argparse.Namespace) -> int:
    from telerig.config import load_rig

    config = load_rig(args.rig)
    console.print(
        f"[green]ok[/] rig {config.name!r}: {len(config.devices)} device(s), {len(config.robots)} robot(s), "
        f"{len(config.cameras)} camera(s), {len(config.bindings)} binding(s)"
    )
    return 0


def _cmd_rig_list(args: argparse.Namespace) -> int:
    from telerig.config import shipped_rig_path, shipped_rigs

    for name in shipped_rigs():
        console.print(f"{name}\t{shipped_rig_path(name)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
