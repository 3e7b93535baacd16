"""Benchmark: the G1 upper-body IK per solve against mink.solve_ik on the same QP; prints a table + JSON.

Input: the shipped BVH clip's skeletons (``sample_bvh_path``), turned into wrist/elbow/waist
targets by the retargeter, solved at 60 Hz (the mocap rigs' control rate) with one QP sub-step,
each solve from the previous solution as in the control loop.

Baseline, same run: ``HumanoidMinkReference``, the same tasks with mink's ``ConfigurationLimit``
and ``VelocityLimit`` solved through ``mink.solve_ik`` (what HumanoidIK ran until it built the box
QP itself), interleaved solve by solve so host noise hits both alike; the ratio is the median of
the per-solve ratios. The clip is played ``--passes`` times.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from telerig.devices.mocap.fake import sample_bvh_path
from telerig.retarget.humanoid import HumanoidIK, HumanoidMinkReference, HumanoidRetargeter
from telerig.retarget.offline import load_skeletons

DT = 1 / 60


def bench(passes: int) -> dict[str, float]:
    ik = HumanoidIK()
    reference = HumanoidMinkReference()
    retargeter = HumanoidRetargeter(ik)
    targets = [retargeter.targets(s) for s in load_skeletons(sample_bvh_path())] * passes
    q_ik = q_mink = np.array(ik.home)
    ours, theirs, errors = np.empty(len(targets)), np.empty(len(targets)), np.empty(len(targets))
    apart = 0.0
    for k, target in enumerate(targets):
        t0 = time.perf_counter()
        result = ik.solve(target, q_ik, DT)
        t1 = time.perf_counter()
        q_mink = reference.solve(target, q_mink, DT).q
        t2 = time.perf_counter()
        q_ik = result.q
        ours[k], theirs[k], errors[k] = t1 - t0, t2 - t1, float(np.max(result.wrist_errors))
        apart = max(apart, float(np.max(np.abs(q_ik - q_mink))))
    return {
        "solves": len(targets),
        "median_us": float(np.median(ours) * 1e6),
        "p99_us": float(np.percentile(ours, 99) * 1e6),
        "mink_median_us": float(np.median(theirs) * 1e6),
        "mink_p99_us": float(np.percentile(theirs, 99) * 1e6),
        "ratio": float(np.median(ours / theirs)),
        "wrist_error_mean_mm": float(errors.mean() * 1e3),
        "max_joint_difference_rad": apart,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--passes", type=int, default=3)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/humanoid_ik.json"))
    args = parser.parse_args()
    console = Console(width=120)
    console.print(f"solving the shipped clip {args.passes} times, interleaved with mink.solve_ik ...")
    r = bench(args.passes)
    table = Table(title=f"G1 upper-body IK per solve, 1 sub-step at 60 Hz ({r['solves']} solves)")
    for col in ("solver", "median µs", "p99 µs"):
        table.add_column(col, justify="right")
    table.add_row("HumanoidIK (box QP, DAQP)", f"{r['median_us']:.0f}", f"{r['p99_us']:.0f}")
    table.add_row("mink.solve_ik (same QP)", f"{r['mink_median_us']:.0f}", f"{r['mink_p99_us']:.0f}")
    console.print(table)
    console.print(
        f"HumanoidIK against mink.solve_ik (interleaved): {r['ratio']:.2f}x the time; joints apart at "
        f"most {r['max_joint_difference_rad']:.1e} rad; "
        f"mean worst-wrist error {r['wrist_error_mean_mm']:.1f} mm"
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"benchmark": "humanoid_ik", "results": r}, indent=2))
    console.print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
