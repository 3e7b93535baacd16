"""Benchmark: UR driver round trip against the fake controller (send -> applied -> state back); table + JSON.

Each sample writes a new target with :meth:`URRobot.send` and waits until an RTDE state
package reports it as ``target_q``, i.e. the controller's servo loop read the registers and the
next output package carried it back. Latency is package arrival minus the send stamp. On a real
robot add the network round trip; the controller side is bounded by its 2 ms cycle plus one
output period.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from telerig.ir.types import JointCommand, Stamp
from telerig.robots.ur.driver import URRobot
from telerig.robots.ur.fake import FakeURController
from telerig.robots.ur.script import ServoProgram


def bench(rate_hz: float, samples: int) -> dict[str, float]:
    with FakeURController(rtde_port=0, script_port=0) as fake:
        driver = URRobot(
            "127.0.0.1",
            rtde_port=fake.rtde_port,
            script_port=fake.script_port,
            control_rate_hz=rate_hz,
            program=ServoProgram(watchdog_cycles=500),
            stale_timeout_s=2.0,
        )
        with driver:
            home = driver.read_state().positions
            lat = np.empty(samples)
            send_us = np.empty(samples)
            for k in range(samples):
                target = home + (0.001 * (k % 2 + 1))
                t0 = time.perf_counter()
                sent = driver.send(JointCommand(Stamp.now("bench", k), driver.joint_names, target))
                send_us[k] = (time.perf_counter() - t0) * 1e6
                deadline = time.monotonic() + 1.0
                while True:
                    status = driver.status()
                    if (
                        np.allclose(status.target_q, sent.positions)
                        and status.arrival_ns > sent.stamp.capture_ns
                    ):
                        break
                    if time.monotonic() > deadline:
                        raise RuntimeError("the fake did not apply a command within 1 s")
                    time.sleep(0.0001)
                lat[k] = (status.arrival_ns - sent.stamp.capture_ns) / 1e6
            stats = driver.stats()
    return {
        "rate_hz": rate_hz,
        "samples": samples,
        "round_trip_p50_ms": float(np.percentile(lat, 50)),
        "round_trip_p99_ms": float(np.percentile(lat, 99)),
        "round_trip_max_ms": float(lat.max()),
        "send_call_p50_us": float(np.percentile(send_us, 50)),
        "malformed": stats.malformed,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=500)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/ur_rtde.json"))
    args = parser.parse_args()
    rows = [bench(rate, args.samples) for rate in (125.0, 500.0)]
    table = Table(title="UR driver vs FakeURController on 127.0.0.1: send -> applied -> state back")
    for col in ("RTDE rate Hz", "p50 ms", "p99 ms", "max ms", "send() µs p50"):
        table.add_column(col, justify="right")
    for r in rows:
        table.add_row(
            f"{r['rate_hz']:.0f}",
            f"{r['round_trip_p50_ms']:.2f}",
            f"{r['round_trip_p99_ms']:.2f}",
            f"{r['round_trip_max_ms']:.2f}",
            f"{r['send_call_p50_us']:.0f}",
        )
    console = Console(width=120)
    console.print(table)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"benchmark": "ur_rtde", "rows": rows}, indent=2))
    console.print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
