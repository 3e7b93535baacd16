"""Plan-preview-execute (issue 17): what a plan costs, and why it runs on a worker, not on the tick.

For TIAGo reach targets at several distances (arm only, base 0.3-1.3 m away), from home:

* the baseline: :class:`MobileReachPlanner` alone (mink IK, arm first, then with the base joints);
* a whole plan as the aid makes it: planner plus the kinematic dry run of the executor whose samples
  are the preview paths (``ReachPlanAid`` on its worker thread, command to ``staged``);
* one control tick's share while a plan executes (``ReachPlanAid.action`` + ``WholeBodyController.step``).

A control period is 10 ms: anything near it cannot run in the command handler on the control thread.

Usage: python benchmarks/reach_plan.py [--repeats 5] [--out benchmarks/results/reach_plan.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import mujoco
import numpy as np
from rich.console import Console
from rich.table import Table

from telerig.retarget.mobile_reach import MobileReachPlanner
from telerig.retarget.reach_plan import ReachPlanAid
from telerig.retarget.wbc import WholeBodyController
from telerig.robots.models.tiago import build_tiago_kinematics

TARGETS = {
    "arm only": (0.75, -0.25, 0.95),
    "base 0.35 m": (1.0, -0.2, 1.0),
    "base 0.75 m": (1.4, -0.3, 0.9),
    "base 1.3 m": (2.0, 1.0, 0.7),
}


def _ms(samples: list[float]) -> dict[str, float]:
    return {"median_ms": float(np.median(samples)) * 1e3, "max_ms": float(np.max(samples)) * 1e3}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/reach_plan.json"))
    args = parser.parse_args()
    scene = build_tiago_kinematics()
    data = mujoco.MjData(scene.model)
    data.qpos[:] = scene.home
    mujoco.mj_kinematics(scene.model, data)
    hand = np.empty(4)
    mujoco.mju_mat2Quat(hand, data.site_xmat[scene.model.site(scene.ee_site).id])
    planner = MobileReachPlanner(scene)
    rows = []
    for name, target in TARGETS.items():
        alone = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            plan = planner.plan(target, hand, scene.home)
            alone.append(time.perf_counter() - t0)
        whole, ticks, points = [], [], 0
        for _ in range(args.repeats):
            wbc = WholeBodyController(scene)
            aid = ReachPlanAid(wbc, planner)
            aid.observe(scene.home.copy())
            t0 = time.perf_counter()
            aid.command("plan " + " ".join(map(str, target)))
            aid.join(60.0)
            whole.append(time.perf_counter() - t0)
            state = aid.state()
            assert state["status"] == "staged", state["reason"]
            points = len(state["ee_path"])  # type: ignore[arg-type]
            aid.command(f"execute {state['id']}")
            q = scene.home.copy()
            for _ in range(200):
                t1 = time.perf_counter()
                action = aid.action(q, 0.0)
                if action is None:
                    break
                q = np.array(wbc.step(action, q, 0.01).q)
                aid.observe(q)
                ticks.append(time.perf_counter() - t1)
        rows.append(
            {
                "target": name,
                "base_moves": plan.base_moves,
                "manual_instructions": plan.manual_instructions,
                "planner": _ms(alone),
                "plan_and_preview": _ms(whole),
                "preview_points": points,
                "execute_tick": _ms(ticks),
                "ratio_whole_over_planner": float(np.median(whole) / np.median(alone)),
            }
        )
    table = Table(title="reach plan cost (TIAGo, from home)")
    for column in ("target", "planner median/max ms", "plan+preview median/max ms", "x planner", "tick ms"):
        table.add_column(column)
    for r in rows:
        p, w, t = r["planner"], r["plan_and_preview"], r["execute_tick"]
        table.add_row(
            str(r["target"]),
            f"{p['median_ms']:.1f} / {p['max_ms']:.1f}",  # type: ignore[index]
            f"{w['median_ms']:.0f} / {w['max_ms']:.0f}",  # type: ignore[index]
            f"{r['ratio_whole_over_planner']:.0f}",
            f"{t['median_ms']:.3f}",  # type: ignore[index]
        )
    Console().print(table)
    result = {
        "host": platform.node(),
        "load": os.getloadavg()[0],
        "repeats": args.repeats,
        "rows": rows,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
