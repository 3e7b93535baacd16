"""Benchmark: CPU per simulated physics step against the steps the physics thread takes per wake-up.

Runs ``SimPhysics`` in real time (its own thread, as a rig runs it) on the shipped scenes of the
fleet rig's arm kinds for ``--seconds`` at 1, 2, 5 and 10 steps per wake-up, and reports the thread's
CPU per step against one step per wake-up measured in the same run (``time.thread_time`` would
need the thread's own clock: the process CPU is used, the main thread only sleeps). On a virtual
machine a wake-up (timer, context switch) costs about what a step of a 6-DoF arm scene costs.

Usage: python benchmarks/sim_physics.py [--seconds 4] [--out benchmarks/results/sim_physics.json]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import mujoco
from rich.console import Console
from rich.table import Table

from telerig.robots.sim.arm import SimPhysics
from telerig.robots.sim.gripper import build_gripper_scene
from telerig.robots.sim.scene import build_arm_scene

PACINGS = (1, 2, 5, 10)


def measure(model: mujoco.MjModel, steps_per_wake: int, seconds: float) -> dict[str, float]:
    """CPU per step [us], steps per second and the realtime factor of ``seconds`` of real-time physics."""
    physics = SimPhysics(model, name="bench", steps_per_wake=steps_per_wake)
    physics.acquire()
    try:
        time.sleep(0.5)  # past start-up
        before, cpu0, wall0 = physics.stats(), time.process_time(), time.monotonic()
        time.sleep(seconds)
        after, cpu1, wall1 = physics.stats(), time.process_time(), time.monotonic()
    finally:
        physics.release()
    steps = after.steps - before.steps
    return {
        "steps_per_wake": steps_per_wake,
        "cpu_per_step_us": (cpu1 - cpu0) / max(steps, 1) * 1e6,
        "steps_per_s": steps / (wall1 - wall0),
        "cores": (cpu1 - cpu0) / (wall1 - wall0),
    }


def bare_step_us(model: mujoco.MjModel, steps: int = 2000) -> float:
    """``mj_step`` alone, back to back on this thread [us]."""
    data = mujoco.MjData(model)
    start = time.perf_counter()
    for _ in range(steps):
        mujoco.mj_step(model, data)
    return (time.perf_counter() - start) / steps * 1e6


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=4.0)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/sim_physics.json"))
    args = parser.parse_args()
    scenes = {
        "UR5e + Robotiq (500 Hz)": build_arm_scene().model,
        "Robotiq 2F-85 alone (500 Hz)": build_gripper_scene().model,
    }
    console = Console(width=120)
    table = Table(title="Real-time physics thread: CPU per step by steps per wake-up")
    for col in (
        "scene",
        "mj_step alone µs",
        "steps / wake",
        "CPU / step µs",
        "vs 1 / wake",
        "steps/s",
        "cores",
    ):
        table.add_column(col, justify="right")
    results = []
    for name, model in scenes.items():
        bare = bare_step_us(model)
        rows = [measure(model, k, args.seconds) for k in PACINGS]
        base = rows[0]["cpu_per_step_us"]
        for row in rows:
            row["ratio_to_one_per_wake"] = row["cpu_per_step_us"] / base
            table.add_row(
                name,
                f"{bare:.0f}",
                str(row["steps_per_wake"]),
                f"{row['cpu_per_step_us']:.0f}",
                f"{row['ratio_to_one_per_wake']:.2f}",
                f"{row['steps_per_s']:.0f}",
                f"{row['cores']:.3f}",
            )
        results.append({"scene": name, "mj_step_us": bare, "pacings": rows})
    console.print(table)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(
        json.dumps({"benchmark": "sim_physics", "seconds": args.seconds, "scenes": results}, indent=2)
    )
    console.print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
