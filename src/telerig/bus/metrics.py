"""Small thread-safe meters for stream rates, gaps and latencies, cheap enough for the control loop."""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import numpy as np

__all__ = ["LatencySummary", "LatencyTracker", "StreamMeter", "StreamSummary"]


@dataclass(frozen=True, slots=True)
class LatencySummary:
    """Latency distribution [ms]."""

    count: int
    p50_ms: float
    p99_ms: float
    max_ms: float
    mean_ms: float


class LatencyTracker:
    """Collects latencies [ns] into a preallocated ring (the newest ``capacity`` values)."""

    def __init__(self, capacity: int = 200_000) -> None:
        self._values = np.zeros(capacity, dtype=np.int64)
        self._count = 0
        self._lock = threading.Lock()

    def add(self, latency_ns: int) -> None:
        with self._lock:
            self._values[self._count % self._values.size] = latency_ns
            self._count += 1

    def reset(self) -> None:
        with self._lock:
            self._count = 0

    def values_ns(self) -> np.ndarray:
        with self._lock:
            n = min(self._count, self._values.size)
            return self._values[:n].copy()

    def summary(self) -> LatencySummary:
        v = self.values_ns() / 1e6
        if v.size == 0:
            return LatencySummary(0, float("nan"), float("nan"), float("nan"), float("nan"))
        p50, p99 = np.percentile(v, [50, 99])
        return LatencySummary(int(v.size), float(p50), float(p99), float(v.max()), float(v.mean()))


@dataclass(frozen=True, slots=True)
class StreamSummary:
    """Rate and loss of one stream over a window.

    ``rejected`` counts the messages refused on the stream (by the recorder: oversized, malformed,
    wrong type, implausible stamp...), per reason; they are not in ``messages``.
    """

    name: str
    expected_hz: float
    measured_hz: float
    messages: int
    drops: int
    max_gap_ms: float
    rejected: dict[str, int] = field(default_factory=dict)


class StreamMeter:
    """Counts messages of one stream by capture time; drops from sequence gaps; rejects per reason."""

    def __init__(self, name: str, expected_hz: float) -> None:
        self.name = name
        self.expected_hz = expected_hz
        self._count = 0
        self._drops = 0
        self._first_ns = 0
        self._last_ns = 0
        self._max_gap_ns = 0
        self._last_seq: int | None = None
        self._rejected: dict[str, int] = {}
        self._lock = threading.Lock()

    def add(self, capture_ns: int, seq: int | None = None) -> None:
        with self._lock:
            if self._count == 0:
                self._first_ns = capture_ns
            elif capture_ns > self._last_ns:
                self._max_gap_ns = max(self._max_gap_ns, capture_ns - self._last_ns)
            if seq is not None and self._last_seq is not None and seq > self._last_seq + 1:
                self._drops += seq - self._last_seq - 1
            if seq is not None:
                self._last_seq = seq
            self._last_ns = max(self._last_ns, capture_ns)
            self._count += 1

    def add_drops(self, n: int) -> None:
        with self._lock:
            self._drops += n

    def add_rejected(self, reason: str) -> None:
        """Count one message refused for ``reason`` (not a message of the stream)."""
        with self._lock:
            self._rejected[reason] = self._rejected.get(reason, 0) + 1

    def summary(self) -> StreamSummary:
        with self._lock:
            span = (self._last_ns - self._first_ns) / 1e9
            rate = (self._count - 1) / span if self._count > 1 and span > 0 else 0.0
            return StreamSummary(
                self.name,
                self.expected_hz,
                rate,
                self._count,
                self._drops,
                self._max_gap_ns / 1e6,
                dict(self._rejected),
            )
