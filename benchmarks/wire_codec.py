"""Benchmark telerig.ir.wire encode/decode [µs per call] per IR type; prints a table, writes JSON.

Encode is timed both ways in the same run: with the thread's reused Envelope (what telerig does)
and with a fresh Envelope per call (``wire._reuse`` off: the code before issue 18), and their ratio.
Times are the best of 7 repeats (fresh and reused alternating), so a loaded host inflates them
less than a mean would.

A second table is the control node's per-tick ``control_source`` record (robots with a handover),
encode + publish on an in-memory bus, before (a dict through ``json.dumps``, what the node did until
issue 18) and after (a typed :class:`~telerig.ir.types.ControlSource` through the reused Envelope),
timed alternately in the same run, with the Python memory blocks each leaves allocated during the
call (tracemalloc peak per tick) and the payload size.

A third table does the same for the per-solve ``residual`` record (every retargeting robot),
with the real retargeters' residual objects: the arm IK (2 metrics), the humanoid IK (5) and the
whole-body controller (16): before, ``json.dumps`` of ``{capture_ns, flagged, **metrics()}``; after,
a typed :class:`~telerig.ir.types.RetargetResidual` through the reused Envelope (the node's code).
"""

from __future__ import annotations

import json
import os
import platform
import timeit
import tracemalloc
from collections.abc import Callable
from pathlib import Path

import numpy as np

from telerig.bus.memory import InMemoryBus
from telerig.ir import wire
from telerig.ir.types import (
    BodySkeleton,
    CameraFrame,
    ControlKind,
    ControllerState,
    ControlSource,
    HandPose,
    JointCommand,
    JointState,
    Pose,
    RetargetResidual,
    Sample,
    Stamp,
)
from telerig.retarget.arm_ik import IKResult
from telerig.retarget.binding import Residual
from telerig.retarget.humanoid import HumanoidIKResult
from telerig.retarget.wbc import TaskErrors, WBCResult
from telerig.retarget.whole_body import WholeBodyResidual

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
        "ControlSource": ControlSource(st, "pi0", "policy", "auto"),
        "RetargetResidual(2)": RetargetResidual(
            st, False, ("position_error_m", "orientation_error_rad"), (0.01, 0.2)
        ),
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


_CONTROL_TOPIC = "telerig/v1/bench/arm0/control_source"


def _control_ticks(
    bus: InMemoryBus | None, source: str | None, kind: ControlKind
) -> dict[str, Callable[[], None]]:
    """One tick's ``control_source`` record, encoded and (with a bus) published, the JSON way
    (before) and the typed way (after)."""
    clock = [1_700_000_000_000_000_000]
    json_kind = None if kind == "none" else kind
    publish = bus.publish if bus is not None else lambda topic, payload: None

    def before() -> None:  # control_node._publish_control before issue 18, verbatim but for names
        clock[0] += 10_000_000
        record = {"capture_ns": clock[0], "source": source, "kind": json_kind, "mode": "auto"}
        publish(_CONTROL_TOPIC, json.dumps(record).encode())

    seq = [0]

    def after() -> None:  # control_node._publish_control now
        clock[0] += 10_000_000
        seq[0] += 1
        now = clock[0]
        stamp = Stamp("arm0", seq[0], now, now)
        publish(_CONTROL_TOPIC, wire.encode(ControlSource(stamp, source, kind, "auto")))

    return {"json": before, "typed": after}


def _peak_bytes(fn: Callable[[], None], n: int = 200) -> float:
    """Mean tracemalloc peak [bytes] above the baseline during one call of ``fn`` (Python objects)."""
    fn()  # warm: the reused Envelope and interned strings exist
    tracemalloc.start()
    try:
        total = 0
        for _ in range(n):
            tracemalloc.reset_peak()
            base, _ = tracemalloc.get_traced_memory()
            fn()
            total += tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()
    return total / n


def control_source_rows(number: int = 5000, repeat: int = 7) -> list[dict[str, object]]:
    """The per-tick ``control_source`` record, JSON against typed, alternating in one run: encoded
    only, and encoded and published on an in-memory bus with one subscriber (as the recorder)."""
    bus = InMemoryBus()
    last_size = [0]
    bus.subscribe(_CONTROL_TOPIC, lambda m: last_size.__setitem__(0, len(m.payload)))
    cases: tuple[tuple[str, str | None, ControlKind], ...] = (
        ("policy drives", "pi0", "policy"),
        ("nobody drives", None, "none"),
    )
    rows: list[dict[str, object]] = []
    for case, source, kind in cases:
        for stage, target in (("encode", None), ("encode+publish", bus)):
            ticks = _control_ticks(target, source, kind)
            published = _control_ticks(bus, source, kind)
            rows.append(_json_vs_typed(case, stage, ticks, published, last_size, number, repeat))
    return rows


