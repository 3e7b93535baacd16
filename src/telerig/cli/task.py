"""``telerig collect`` and ``telerig eval``: unattended episodes of a randomized task rig.

``collect`` records demonstrations (seeds from 0 by default); ``eval`` rolls a policy checkpoint
out on held-out seeds (from :data:`~telerig.runtime.task.EVAL_SEED_BASE`) and reports success
measured from the scene with a Wilson 95 % interval, the mean time to success and the quality
gates' verdicts; ``--compare`` rolls a second checkpoint out on the same seeds and tests the
difference (McNemar exact).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn
from rich.table import Table

from telerig.errors import ConfigError, TelerigError
from telerig.runtime.process_settings import raise_terminated

if TYPE_CHECKING:
    from telerig.config.schema import RigConfig
    from telerig.runtime.evaluation import PairedComparison, TaskEpisode, TaskSummary

__all__ = ["add_arguments", "checkpoint_spec", "policy_rig"]

console = Console(width=None if sys.stdout.isatty() else 130)

_POLICY = "policy"


def add_arguments(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add ``telerig collect`` and ``telerig eval``."""
    collect = sub.add_parser(
        "collect",
        help="record N episodes of a randomized task rig unattended (scene reset between episodes)",
        description="Record N episodes of a task rig (e.g. pick_place) unattended: before episode k the "
        "arm goes home and the cube is placed from seed S + k; everything is recorded and the outcome "
        "judged from the scene.",
    )
    collect.add_argument("rig", help="rig file path or shipped rig name (e.g. pick_place)")
    _common(collect, default_seed="0")
    collect.set_defaults(handler=_cmd_collect)

    ev = sub.add_parser(
        "eval",
        help="roll a policy checkpoint out on held-out seeds: success rate (Wilson 95 %%), time, gates",
        description="Roll a policy out on a task rig with held-out seeds and measure success from the scene. "
        "The rig's policy device gets the checkpoint; a rig without one gets a policy bound to its task "
        "robot in place of the operator.",
    )
    ev.add_argument("rig", help="rig file path or shipped rig name (e.g. pick_place)")
    ev.add_argument("--policy", type=Path, required=True, help="checkpoint to evaluate (telerig train --out)")
    ev.add_argument(
        "--compare",
        type=Path,
        default=None,
        help="a second checkpoint rolled out on the same seeds; the difference is tested (McNemar exact)",
    )
    ev.add_argument(
        "--execute-actions",
        type=int,
        default=None,
        help="actions of each predicted chunk sent before the policy is asked again "
        "(default: the rig's policy device, or 1: ask every tick)",
    )
    ev.add_argument(
        "--temporal-ensemble",
        type=float,
        default=None,
        metavar="K",
        help="ACT's temporal ensembling: ask the policy every tick and send the mean of the "
        "overlapping chunks' actions, weighted exp(-K i) from the oldest (ACT: 0.01)",
    )
    _common(ev, default_seed="held-out, from 1000000")
    ev.set_defaults(handler=_cmd_eval, episodes=50)


def _common(p: argparse.ArgumentParser, *, default_seed: str) -> None:
    p.add_argument("--episodes", type=int, default=None, help="episodes to run (default: the rig's; eval 50)")
    p.add_argument(
        "--seed", type=int, default=None, help=f"base seed: episode k uses seed + k (default {default_seed})"
    )
    p.add_argument("--duration", type=float, default=None, help="seconds per episode (default: from the rig)")
    p.add_argument("--data-root", type=Path, default=None, help="where episodes go (default: from the rig)")
    p.add_argument("--json", type=Path, default=None, help="also write the results as JSON here")
    p.add_argument(
        "--gates-wait",
        type=float,
        default=30.0,
        help="seconds to wait at the end for each episode's quality gates (default 30; 0: report those done)",
    )


def _prepare(args: argparse.Namespace, *, held_out: bool) -> tuple[RigConfig, int, int, float]:
    from telerig.config import load_rig
    from telerig.runtime.task import COLLECT_SEED_BASE, EVAL_SEED_BASE, check_seed_range, with_task_seed

    signal.signal(signal.SIGTERM, raise_terminated)
    os.environ.setdefault("MUJOCO_GL", "osmesa")
    os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
    config = load_rig(args.rig)
    episodes = args.episodes if args.episodes is not None else config.recording.episodes
    duration = args.duration if args.duration is not None else config.recording.episode_duration_s
    if episodes < 1 or not (math.isfinite(duration) and duration > 0):
        raise ConfigError("--episodes must be >= 1 and --duration > 0 s")
    seed = args.seed if args.seed is not None else (EVAL_SEED_BASE if held_out else COLLECT_SEED_BASE)
    check_seed_range(seed, episodes, held_out=held_out)
    return with_task_seed(config, seed), episodes, seed, duration


