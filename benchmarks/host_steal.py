"""CPU time the hypervisor took from this machine while a benchmark measured (steal).

On a shared virtual machine the guest's vCPUs wait whenever the host runs another tenant; Linux
counts that time as *steal* in ``/proc/stat``. A latency tail measured then is the host's, not
telerig's: on 2026-11-26 a SCHED_FIFO thread sleeping 1 ms on this 2-core VM woke 100-536 ms late,
hundreds of times a minute, while ``vmstat`` showed 42-66 % steal, and every benchmark of the
control path (the minimal prototype included) read 2-3x its usual latency. The load average does
not show it. The control-path benchmarks record the steal over each measuring window beside their
numbers, so a run can be read, or discarded, for what it is.
"""

from __future__ import annotations

import psutil

#: Steal above this fraction of the machine's CPU time makes a timing row the host's.
STEAL_WARN = 0.05


class StealMeter:
    """Fraction of all CPUs' time stolen by the hypervisor between ``start()`` and ``stop()``.

    ``fraction`` is ``None`` where the kernel does not report steal (not Linux, no hypervisor).
    Use as a context manager around one measuring window.
    """

    def __init__(self) -> None:
        self._start: tuple[float, float] | None = None
        self.fraction: float | None = None

    @staticmethod
    def _read() -> tuple[float, float] | None:
        times = psutil.cpu_times()
        steal = getattr(times, "steal", None)
        if steal is None:
            return None
        return float(steal), float(sum(times))

    def start(self) -> StealMeter:
        self._start = self._read()
        self.fraction = None
        return self

    def stop(self) -> float | None:
        end = self._read()
        if self._start is None or end is None:
            return None
        stolen, total = end[0] - self._start[0], end[1] - self._start[1]
        self.fraction = stolen / total if total > 0 else None
        return self.fraction

    def __enter__(self) -> StealMeter:
        return self.start()

    def __exit__(self, *_exc: object) -> None:
        self.stop()


def steal_text(fraction: float | None) -> str:
    """A table cell: the steal in percent, or '-' where the kernel does not report it."""
    return "-" if fraction is None else f"{fraction:.0%}"


def steal_warning(fractions: list[float | None]) -> str | None:
    """One line when any window lost more than :data:`STEAL_WARN` of the CPU to the host, else None."""
    seen = [f for f in fractions if f is not None]
    if not seen or max(seen) <= STEAL_WARN:
        return None
    return (
        f"the host took up to {max(seen):.0%} of this machine's CPU time (steal) while measuring: "
        "these timings are the host's; rerun when `vmstat 1` shows st near 0"
    )
