"""Benchmark telerig.ir.wire encode/decode [µs per call] per IR type; prints a table, writes JSON."""

from __future__ import annotations

import json
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


def main() -> None:
    """Run the benchmark, print a table and write :data:`RESULTS`."""
    rows = []
    for name, sample in _samples().items():
        data = wire.encode(sample)
        rows.append(
            {
                "type": name,
                "bytes": len(data),
                "encode_us": _best_us(lambda s=sample: wire.encode(s), 5000),
                "decode_us": _best_us(lambda d=data: wire.decode(d), 5000),
            }
        )
    print(f"{'type':<18} {'bytes':>6} {'encode µs':>10} {'decode µs':>10}")
    for r in rows:
        print(f"{r['type']:<18} {r['bytes']:>6} {r['encode_us']:>10.2f} {r['decode_us']:>10.2f}")
    RESULTS.parent.mkdir(exist_ok=True)
    meta = {"python": platform.python_version(), "machine": platform.machine()}
    RESULTS.write_text(json.dumps({"meta": meta, "rows": rows}, indent=2))
    print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
