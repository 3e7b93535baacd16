"""Benchmark: µs per SafetyChain.step on the UR5e, workspace and self-collision checks off and on.

The request follows a 0.5 Hz motion of every joint around home at 100 Hz (past the start-up
ramp), with the measured state following the output, as in the control loop. ``refusing`` rows
push the tool into a keep-out zone for part of the cycle, so the guard refuses and brakes.
Collision checks run on the kinematic model's collision meshes (convex hulls), every tick.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from telerig.ir.types import JointCommand, JointState, Stamp
from telerig.robots.base import JointLimits
from telerig.robots.models.arm import ArmScene, build_arm_kinematics
from telerig.safety import (
    Box,
    ConfigurationCheck,
    ConfigurationGuard,
    KinematicsModel,
    SafetyChain,
    SelfCollision,
    Sphere,
    WorkspaceBounds,
)

PERIOD_NS = 10_000_000
WARMUP = 400


def limits_of(scene: ArmScene) -> JointLimits:
    m = scene.model
    ids = [m.joint(j).id for j in scene.arm_joints]
    return JointLimits(
        scene.arm_joints, m.jnt_range[ids, 0], m.jnt_range[ids, 1], np.full(6, np.pi), np.full(6, 8.0)
    )


def build_chain(scene: ArmScene, workspace: bool, collision: bool, refusing: bool) -> SafetyChain:
    kin = KinematicsModel(scene.model, scene.arm_joints, base_body=scene.base_body)
    checks: list[ConfigurationCheck] = []
    if workspace:
        tool = WorkspaceBounds(kin, [scene.ee_site], keep_out=[Sphere([0, 0, 0], 0.1)]).points(scene.home)[0]
        zone = (
            Sphere(tool + np.array([0.12, 0.0, 0.0]), 0.1, "fixture")
            if refusing
            else Sphere([0, 0, 0.3], 0.12, "column")
        )
        points = [scene.ee_site, "wrist_2_link"]
        checks.append(
            WorkspaceBounds(kin, points, box=Box([-0.9, -0.9, 0.05], [0.9, 0.9, 1.2]), keep_out=[zone])
        )
    if collision:
        checks.append(SelfCollision(kin, allowed=[scene.home], margin_m=0.005))
    guard = ConfigurationGuard(checks) if checks else None
    return SafetyChain.default(limits_of(scene), guard=guard, ramp_duration_s=1.0)


def bench(
    scene: ArmScene, ticks: int, *, workspace: bool, collision: bool, refusing: bool
) -> dict[str, object]:
    chain = build_chain(scene, workspace, collision, refusing)
    names = scene.arm_joints
    t0 = time.time_ns()
    phases = np.linspace(0.0, 1.0, 6)
    requests = []
    for k in range(ticks + WARMUP):
        t = t0 + k * PERIOD_NS
        q = scene.home + 0.25 * np.sin(2.0 * np.pi * 0.5 * k * 0.01 + phases)
        requests.append(JointCommand(Stamp("retarget", k, t, t), names, q))
    q_meas = scene.home.copy()
    times = np.empty(ticks)
    refused = 0
    for k in range(ticks + WARMUP):
        measured = JointState(Stamp("robot", k, t0, t0), names, q_meas, np.zeros(6))
        start = time.perf_counter()
        out = chain.step(requests[k], now_ns=t0 + k * PERIOD_NS, measured=measured)
        elapsed = time.perf_counter() - start
        if k >= WARMUP:
            times[k - WARMUP] = elapsed
            refused += any(e.code in ("workspace", "self_collision") for e in out.events)
        if out.command is not None:
            q_meas = out.command.positions
    return {
        "workspace": workspace,
        "self_collision": collision,
        "mode": "refusing" if refusing else "tracking",
        "median_us": float(np.median(times) * 1e6),
        "p99_us": float(np.percentile(times, 99) * 1e6),
        "mean_us": float(times.mean() * 1e6),
        "guarded_ticks": refused,
        "ticks": ticks,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ticks", type=int, default=5000)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/safety_chain.json"))
    args = parser.parse_args()
    scene = build_arm_kinematics()
    cases = [
        (False, False, False),
        (True, False, False),
        (False, True, False),
        (True, True, False),
        (True, True, True),
    ]
    rows = [bench(scene, args.ticks, workspace=w, collision=c, refusing=r) for w, c, r in cases]
    table = Table(title="SafetyChain.step on the UR5e (6 joints), 100 Hz, per tick")
    for col in ("workspace", "self-collision", "mode", "median µs", "p99 µs", "guarded ticks"):
        table.add_column(col, justify="right")
    for r in rows:
        table.add_row(
            "on" if r["workspace"] else "off",
            "on" if r["self_collision"] else "off",
            str(r["mode"]),
            f"{r['median_us']:.0f}",
            f"{r['p99_us']:.0f}",
            f"{r['guarded_ticks']}/{r['ticks']}",
        )
    console = Console(width=120)
    console.print(table)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"benchmark": "safety_chain", "robot": "ur5e", "rows": rows}, indent=2))
    console.print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
