"""Rate, gap and latency meters (most live in :mod:`telerig.bus.metrics`: record and store use them),
and the rolling latency window the control loop feeds for the live dashboard."""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import numpy as np

from telerig.bus.metrics import LatencySummary, LatencyTracker, StreamMeter, StreamSummary

__all__ = [
    "LatencySummary",
    "LatencyTracker",
    "LatencyWindow",
    "StreamMeter",
    "StreamSummary",
    "WindowSummary",
]


@dataclass(frozen=True, slots=True)
class WindowSummary:
    """Latencies of the last ``window_s`` [ms]; the percentiles are ``nan`` when ``count`` is 0.

    Attributes:
        count: Values in the window (at most the ring's capacity).
        p50_ms: Median [ms].
        p99_ms: 99th percentile [ms] (linear interpolation, as :func:`numpy.percentile`).
        max_ms: Largest [ms].
    """

    count: int
    p50_ms: float
    p99_ms: float
    max_ms: float

    def to_json(self) -> dict[str, float | int | None]:
        """``{"count", "p50_ms", "p99_ms", "max_ms"}``, ``null`` for what the window cannot say."""

        def ms(value: float) -> float | None:
            return round(value, 3) if math.isfinite(value) else None

        return {
            "count": self.count,
            "p50_ms": ms(self.p50_ms),
            "p99_ms": ms(self.p99_ms),
            "max_ms": ms(self.max_ms),
        }


class LatencyWindow:
    """Latencies [ns] and when they happened [ns], in two preallocated rings, for rolling percentiles.

    :meth:`add` is cheap enough for every control tick: two integer stores under a lock, no
    allocation, no JSON. :meth:`summary` (called from a low-rate reporting thread) copies the ring
    and computes the percentiles of the values added in the last ``window_s``. A control loop faster
    than ``capacity / window_s`` ticks per second keeps only the newest ``capacity`` values: the
    window is then shorter than asked for, and ``count`` says so.

    Args:
        window_s: Rolling window [s] (> 0).
        capacity: Ring size (>= 1); 4096 covers a 2 s window up to 2 kHz.
    """

    def __init__(self, window_s: float = 2.0, capacity: int = 4096) -> None:
        if not window_s > 0 or not math.isfinite(window_s):
            raise ValueError(f"window_s must be a finite number > 0 s, got {window_s}")
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        self.window_ns = round(window_s * 1e9)
        self._at = np.zeros(capacity, dtype=np.int64)
        self._values = np.zeros(capacity, dtype=np.int64)
        self._count = 0
        self._lock = threading.Lock()

    def add(self, latency_ns: int, at_ns: int) -> None:
        """Keep one latency [ns] observed at ``at_ns`` [ns, the clock :meth:`summary` is given]."""
        with self._lock:
            i = self._count % self._values.size
            self._values[i] = latency_ns
            self._at[i] = at_ns
            self._count += 1

    def reset(self) -> None:
        """Forget every value."""
        with self._lock:
            self._count = 0

    def summary(self, now_ns: int) -> WindowSummary:
        """Percentiles of the values added in ``(now_ns - window, now_ns]`` [ms]."""
        with self._lock:
            n = min(self._count, self._values.size)
            at = self._at[:n].copy()
            values = self._values[:n].copy()
        keep = (at > now_ns - self.window_ns) & (at <= now_ns)
        v = values[keep] / 1e6
        if v.size == 0:
            nan = float("nan")
            return WindowSummary(0, nan, nan, nan)
        p50, p99 = np.percentile(v, [50, 99])
        return WindowSummary(int(v.size), float(p50), float(p99), float(v.max()))