def _run(
    config: RigConfig, episodes: int, seed: int, duration: float, args: argparse.Namespace, what: str
) -> list[TaskEpisode]:
    from telerig.runtime.evaluation import run_task_episodes
    from telerig.runtime.process_settings import control_process

    with Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeRemainingColumn(),
        console=console,
    ) as progress:
        overall = progress.add_task(f"{what}: starting broker, robot and nodes", total=episodes)
        current = progress.add_task("", total=duration, visible=False)
        successes = 0

        def on_start(k: int) -> object:
            progress.update(overall, description=f"{what}: episode {k + 1}/{episodes} (seed {seed + k})")
            progress.reset(current, total=duration, visible=True, description="  recording")

            def elapsed(done: float, total: float) -> None:
                progress.update(current, completed=min(done, total))

            return elapsed

        def on_episode(k: int, episode: TaskEpisode) -> None:
            nonlocal successes
            successes += episode.success
            progress.update(overall, advance=1)
            mark = "[green]success[/]" if episode.success else f"[yellow]failure[/] ({episode.reason})"
            progress.console.print(f"  {episode.episode_id} seed {episode.seed}: {mark}", highlight=False)

        with control_process(realtime_priority=config.runtime.realtime_priority):
            results = run_task_episodes(
                config,
                episodes=episodes,
                seed=seed,
                data_root=args.data_root,
                duration_s=duration,
                on_start=on_start,  # type: ignore[arg-type]
                on_episode=on_episode,
                gates_wait_s=max(0.0, args.gates_wait),
            )
        progress.update(overall, description=f"{what}: {successes}/{episodes} successes")
    return results


def _cmd_collect(args: argparse.Namespace) -> int:
    from telerig.runtime.evaluation import summarize

    config, episodes, seed, duration = _prepare(args, held_out=False)
    console.print(
        f"[bold]telerig collect[/] rig [cyan]{config.name}[/]: {episodes} episode(s) of {duration:g} s, "
        f"seeds {seed}..{seed + episodes - 1} → {args.data_root or config.recording.data_root}"
    )
    results = _run(config, episodes, seed, duration, args, "collect")
    summary = summarize(results)
    _print_episodes(results)
    _print_summary({"collected": summary})
    _write_json(
        args.json,
        {"rig": config.name, "seed": seed, "episodes": _episodes_json(results), "summary": summary.to_json()},
    )
    return 0


def _cmd_eval(args: argparse.Namespace) -> int:
    from telerig.runtime.evaluation import compare_paired, summarize

    if args.execute_actions is not None and args.execute_actions < 1:
        raise ConfigError(
            f"--execute-actions must be >= 1 (actions of each predicted chunk run before the policy is "
            f"asked again), got {args.execute_actions}"
        )
    ensemble = args.temporal_ensemble
    if ensemble is not None and not (math.isfinite(ensemble) and 0 < ensemble <= 10):
        raise ConfigError(
            f"--temporal-ensemble must be a weight decay in (0, 10] per tick (ACT: 0.01), got {ensemble}"
        )
    if ensemble is not None and (args.execute_actions or 1) != 1:
        raise ConfigError(
            "--temporal-ensemble asks the policy every tick: leave out --execute-actions "
            f"({args.execute_actions}) or the ensemble"
        )
    config, episodes, seed, duration = _prepare(args, held_out=True)
    runs: dict[str, list[TaskEpisode]] = {}
    checkpoints = [args.policy] + ([args.compare] if args.compare is not None else [])
    for checkpoint in checkpoints:
        if not Path(checkpoint).is_file():
            raise ConfigError(f"--policy/--compare {checkpoint}: no such checkpoint file")
    for checkpoint in checkpoints:
        rig = policy_rig(
            config,
            Path(checkpoint),
            checkpoint_spec(Path(checkpoint)),
            execute_actions=args.execute_actions,
            temporal_ensemble=ensemble,
        )
        console.print(
            f"[bold]telerig eval[/] [cyan]{checkpoint}[/] on rig [cyan]{config.name}[/]: "
            f"{episodes} episode(s) of {duration:g} s, held-out seeds {seed}..{seed + episodes - 1}"
        )
        runs[str(checkpoint)] = _run(rig, episodes, seed, duration, args, Path(checkpoint).name)
    summaries = {name: summarize(r) for name, r in runs.items()}
    for r in runs.values():
        _print_episodes(r)
    _print_summary(summaries)
    comparison = None
    if args.compare is not None:
        a, b = runs.values()
        comparison = compare_paired(a, b)
        _print_comparison(str(args.policy), str(args.compare), comparison)
    _write_json(
        args.json,
        {
            "rig": config.name,
            "seed": seed,
            "runs": {
                name: {"episodes": _episodes_json(r), "summary": summaries[name].to_json()}
                for name, r in runs.items()
            },
            "comparison": None if comparison is None else comparison.to_json(),
        },
    )
    return 0


