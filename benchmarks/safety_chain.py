"""Benchmark: microseconds per SafetyChain.step on a 7-joint arm (tracking, holding); prints a table."""

from __future__ import annotations

import json
import sys
import time

import numpy as np

from telerig.ir.types import JointCommand, JointState, Stamp
from telerig.robots.base import JointLimits
from telerig.safety import SafetyChain

N_JOINTS = 7
TICKS = 20_000
PERIOD_NS = 10_000_000


def _bench(mode: str) -> float:
    names = tuple(f"joint{i + 1}" for i in range(N_JOINTS))
    limits = JointLimits(names, [-3.0] * N_JOINTS, [3.0] * N_JOINTS, [2.0] * N_JOINTS, [10.0] * N_JOINTS)
    chain = SafetyChain.default(limits)
    t0 = time.time_ns()
    measured = JointState(Stamp("robot", 0, t0, t0), names, np.zeros(N_JOINTS), np.zeros(N_JOINTS))
    phases = np.linspace(0.0, 1.0, N_JOINTS)
    # Build requests up front: only the step is timed.
    requests = []
    for k in range(TICKS):
        t = t0 + k * PERIOD_NS
        q = 0.5 * np.sin(2.0 * np.pi * 0.5 * k * 0.01 + phases)
        requests.append(JointCommand(Stamp("retarget", k, t, t), names, q))
    for k in range(400):  # past the start-up ramp
        chain.step(requests[k], now_ns=t0 + k * PERIOD_NS, measured=measured)
    start = time.perf_counter()
    for k in range(400, TICKS):
        request = requests[k] if mode == "tracking" or k % 8 == 0 else None
        chain.step(request, now_ns=t0 + k * PERIOD_NS, measured=measured)
    return (time.perf_counter() - start) / (TICKS - 400) * 1e6


def main() -> None:
    results = {mode: _bench(mode) for mode in ("tracking", "holding")}
    print(f"{'mode':<10} {'us/step':>8}")
    for mode, us in results.items():
        print(f"{mode:<10} {us:8.1f}")
    json.dump({"benchmark": "safety_chain", "joints": N_JOINTS, "us_per_step": results}, sys.stderr)
    sys.stderr.write("\n")


if __name__ == "__main__":
    main()