def _json_vs_typed(
    case: str,
    stage: str,
    ticks: dict[str, Callable[[], None]],
    published: dict[str, Callable[[], None]],
    last_size: list[int],
    number: int,
    repeat: int,
) -> dict[str, object]:
    """One table row: best time of each way over ``repeat`` alternating runs, peak allocation, and
    the payload size (``published`` ways publish on the bus whose subscriber sets ``last_size``)."""
    best = dict.fromkeys(ticks, float("inf"))
    for _ in range(repeat):
        for way, fn in ticks.items():
            best[way] = min(best[way], timeit.timeit(fn, number=number) / number * 1e6)
    size = {}
    for way, fn in published.items():
        fn()
        size[way] = last_size[0]
    return {
        "case": case,
        "stage": stage,
        "json_us": best["json"],
        "typed_us": best["typed"],
        "typed_over_json": best["typed"] / best["json"],
        "json_peak_bytes": _peak_bytes(ticks["json"]),
        "typed_peak_bytes": _peak_bytes(ticks["typed"]),
        "json_payload_bytes": size["json"],
        "typed_payload_bytes": size["typed"],
    }


_RESIDUAL_TOPIC = "telerig/v1/bench/arm0/residual"


def _residuals() -> dict[str, Residual]:
    """One residual of each kind of retargeter, as it hands them to the control node."""
    q = np.zeros(6)
    errors = TaskErrors(0.01, 0.02, 0.0, 0.0, 0.0, 0.003, 0.01)
    wbc = WBCResult(np.zeros(10), np.zeros(10), 0.0, 0, errors, True)
    return {
        "arm IK (2)": IKResult(q, 0.0123, 0.0456, False),
        "humanoid (5)": HumanoidIKResult(q, np.array([0.01, 0.02]), np.array([0.03, 0.04]), False, 0.0005),
        "whole body (17)": WholeBodyResidual(
            wbc, np.array([0.1, 0.0, 0.0, 0.0, 0.0, 0.2, 1.0, 0.0]), 0.05, 1.2e-4
        ),
    }


def _residual_ticks(bus: InMemoryBus | None, residual: Residual) -> dict[str, Callable[[], None]]:
    """One solve's ``residual`` record, encoded and (with a bus) published, the JSON way (before)
    and the typed way (after)."""
    clock = [1_700_000_000_000_000_000]
    publish = bus.publish if bus is not None else lambda topic, payload: None

    def before() -> None:  # control_node._publish_residual before issue 18, verbatim but for names
        clock[0] += 10_000_000
        record: dict[str, float | int | bool] = {"capture_ns": clock[0], "flagged": residual.flagged}
        record.update(residual.metrics())
        publish(_RESIDUAL_TOPIC, json.dumps(record).encode())

    seq = [0]

    def after() -> None:  # control_node._publish_residual now
        clock[0] += 10_000_000
        metrics = residual.metrics()
        seq[0] += 1
        stamp = Stamp("arm0", seq[0], clock[0], clock[0])
        sample = RetargetResidual(stamp, residual.flagged, tuple(metrics), tuple(metrics.values()))
        publish(_RESIDUAL_TOPIC, wire.encode(sample))

    return {"json": before, "typed": after}


def residual_rows(number: int = 5000, repeat: int = 7) -> list[dict[str, object]]:
    """The per-solve ``residual`` record, JSON against typed, alternating in one run: encoded only,
    and encoded and published on an in-memory bus with one subscriber (as the recorder)."""
    bus = InMemoryBus()
    last_size = [0]
    bus.subscribe(_RESIDUAL_TOPIC, lambda m: last_size.__setitem__(0, len(m.payload)))
    rows: list[dict[str, object]] = []
    for case, residual in _residuals().items():
        for stage, target in (("encode", None), ("encode+publish", bus)):
            ticks = _residual_ticks(target, residual)
            published = _residual_ticks(bus, residual)
            rows.append(_json_vs_typed(case, stage, ticks, published, last_size, number, repeat))
    return rows


def _print_per_tick(title: str, rows: list[dict[str, object]]) -> None:
    print()
    print(title)
    head = f"{'case':<16} {'stage':<15} {'json µs':>8} {'typed µs':>9} {'ratio':>6}"
    print(f"{head} {'json B*':>8} {'typed B*':>9} {'payload':>9}")
    for c in rows:
        print(
            f"{c['case']:<16} {c['stage']:<15} {c['json_us']:>8.2f} {c['typed_us']:>9.2f} "
            f"{c['typed_over_json']:>6.2f} {c['json_peak_bytes']:>8.0f} {c['typed_peak_bytes']:>9.0f} "
            f"{c['json_payload_bytes']:>4}/{c['typed_payload_bytes']:<4}"
        )
    print("* tracemalloc peak of Python allocations during one tick [bytes]; payload: JSON/typed bytes")


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
    control = control_source_rows()
    _print_per_tick(
        "control_source per tick, JSON before vs typed after, alternating in the same run:", control
    )
    residual = residual_rows()
    _print_per_tick("residual per solve, JSON before vs typed after, alternating in the same run:", residual)
    RESULTS.parent.mkdir(exist_ok=True)
    meta = {
        "python": platform.python_version(),
        "machine": platform.machine(),
        "load_avg": os.getloadavg(),
        "nice": os.nice(0),
    }
    RESULTS.write_text(
        json.dumps({"meta": meta, "rows": rows, "control_source": control, "residual": residual}, indent=2)
    )
    print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