def checkpoint_spec(checkpoint: Path) -> dict[str, Any]:
    """The checkpoint's cameras, image size (H, W) and fps, read in a child process so torch never
    enters the control process (as the policy device's own inference process does).

    Raises:
        ConfigError: one line when the checkpoint cannot be read.
    """
    code = (
        "import json, sys\n"
        "from telerig.policy.runner import load_policy\n"
        "s = load_policy(sys.argv[1]).spec\n"
        "print(json.dumps({'camera_keys': list(s.camera_keys), 'image_size': list(s.image_size), "
        "'fps': s.fps, 'id': s.checkpoint_id}))\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code, str(checkpoint)],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    if proc.returncode != 0:
        lines = [line for line in proc.stderr.splitlines() if line.strip()]
        raise ConfigError(f"checkpoint {checkpoint}: {lines[-1] if lines else 'cannot be read'}")
    spec: dict[str, Any] = json.loads(proc.stdout.strip().splitlines()[-1])
    return spec


def _acting(execute_actions: int | None, temporal_ensemble: float | None) -> dict[str, Any]:
    """The policy device settings ``eval`` overrides: how it sends each chunk's actions."""
    acting: dict[str, Any] = {}
    if temporal_ensemble is not None:
        acting = {"temporal_ensemble": temporal_ensemble, "execute_actions": 1}
    if execute_actions is not None:
        acting["execute_actions"] = execute_actions
    return acting


def policy_rig(
    config: RigConfig,
    checkpoint: Path,
    spec: dict[str, Any] | None = None,
    *,
    execute_actions: int | None = None,
    temporal_ensemble: float | None = None,
) -> RigConfig:
    """The rig with ``checkpoint`` as its policy: every ``policy`` device gets it; a rig without
    one gets a policy device bound to the task robot's arm and gripper (``joint_passthrough``,
    ``joint_gripper``) in place of the devices that drove them, and the cameras the checkpoint
    reads publish observations at its image size and rate (``spec``: :func:`checkpoint_spec`).
    ``execute_actions`` (when set) is every policy device's actions per predicted chunk;
    ``temporal_ensemble`` (when set) turns on every policy device's temporal ensembling (and sets
    ``execute_actions`` to 1).

    Raises:
        ConfigError: the rig has no task robot, the checkpoint needs a camera the rig lacks, or the
            policy binding's retargeters are not in this telerig.
    """
    from telerig.config.schema import RigConfig
    from telerig.registry import RETARGETERS
    from telerig.runtime.task import task_robots

    data = config.model_dump(mode="python")
    policies = [d for d in data["devices"] if d.get("type") == _POLICY]
    if policies:
        for device in policies:
            device["checkpoint"] = checkpoint
            device.update(_acting(execute_actions, temporal_ensemble))
        return _validated(RigConfig, data, config.name)
    robots = task_robots(config)
    if not robots:
        raise ConfigError(f"rig {config.name!r} has no task robot to evaluate on (type mujoco_pick_place)")
    robot = robots[0]
    missing = [t for t in ("joint_passthrough", "joint_gripper") if t not in RETARGETERS.names()]
    if missing:
        raise ConfigError(
            f"rig {config.name!r} binds no policy device and this telerig has no {', '.join(missing)} "
            "retargeter to bind one: add a device of type policy bound to the arm to the rig"
        )
    spec = spec or {"camera_keys": [], "image_size": [96, 96], "fps": 15.0}
    height, width = (int(v) for v in spec["image_size"])
    cameras = {c["id"]: c for c in data["cameras"]}
    for key in spec["camera_keys"]:
        camera = cameras.get(str(key).rsplit(".", 1)[-1])
        if camera is None:
            raise ConfigError(
                f"checkpoint camera {key!r} has no camera in rig {config.name!r} "
                f"(cameras: {', '.join(cameras) or 'none'})"
            )
        rate = min(float(spec["fps"]), float(camera.get("fps", 30.0)))
        camera["observation"] = {"width": width, "height": height, "rate_hz": rate}
    driving = {
        b["device"] for b in data["bindings"] if b["robot"] == robot and b["target"] in ("arm", "gripper")
    }
    data["devices"] = [d for d in data["devices"] if d["id"] not in driving]
    data["bindings"] = [b for b in data["bindings"] if b["device"] not in driving]
    data["devices"].append(
        {
            "id": _POLICY,
            "type": _POLICY,
            "checkpoint": checkpoint,
            "robot": robot,
            "rate_hz": float(spec["fps"]),
            **_acting(execute_actions, temporal_ensemble),
        }
    )
    data["bindings"] += [
        {
            "device": _POLICY,
            "part": "joints",
            "robot": robot,
            "target": "arm",
            "retargeter": {"type": "joint_passthrough"},
        },
        {
            "device": _POLICY,
            "part": "joints",
            "robot": robot,
            "target": "gripper",
            "retargeter": {"type": "joint_gripper"},
        },
    ]
    if data.get("episode_control") and data["episode_control"].get("device") in driving:
        data["episode_control"] = None
    data["recording"]["operator"] = _POLICY
    return _validated(RigConfig, data, config.name)


def _validated(model: type[RigConfig], data: dict[str, Any], name: str) -> RigConfig:
    try:
        return model.model_validate(data)
    except ValueError as exc:
        first = str(exc).strip().splitlines()
        raise ConfigError(f"binding a policy to rig {name!r}: {' '.join(first[:3])}") from None


def _episodes_json(results: Sequence[TaskEpisode]) -> list[dict[str, object]]:
    return [
        {
            "episode_id": e.episode_id,
            "status": e.status,
            "seed": e.seed,
            "success": e.success,
            "time_to_success_s": e.time_to_success_s,
            "reason": e.reason,
            "gates": e.gates,
        }
        for e in results
    ]


def _write_json(path: Path | None, data: dict[str, object]) -> None:
    if path is None:
        return
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(data, indent=2, default=str))
    except OSError as exc:
        raise TelerigError(f"--json {path}: cannot write: {exc}") from None
    console.print(f"results → {path}")


