"""Python's cyclic garbage collections in this process, timed: each one stops every thread of it.

A collection walks the tracked objects of its generation with the interpreter lock held, so in a
station whose robots run as threads (the fleet rig) every control loop waits for it. ``gc.freeze``
after start-up (``runtime.process_settings.settle_heap``) keeps the start-up objects out of the
walk; what an episode makes and keeps is walked again by every full collection after it.

:class:`GcPauses` hooks ``gc.callbacks`` while its block runs and notes each collection that held
the lock for ``threshold_ms`` or more: a benchmark can then tell a gap that fell in one from the
rest, as :mod:`rt_blackout` does for the kernel's stalls.
"""

from __future__ import annotations

import gc
import threading
import time
from dataclasses import dataclass
from types import TracebackType
from typing import Any


@dataclass(frozen=True, slots=True)
class GcPause:
    """One collection of ``generation`` (0-2) from ``start_ns`` [ns, wall clock] for ``ms`` [ms] of
    wall time, run by the thread named ``thread`` (whose allocation set it off). The wall time
    includes any time that thread waited for a CPU meanwhile, the lock still held: a collection
    set off by a low-priority thread is as long as the threads above it make it."""

    generation: int
    start_ns: int
    ms: float
    thread: str = ""


class GcPauses:
    """Context manager: every collection of this process of ``threshold_ms`` [ms] or more while the
    block runs, in :attr:`pauses`; :attr:`counts` has every collection by generation."""

    def __init__(self, threshold_ms: float = 2.0) -> None:
        if not threshold_ms >= 0:
            raise ValueError(f"threshold_ms must be >= 0, got {threshold_ms}")
        self._threshold_ns = round(threshold_ms * 1e6)
        self._started: tuple[int, int] | None = None  # (wall ns, monotonic ns) of the one running
        #: The collections that took ``threshold_ms`` or more, by time.
        self.pauses: list[GcPause] = []
        #: Every collection, by generation.
        self.counts: dict[int, int] = {0: 0, 1: 0, 2: 0}

    def _callback(self, phase: str, info: dict[str, Any]) -> None:
        # Runs inside the collector, on the thread that triggered it: no allocation beyond the tuple.
        if phase == "start":
            self._started = (time.time_ns(), time.monotonic_ns())
            return
        if self._started is None:
            return
        wall_ns, mono_ns = self._started
        self._started = None
        generation = int(info.get("generation", 0))
        self.counts[generation] = self.counts.get(generation, 0) + 1
        took = time.monotonic_ns() - mono_ns
        if took >= self._threshold_ns:
            self.pauses.append(GcPause(generation, wall_ns, took / 1e6, threading.current_thread().name))

    def __enter__(self) -> GcPauses:
        gc.callbacks.append(self._callback)
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        gc.callbacks.remove(self._callback)

    def overlapping(self, start_ns: int, end_ns: int) -> list[GcPause]:
        """The pauses that overlap ``[start_ns, end_ns]`` [ns, wall clock]."""
        return [p for p in self.pauses if p.start_ns <= end_ns and p.start_ns + p.ms * 1e6 >= start_ns]
