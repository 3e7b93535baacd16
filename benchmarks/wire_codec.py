"""Benchmark telerig.ir.wire encode/decode [µs per call] per IR type; prints a table, writes JSON.

Encode is timed both ways in the same run: with the thread's reused Envelope (what telerig does)
and with a fresh Envelope per call (``wire._reuse`` off: the code before issue 18), and their ratio.
Times are the best of 7 repeats (fresh and reused alternating), so a loaded host inflates them
less than a mean would.
"""

from __future__ import annotations

import json
import os
import platform
import timeit
from pathlib import Path

import numpy as np

from telerig.ir import wire
from telerig.ir.types import (
    BodySkeleton,
    CameraFrame,
    ControllerState,
    HandPose,
    JointCommand,
    JointState,
    Pose,
    Sample,
    Stamp,
)

RESULTS = Path(__file__).parent / "results" / "wire_codec.json"


def _samples() -> dict[str, Sample]:
    rng = np.random.default_rng(0)
    st = Stamp("vr0/right", 7, 123, 1_700_000_000_000_000_000, 1_700_000_000_000_100_000, 0.9)
    q = np.array([1.0, 0.0, 0.0, 0.0])
    names = tuple(f"joint_{i}" for i in range(7))
    return {
        "Pose": Pose(st, rng.normal(size=3), q, "operator"),
        "ControllerState": ControllerState(
            st, "right", rng.normal(size=3), q, "operator", frozenset({"a"}), 0.5, 1.0, np.array([0.1, 0.2])
        ),
        "HandPose": HandPose(
            st, "left", rng.normal(size=3), q, rng.normal(size=(21, 3)), rng.uniform(size=21), "operator"
        ),
        "BodySkeleton(24)": BodySkeleton(
            st, tuple(f"j{i}" for i in range(24)), rng.normal(size=(24, 3)), rng.normal(size=(24, 4)), "mocap"
        ),
        "JointCommand(7)": JointCommand(st, names, rng.normal(size=7)),
        "JointState(7)": JointState(st, names, rng.normal(size=7), rng.normal(size=7), rng.normal(size=7)),
        "CameraFrame": CameraFrame(st, "wrist", 1234, 640, 480),
    }


def _best_us(fn: object, number: int) -> float:
    times = timeit.repeat(fn, number=number, repeat=5)  # type: ignore[arg-type]
    return min(times) / number * 1e6


def _interleaved_us(fn: object, number: int, repeat: int = 7) -> tuple[float, float]:
    """Best µs per call of ``fn`` with fresh Envelopes and with reused ones, timed in alternation
    (a host whose load changes during the run weighs on both alike)."""
    fresh, reused = [], []
    for _ in range(repeat):
        wire._reuse = False
        try:
            fresh.append(timeit.timeit(fn, number=number))  # type: ignore[arg-type]
        finally:
            wire._reuse = True
        reused.append(timeit.timeit(fn, number=number))  # type: ignore[arg-type]
    return min(fresh) / number * 1e6, min(reused) / number * 1e6


def main() -> None:
    """Run the benchmark, print a table and write :data:`RESULTS`."""
    rows = []
    for name, sample in _samples().items():
        data = wire.encode(sample)
        fresh_us, encode_us = _interleaved_us(lambda s=sample: wire.encode(s), 2000)
        rows.append(
            {
                "type": name,
                "bytes": len(data),
                "encode_us": encode_us,
                "encode_fresh_us": fresh_us,
                "encode_reused_over_fresh": encode_us / fresh_us,
                "decode_us": _best_us(lambda d=data: wire.decode(d), 5000),
            }
        )
    print(f"{'type':<18} {'bytes':>6} {'encode µs':>10} {'fresh µs':>9} {'ratio':>6} {'decode µs':>10}")
    for r in rows:
        print(
            f"{r['type']:<18} {r['bytes']:>6} {r['encode_us']:>10.2f} {r['encode_fresh_us']:>9.2f} "
            f"{r['encode_reused_over_fresh']:>6.2f} {r['decode_us']:>10.2f}"
        )
    RESULTS.parent.mkdir(exist_ok=True)
    meta = {
        "python": platform.python_version(),
        "machine": platform.machine(),
        "load_avg": os.getloadavg(),
        "nice": os.nice(0),
    }
    RESULTS.write_text(json.dumps({"meta": meta, "rows": rows}, indent=2))
    print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
