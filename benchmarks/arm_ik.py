"""Benchmark: arm IK per solve and MuJoCo physics per step for the demo UR5e; prints a table + JSON.

IK tracks a 0.5 Hz circle of 10 cm radius around the home pose at 100 Hz, so each
solve starts from the previous solution like in the control loop. Rows for 1, 2
and 3 QP sub-steps per solve show the cost/accuracy trade (rigs default to 1).

Baseline, same run: the same QP built by mink's tasks and limits and solved through
``mink.solve_ik`` (``MinkReference``, what ArmIK used until it built the box QP itself),
one sub-step per solve, interleaved solve by solve with ArmIK's; the ratio is the median of
the per-solve ratios (both compute the residual they report).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from telerig.retarget.arm_ik import ArmIK, MinkReference
from telerig.robots.sim.scene import build_arm_scene

sys.path.insert(0, str(Path(__file__).parent))
from sim_physics import bare_step_us

DT = 0.01


def bench_ik(iterations: int, solves: int) -> dict[str, float]:
    scene = build_arm_scene()
    ik = ArmIK(scene, iterations=iterations)
    home_p, home_q = ik.forward(scene.home)
    q = scene.home.copy()
    times = np.empty(solves)
    errors = np.empty(solves)
    for k in range(solves):
        angle = 2 * np.pi * 0.5 * k * DT
        target = home_p + 0.1 * np.array([np.cos(angle) - 1.0, np.sin(angle), 0.0])
        t0 = time.perf_counter()
        result = ik.solve(target, home_q, q, DT)
        times[k] = time.perf_counter() - t0
        errors[k] = result.position_error
        q = result.q
    return {
        "iterations": iterations,
        "median_us": float(np.median(times) * 1e6),
        "p99_us": float(np.percentile(times, 99) * 1e6),
        "tracking_error_mean_mm": float(errors[solves // 10 :].mean() * 1e3),
    }


def bench_against_mink(solves: int) -> dict[str, float]:
    """ArmIK (1 sub-step) and the baseline, one mink ``solve_ik`` step, interleaved solve by solve
    along the same circle (each from its own previous solution): host noise hits both alike."""
    scene = build_arm_scene()
    ik = ArmIK(scene, iterations=1)
    reference = MinkReference(ik)
    home_p, home_q = ik.forward(scene.home)
    q_ik = q_mink = scene.home.copy()
    ours, theirs = np.empty(solves), np.empty(solves)
    for k in range(solves):
        angle = 2 * np.pi * 0.5 * k * DT
        target = home_p + 0.1 * np.array([np.cos(angle) - 1.0, np.sin(angle), 0.0])
        t0 = time.perf_counter()
        q_ik = ik.solve(target, home_q, q_ik, DT).q
        t1 = time.perf_counter()
        q_mink = reference.solve(target, home_q, q_mink, DT).q
        t2 = time.perf_counter()
        ours[k], theirs[k] = t1 - t0, t2 - t1
    return {
        "armik_median_us": float(np.median(ours) * 1e6),
        "median_us": float(np.median(theirs) * 1e6),
        "p99_us": float(np.percentile(theirs, 99) * 1e6),
        "ratio": float(np.median(ours / theirs)),
        "max_joint_difference_rad": float(np.max(np.abs(q_ik - q_mink))),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--solves", type=int, default=1000)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/arm_ik.json"))
    args = parser.parse_args()
    rows = [bench_ik(n, args.solves) for n in (1, 2, 3)]
    baseline = bench_against_mink(args.solves)
    ratio = baseline["ratio"]
    step_us = bare_step_us(build_arm_scene().model, 5000)
    table = Table(title="UR5e arm IK per solve (box QP, DAQP), 100 Hz circle tracking")
    for col in ("QP sub-steps", "median µs", "p99 µs", "mean tracking error mm"):
        table.add_column(col, justify="right")
    for r in rows:
        table.add_row(
            str(r["iterations"]),
            f"{r['median_us']:.0f}",
            f"{r['p99_us']:.0f}",
            f"{r['tracking_error_mean_mm']:.2f}",
        )
    table.add_row("mink.solve_ik, 1", f"{baseline['median_us']:.0f}", f"{baseline['p99_us']:.0f}", "")
    console = Console(width=120)
    console.print(table)
    console.print(
        f"1 sub-step against mink.solve_ik's (same QP, interleaved): {ratio:.2f}x the time "
        f"(medians {baseline['armik_median_us']:.0f} / {baseline['median_us']:.0f} µs; joints apart "
        f"{baseline['max_joint_difference_rad']:.1e} rad after {args.solves} solves)"
    )
    console.print(f"MuJoCo step (UR5e + Robotiq + cube, 2 ms): {step_us:.1f} µs → max {1e6 / step_us:.0f} Hz")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(
        json.dumps(
            {
                "benchmark": "arm_ik",
                "ik": rows,
                "mink_solve_ik": baseline,
                "ratio_to_mink": ratio,
                "physics_step_us": step_us,
            },
            indent=2,
        )
    )
    console.print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
