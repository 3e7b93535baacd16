"""Benchmark: do the quality gates run after each commit hurt the recording of the next episode?

The demo rig (scripted VR operator, simulated UR5e, MuJoCo scene camera) records N episodes in a
row, in one station, as ``telerig run`` does; episode k+1 records while the gate process
(:mod:`telerig.runtime.qa_worker`) may check episode k. Three configs, alternating:

* ``gates SCHED_IDLE``: the default (``qa.while_recording: idle``): the gate process runs on, on
  CPU time nothing else wants;
* ``gates paused``: ``qa.while_recording: pause``: it is stopped while an episode records;
* ``gates off``: ``qa.after_commit: false``.

The episodes that recorded while gates could run (2..N) are compared: input-to-actuation latency
(p50, p99, max), robot states recorded per second, camera frames; and how far the gates fell
behind: the most episodes waiting for a verdict at any episode's end (the one just committed
included), and the delay from commit to verdict. Also measured: gate + score time per
episode-minute, with the station idle (in this process, not niced).

On a shared 2-core host every number moves with the neighbours' load: compare the two configs
within a trial (they alternate), and look at several trials.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time
from concurrent.futures import Future
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.table import Table

from telerig.config import load_rig
from telerig.config.qa import QaThresholds
from telerig.config.schema import RigConfig
from telerig.qa.checker import QaOutcome, check_episode
from telerig.runtime.process_settings import control_process
from telerig.runtime.rig import RigRuntime
from telerig.store.episodes import EpisodeStore


def _record(rig: RigConfig, root: Path, episodes: int, duration_s: float) -> dict[str, Any]:
    rows: list[dict[str, float]] = []
    verdict_delay_s: list[float] = []
    pending: list[int] = []
    with (
        control_process(realtime_priority=rig.runtime.realtime_priority),
        RigRuntime(rig, data_root=root) as rt,
    ):
        for _ in range(episodes):
            result = rt.run_episode(duration_s)
            committed = time.monotonic()
            future: Future[QaOutcome] | None = rt.storage.qa_checks.get(result.episode_id)
            if future is not None:

                def done(_: Future[QaOutcome], t0: float = committed) -> None:
                    verdict_delay_s.append(time.monotonic() - t0)

                future.add_done_callback(done)
            pending.append(sum(not f.done() for f in rt.storage.qa_checks.values()))
            states = next(s for s in result.streams if s.name.endswith("arm0/joint_state"))
            rows.append(
                {
                    "p50_ms": result.latency.p50_ms,
                    "p99_ms": result.latency.p99_ms,
                    "max_ms": result.latency.max_ms,
                    "state_hz": states.measured_hz,
                    "frames": float(sum(result.camera_frames.values())),
                }
            )
        for future in list(rt.storage.qa_checks.values()):
            future.result(600)
    later = rows[1:]  # recorded while the previous episode's gates could run
    return {
        **{k: statistics.median(r[k] for r in later) for k in later[0]},
        "verdict_delay_s": statistics.median(verdict_delay_s) if verdict_delay_s else None,
        "max_pending": float(max(pending)) if rig.qa.after_commit else None,
    }


def _gate_time(root: Path) -> dict[str, float]:
    """Gates + score on each recorded episode in this process: seconds per episode-minute."""
    store = EpisodeStore(root)
    per_minute: list[float] = []
    for summary in store.list(include_failures=True):
        t0 = time.perf_counter()
        check_episode(store, summary.id, QaThresholds())
        seconds = time.perf_counter() - t0
        per_minute.append(seconds / ((summary.duration_s or 1.0) / 60.0))
    return {"gate_s_per_episode_min": statistics.median(per_minute)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=3)
    parser.add_argument("--duration", type=float, default=6.0, help="seconds per episode")
    parser.add_argument("--trials", type=int, default=1)
    parser.add_argument("--json", type=Path, default=None, help="write the results here")
    args = parser.parse_args()
    if args.episodes < 2 or args.trials < 1 or args.duration <= 0:
        parser.error(
            "--episodes must be >= 2 (episode 1 records before any gates run; 2..N are compared), "
            "--trials >= 1 and --duration > 0"
        )
    os.environ.setdefault("MUJOCO_GL", "osmesa")
    os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
    demo = load_rig("demo")
    configs = {
        "gates SCHED_IDLE": demo.model_copy(update={"qa": QaThresholds(while_recording="idle")}),
        "gates paused": demo.model_copy(update={"qa": QaThresholds(while_recording="pause")}),
        "gates off": demo.model_copy(update={"qa": QaThresholds(after_commit=False)}),
    }
    results: dict[str, list[dict[str, Any]]] = {name: [] for name in configs}
    gate_times: list[dict[str, float]] = []
    with tempfile.TemporaryDirectory(prefix="telerig-qa-bench-") as tmp:
        for trial in range(args.trials):
            order = list(configs) if trial % 2 == 0 else list(configs)[::-1]
            for name in order:
                root = Path(tmp) / f"{trial}-{name.replace(' ', '_')}"
                results[name].append(_record(configs[name], root, args.episodes, args.duration))
                if name == "gates off":
                    gate_times.append(_gate_time(root))
    table = Table(title=f"episodes 2..{args.episodes} of {args.duration:g} s (median over trials)")
    columns = ("config", "p50 ms", "p99 ms", "max ms", "joint_state Hz", "camera frames", "verdict after s",
               "most waiting")  # fmt: skip
    for col in columns:
        table.add_column(col, justify="right" if col != "config" else "left")
    summary: dict[str, Any] = {"episodes": args.episodes, "duration_s": args.duration, "trials": args.trials}
    for name, trials in results.items():
        med = {k: statistics.median(t[k] for t in trials if t[k] is not None) if any(
            t[k] is not None for t in trials) else None for k in trials[0]}  # fmt: skip
        summary[name] = {"median": med, "trials": trials}
        delay, waiting = med["verdict_delay_s"], med["max_pending"]
        table.add_row(
            name, f"{med['p50_ms']:.2f}", f"{med['p99_ms']:.2f}", f"{med['max_ms']:.2f}",
            f"{med['state_hz']:.1f}", f"{med['frames']:.0f}", "-" if delay is None else f"{delay:.1f}",
            "-" if waiting is None else f"{waiting:.0f}",
        )  # fmt: skip
    gate = statistics.median(g["gate_s_per_episode_min"] for g in gate_times)
    summary["gate_s_per_episode_min"] = gate
    console = Console(width=130)
    console.print(table)
    console.print(f"gates + score, station idle: {gate:.1f} s per episode-minute")
    if args.json is not None:
        args.json.write_text(json.dumps(summary, indent=2))


if __name__ == "__main__":
    main()
