"""Rate, gap and latency meters (most live in :mod:`telerig.bus.metrics`: record and store use them),
and the rolling latency window the control loop feeds for the live dashboard: one latency per entry,
or the stamps of one sample's stages (capture, receive, ..., state) for a per-stage breakdown."""

from __future__ import annotations

import math
import threading
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from telerig.bus.metrics import LatencySummary, LatencyTracker, StreamMeter, StreamSummary

__all__ = [
    "LatencySummary",
    "LatencyTracker",
    "LatencyWindow",
    "StageSummary",
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


@dataclass(frozen=True, slots=True)
class StageSummary:
    """Per-stage latencies of the last ``window_s`` [ms], from rows of stamps (see :class:`LatencyWindow`).

    Attributes:
        stages: Each stage's latencies (the difference of its row's consecutive stamps), by name.
        total: First to last stamp of each row (the sum of its stages, exactly, row by row).
        out_of_order: Rows with a stamp earlier than the one before it (clock steps between hosts,
            or a producer that stamps wrongly); they are kept in the figures and counted here.
    """

    stages: dict[str, WindowSummary]
    total: WindowSummary
    out_of_order: int


class LatencyWindow:
    """Latencies [ns] and when they happened [ns], in preallocated rings, for rolling percentiles.

    Either one latency per entry (:meth:`add`, :meth:`summary`), or, with ``stages``, one row of
    ``len(stages) + 1`` stamps [ns] per sample followed through those stages (:meth:`add_stamps`,
    :meth:`stage_summary`): stage ``i`` is ``stamp[i + 1] - stamp[i]``, so the stages of a row add up
    to its end-to-end latency exactly. :meth:`add` and :meth:`add_stamps` are cheap enough for every
    control tick: a few integer stores under a lock, no allocation, no JSON. The summaries (called
    from a low-rate reporting thread) copy the ring and compute the percentiles of the entries added
    in the last ``window_s``. A producer faster than ``capacity / window_s`` entries per second
    keeps only the newest ``capacity``: the window is then shorter than asked for, and ``count``
    says so.

    Args:
        window_s: Rolling window [s] (> 0).
        capacity: Ring size (>= 1); 4096 covers a 2 s window up to 2 kHz.
        stages: Stage names, in order; empty for a window of single latencies.
    """

    def __init__(self, window_s: float = 2.0, capacity: int = 4096, *, stages: Sequence[str] = ()) -> None:
        if not window_s > 0 or not math.isfinite(window_s):
            raise ValueError(f"window_s must be a finite number > 0 s, got {window_s}")
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        if len(set(stages)) != len(stages):
            raise ValueError(f"stage names must be unique, got {list(stages)}")
        self.window_ns = round(window_s * 1e9)
        self.stages = tuple(stages)
        self._at = np.zeros(capacity, dtype=np.int64)
        self._values = np.zeros((capacity, len(self.stages) + 1), dtype=np.int64)
        self._count = 0
        self._lock = threading.Lock()

    def add(self, latency_ns: int, at_ns: int) -> None:
        """Keep one latency [ns] observed at ``at_ns`` [ns, the clock :meth:`summary` is given]."""
        with self._lock:
            i = self._count % self._at.size
            self._values[i, 0] = latency_ns
            self._at[i] = at_ns
            self._count += 1

    def add_stamps(self, at_ns: int, *stamps: int) -> None:
        """Keep one sample's stage stamps [ns, common clock], first to last, observed at ``at_ns``.

        Raises:
            ValueError: Not ``len(stages) + 1`` stamps.
        """
        values = self._values
        if len(stamps) != values.shape[1] or not self.stages:
            raise ValueError(f"give {len(self.stages) + 1} stamps for {self.stages}, got {len(stamps)}")
        with self._lock:
            i = self._count % self._at.size
            for j, stamp in enumerate(stamps):
                values[i, j] = stamp
            self._at[i] = at_ns
            self._count += 1

    def reset(self) -> None:
        """Forget every value."""
        with self._lock:
            self._count = 0

    def _recent(self, now_ns: int) -> npt.NDArray[np.int64]:
        with self._lock:
            n = min(self._count, self._at.size)
            at = self._at[:n].copy()
            values = self._values[:n].copy()
        keep = (at > now_ns - self.window_ns) & (at <= now_ns)
        return values[keep]

    def summary(self, now_ns: int) -> WindowSummary:
        """Percentiles of the values added in ``(now_ns - window, now_ns]`` [ms]."""
        return _summary(self._recent(now_ns)[:, 0])

    def rows(self, now_ns: int) -> npt.NDArray[np.int64]:
        """The stamp rows [ns] added in ``(now_ns - window, now_ns]``, oldest first within the ring.
        Shape (rows, len(stages) + 1)."""
        return self._recent(now_ns)

    def stage_summary(self, now_ns: int) -> StageSummary:
        """Per-stage and end-to-end percentiles of the rows added in ``(now_ns - window, now_ns]``."""
        rows = self._recent(now_ns)
        steps = np.diff(rows, axis=1)
        return StageSummary(
            {name: _summary(steps[:, i]) for i, name in enumerate(self.stages)},
            _summary(rows[:, -1] - rows[:, 0]),
            int(np.count_nonzero((steps < 0).any(axis=1))),
        )


def _summary(values_ns: npt.NDArray[np.int64]) -> WindowSummary:
    if values_ns.size == 0:
        nan = float("nan")
        return WindowSummary(0, nan, nan, nan)
    v = values_ns / 1e6
    p50, p99 = np.percentile(v, [50, 99])
    return WindowSummary(int(v.size), float(p50), float(p99), float(v.max()))
