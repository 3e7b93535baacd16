"""Benchmark: the whole-body QP in the live tiago_wbc rig at 100 Hz and 1 kHz, and the same ticks alone.

Runs the shipped ``tiago_wbc`` rig (scripted SpaceMouse → embedded Mosquitto → control node: the
TIAGo whole-body controller, safety chain → MuJoCo driver; the 640x480@30 scene camera rendering and
encoding beside it, every stream recorded) for one episode per configuration: at the rig's 100 Hz
and with the device, the control loop and physics raised to 1 kHz (one QP per control tick when
the loop keeps up), each

* ``threads``: every node in this process, as the rig file ships it;
* ``processes``: the robot, its control loop, device and camera in a process of its own under
  ``SCHED_RR`` (``RigConfig.with_isolation("processes", 10)``, as the demo rig runs).

Each tick's controller time (kinematics, Jacobians, building and solving the QP) is the residual's
``solve_s``, read back from the episode, with how many ticks the loop and the device really made.
The baseline, measured in the same run: the recorded actions replayed through a fresh
``WholeBodyController`` in a closed loop in this process, with nothing else running (the
"standalone" time of issue 18). Target (issue 18): p99 <= 1 ms in the live rig at 1 kHz.

Usage: python benchmarks/wbc_rig.py [--duration 10] [--rates 100 1000] [--out benchmarks/results/wbc_rig.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

os.environ.setdefault("MUJOCO_GL", "osmesa")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])

from rich.console import Console
from rich.table import Table

from telerig.config import load_rig
from telerig.config.schema import RigConfig
from telerig.ir.mcap_log import read_residuals
from telerig.retarget.wbc import WholeBodyController
from telerig.retarget.whole_body import ACTION_KEYS
from telerig.robots.models.tiago import TIAGO_HOME
from telerig.runtime.process_settings import control_process
from telerig.runtime.rig import RigRuntime

sys.path.insert(0, str(Path(__file__).parent))
from host_steal import StealMeter, steal_text

TARGET_RATE_HZ = 1000.0
TARGET_P99_MS = 1.0
REALTIME_PRIORITY = 10
Isolation = Literal["threads", "processes"]


def rig_at(rate_hz: float, isolation: Isolation) -> RigConfig:
    """The shipped tiago_wbc rig with its device and control loop at ``rate_hz``, physics at least as fast."""
    rig = load_rig("tiago_wbc")
    data = rig.model_dump(mode="json", exclude_unset=True)
    for device in data["devices"]:
        device["rate_hz"] = rate_hz
    for robot in data["robots"]:
        robot["control_rate_hz"] = rate_hz
        robot["physics_rate_hz"] = max(rate_hz, robot.get("physics_rate_hz", rate_hz))
    config = RigConfig.model_validate(data)
    if isolation == "processes":
        config = config.with_isolation("processes", REALTIME_PRIORITY)
    return config


def live(
    rate_hz: float, isolation: Isolation, duration_s: float
) -> tuple[dict[str, Any], npt.NDArray[np.float64]]:
    """One episode of the rig at ``rate_hz``; the statistics of its solve times and the actions it solved."""
    config = rig_at(rate_hz, isolation)
    with (
        tempfile.TemporaryDirectory() as tmp,
        control_process(realtime_priority=config.runtime.realtime_priority),
        RigRuntime(config, data_root=Path(tmp)) as runtime,
    ):
        with StealMeter() as steal:
            result = runtime.run_episode(duration_s)
        residuals = [r.metrics() for topic, r, _ in read_residuals(result.path / "episode.mcap")]
        frames = sum(result.camera_frames.values())
        latency = result.latency
        health = json.loads((result.path / "manifest.json").read_text())["extra"]["health"]["streams"]
    measured = {"/".join(topic.split("/")[-2:]): s["measured_hz"] for topic, s in health.items()}
    solve_ms = np.array([r["solve_s"] for r in residuals]) * 1e3
    actions = np.array([[r[k] for k in ACTION_KEYS] for r in residuals], dtype=np.float64)
    row = {
        "config": f"live rig {rate_hz:g} Hz, {isolation}",
        "rate_hz": rate_hz,
        "isolation": isolation,
        "solves": int(solve_ms.size),
        "solve_rate_hz": solve_ms.size / duration_s,
        "device_hz": measured.get("sm0/twist", 0.0),
        "loop_hz": measured.get("tiago0/joint_state", 0.0),
        **_stats(solve_ms),
        "latency_p50_ms": latency.p50_ms,
        "latency_p99_ms": latency.p99_ms,
        "camera_frames": frames,
        "steal_fraction": steal.fraction,
    }
    return row, actions


def standalone(actions: npt.NDArray[np.float64], rate_hz: float) -> dict[str, Any]:
    """The recorded actions through a fresh controller in a closed loop, one tick each, timed alone."""
    controller = WholeBodyController()
    q = np.array(TIAGO_HOME, dtype=np.float64)
    dt = 1.0 / rate_hz
    for action in actions[:200]:  # warm up caches and the allocator
        q = controller.step(action, q, dt).q
    controller.reset()
    q = np.array(TIAGO_HOME, dtype=np.float64)
    solve_ms = np.empty(len(actions))
    for k, action in enumerate(actions):
        t0 = time.perf_counter()
        q = controller.step(action, q, dt).q
        solve_ms[k] = (time.perf_counter() - t0) * 1e3
    return {
        "config": f"standalone, the {rate_hz:g} Hz run's actions",
        "rate_hz": rate_hz,
        "solves": int(solve_ms.size),
        **_stats(solve_ms),
    }


def _stats(ms: npt.NDArray[np.float64]) -> dict[str, float]:
    return {
        "p50_ms": float(np.median(ms)),
        "p99_ms": float(np.percentile(ms, 99)),
        "max_ms": float(ms.max()),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=10.0, help="seconds per live episode")
    parser.add_argument("--rates", type=float, nargs="+", default=[100.0, TARGET_RATE_HZ], help="[Hz]")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/wbc_rig.json"))
    args = parser.parse_args()
    if args.duration <= 0 or not all(0 < r <= 1000 for r in args.rates):
        parser.error("--duration must be > 0 and each rate in (0, 1000] Hz")
    console = Console(width=150)
    rows: list[dict[str, Any]] = []
    for rate_hz in args.rates:
        actions: npt.NDArray[np.float64] | None = None
        live_rows = []
        for isolation in ("threads", "processes"):
            with console.status(f"tiago_wbc at {rate_hz:g} Hz, {isolation}, {args.duration:g} s"):
                row, recorded = live(rate_hz, isolation, args.duration)
            live_rows.append(row)
            actions = recorded if actions is None else actions
        assert actions is not None
        with console.status(f"the {rate_hz:g} Hz actions standalone"):
            base = standalone(actions, rate_hz)
        for row in (*live_rows, base):
            row["p99_ratio"] = row["p99_ms"] / base["p99_ms"]
        rows += [*live_rows, base]

    table = Table(
        title="TIAGo whole-body controller tick in the live rig "
        f"(target: p99 <= {TARGET_P99_MS:g} ms at {TARGET_RATE_HZ:g} Hz)"
    )
    for col in (
        "configuration",
        "device / loop / solves Hz",
        "p50 ms",
        "p99 ms",
        "max ms",
        "p99 / alone",
        "latency p50/p99 ms",
        "frames",
        "steal",
    ):
        table.add_column(col, justify="left" if col == "configuration" else "right")
    for row in rows:
        is_live = "solve_rate_hz" in row
        table.add_row(
            row["config"],
            f"{row['device_hz']:.0f} / {row['loop_hz']:.0f} / {row['solve_rate_hz']:.0f}"
            if is_live
            else str(row["solves"]),
            f"{row['p50_ms']:.3f}",
            f"{row['p99_ms']:.3f}",
            f"{row['max_ms']:.2f}",
            f"{row['p99_ratio']:.2f}x",
            f"{row['latency_p50_ms']:.2f} / {row['latency_p99_ms']:.2f}" if is_live else "-",
            str(row["camera_frames"]) if is_live else "-",
            steal_text(row["steal_fraction"]) if is_live else "-",
        )
    console.print(table)
    for row in rows:
        if "solve_rate_hz" not in row or row["rate_hz"] != TARGET_RATE_HZ:
            continue
        kept_up = row["solve_rate_hz"] >= 0.95 * TARGET_RATE_HZ
        met = kept_up and row["p99_ms"] <= TARGET_P99_MS
        console.print(
            f"{row['config']}: p99 {row['p99_ms']:.3f} ms, {row['solve_rate_hz']:.0f} solves/s: "
            + (
                "[green]met[/]"
                if met
                else f"[red]not met[/] (target {TARGET_P99_MS:g} ms at {TARGET_RATE_HZ:g} solves/s)"
            )
        )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(
        json.dumps(
            {
                "benchmark": "wbc_rig",
                "host": {"cpus": os.cpu_count(), "python": platform.python_version()},
                "target_rate_hz": TARGET_RATE_HZ,
                "duration_s": args.duration,
                "target_p99_ms": TARGET_P99_MS,
                "results": rows,
            },
            indent=2,
        )
    )
    console.print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
