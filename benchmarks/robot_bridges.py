"""Benchmark: Dobot, rosbridge and Unitree G1 drivers vs their fake peers on 127.0.0.1: send -> motion seen.

For each sample the arm rests, the driver sends a 0.01 rad step on the first joint, and the
script polls ``read_state`` until a state shows that joint moving toward the step; the
round trip is that state's ``arrival_ns`` minus the sent command's stamp. It includes the
peer's state period (Dobot 8 ms feedback, rosbridge ``rate_hz``, the G1's 2 ms ``rt/lowstate``),
which dominates. The G1 runs over real DDS (Cyclone) on the loopback interface.
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal, cast

import numpy as np
from rich.console import Console
from rich.table import Table

from telerig.ir.types import JointCommand, Stamp
from telerig.robots.base import JointLimits
from telerig.robots.dobot import DobotRobot, FakeDobot
from telerig.robots.rosbridge import CommandType, FakeRosbridge, RosbridgeRobot

STEP = 0.01  # [rad]


def _measure(driver: Any, samples: int) -> dict[str, float]:
    lat = np.empty(samples)
    send_us = np.empty(samples)
    rng = np.random.default_rng(0)
    for k in range(samples):
        # Let the previous step settle; the random part keeps the send phase independent of the peer's tick.
        time.sleep(0.03 + rng.uniform(0.0, 0.02))
        start = driver.read_state().positions
        sign = 1.0 if k % 2 == 0 else -1.0
        target = start.copy()
        target[0] += sign * STEP
        t0 = time.perf_counter()
        sent = driver.send(JointCommand(Stamp.now("bench", k), driver.joint_names, target))
        send_us[k] = (time.perf_counter() - t0) * 1e6
        deadline = time.monotonic() + 1.0
        while True:
            state = driver.read_state()
            if (
                sign * (state.positions[0] - start[0]) > 1e-9
                and state.stamp.arrival_ns > sent.stamp.capture_ns
            ):
                break
            if time.monotonic() > deadline:
                raise RuntimeError("the fake did not move within 1 s")
            time.sleep(0.0001)
        lat[k] = (state.stamp.arrival_ns - sent.stamp.capture_ns) / 1e6
    return {
        "samples": samples,
        "round_trip_p50_ms": float(np.percentile(lat, 50)),
        "round_trip_p99_ms": float(np.percentile(lat, 99)),
        "round_trip_max_ms": float(lat.max()),
        "send_call_p50_us": float(np.percentile(send_us, 50)),
        "send_call_p99_us": float(np.percentile(send_us, 99)),
    }


def bench_dobot(samples: int, motion_on_dashboard: bool) -> dict[str, Any]:
    protocol: Literal["v3", "v4"] = "v4" if motion_on_dashboard else "v3"
    with FakeDobot(dashboard_port=0, motion_port=0, feedback_port=0, protocol=protocol) as fake:
        robot = DobotRobot(
            "127.0.0.1",
            dashboard_port=fake.dashboard_port,
            motion_port=None if motion_on_dashboard else fake.motion_port,
            feedback_port=fake.feedback_port,
            protocol=protocol,
            servo_time_s=0.03,
        )
        with robot:
            row = _measure(robot, samples)
            row["malformed"] = robot.stats["malformed"]
    return {
        "driver": f"dobot {protocol} ({'ServoJ on 29999' if motion_on_dashboard else 'ServoJ on 30003'})",
        "state_period_ms": 8.0,
        **row,
    }


def bench_rosbridge(samples: int, rate_hz: float, kind: str) -> dict[str, Any]:
    names = ("j1", "j2", "j3", "j4", "j5", "j6")
    limits = JointLimits(names, np.full(6, -3.0), np.full(6, 3.0), np.full(6, 3.0), np.full(6, 10.0))
    command_type = cast(CommandType, kind)
    with (
        FakeRosbridge(names, rate_hz=rate_hz, max_velocity=3.0, command_type=command_type) as fake,
        RosbridgeRobot(fake.url, limits, command_type=command_type, trajectory_time_s=0.03) as robot,
    ):
        row = _measure(robot, samples)
        row["malformed"] = robot.stats["malformed"]
    return {"driver": f"rosbridge {kind.split('/')[1]}", "state_period_ms": 1000.0 / rate_hz, **row}


def bench_unitree(samples: int) -> dict[str, Any]:
    from telerig.registry import ROBOTS
    from telerig.robots.unitree.fake import FakeG1

    with FakeG1(domain_id=220, rate_hz=500.0, max_velocity=3.0) as fake:
        entry = {"type": "unitree_g1", "id": "g1", "network_interface": "lo", "domain_id": fake.domain_id}
        with ROBOTS.parse_config({**entry, "weight_ramp_s": 0.05}, "bench").build() as robot:
            time.sleep(0.1)  # the weight ramp
            row = _measure(robot, samples)
            row["bad_crc"] = fake.bad_crc
    return {"driver": "unitree_g1 arm_sdk (DDS)", "state_period_ms": 2.0, **row}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=200)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/robot_bridges.json"))
    args = parser.parse_args()
    runs: list[Callable[[], dict[str, Any]]] = [
        lambda: bench_dobot(args.samples, False),
        lambda: bench_dobot(args.samples, True),
        lambda: bench_rosbridge(args.samples, 100.0, "trajectory_msgs/JointTrajectory"),
        lambda: bench_rosbridge(args.samples, 500.0, "trajectory_msgs/JointTrajectory"),
        lambda: bench_rosbridge(args.samples, 500.0, "std_msgs/Float64MultiArray"),
        lambda: bench_unitree(args.samples),
    ]
    rows = [run() for run in runs]
    table = Table(title="Real-protocol drivers vs fake peers on 127.0.0.1: send -> state shows motion")
    for col in ("driver", "state period ms", "p50 ms", "p99 ms", "max ms", "send() µs p50", "p99"):
        table.add_column(col, justify="right")
    for r in rows:
        table.add_row(
            r["driver"],
            f"{r['state_period_ms']:.0f}",
            f"{r['round_trip_p50_ms']:.2f}",
            f"{r['round_trip_p99_ms']:.2f}",
            f"{r['round_trip_max_ms']:.2f}",
            f"{r['send_call_p50_us']:.0f}",
            f"{r['send_call_p99_us']:.0f}",
        )
    console = Console(width=140)
    console.print(table)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"benchmark": "robot_bridges", "rows": rows}, indent=2))
    console.print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