def _print_episodes(results: Sequence[TaskEpisode]) -> None:
    table = Table(title="episodes")
    for col in ("episode", "seed", "status", "outcome", "time to success s", "gates", "why"):
        table.add_column(col)
    for e in results:
        table.add_row(
            e.episode_id,
            str(e.seed),
            e.status,
            "[green]success[/]" if e.success else "[yellow]failure[/]",
            "-" if e.time_to_success_s is None else f"{e.time_to_success_s:.1f}",
            e.gates or "-",
            e.reason,
        )
    console.print(table)


def _print_summary(summaries: dict[str, TaskSummary]) -> None:
    table = Table(title="success measured from the scene")
    for col in ("run", "episodes", "successes", "rate", "Wilson 95 %", "mean time to success s", "gates"):
        table.add_column(col)
    for name, s in summaries.items():
        lo, hi = s.interval
        table.add_row(
            name,
            str(s.episodes),
            str(s.successes),
            "-" if math.isnan(s.rate) else f"{s.rate:.1%}",
            f"[{lo:.1%}, {hi:.1%}]",
            "-" if math.isnan(s.mean_time_to_success_s) else f"{s.mean_time_to_success_s:.1f}",
            ", ".join(f"{k}: {v}" for k, v in sorted(s.gates.items())),
        )
    console.print(table)


def _print_comparison(a: str, b: str, c: PairedComparison) -> None:
    verdict = "[bold]significant[/]" if c.significant else "not significant"
    console.print(
        f"paired on {c.pairs} seeds: both {c.both}, only {a} {c.only_a}, only {b} {c.only_b}, neither "
        f"{c.neither}; McNemar exact p = {c.p_value:.4f}: {verdict} at {c.alpha:g}",
        highlight=False,
    )
