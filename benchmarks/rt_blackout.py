"""Moments the kernel stopped every real-time thread at once, seen by a probe above all of them.

A robot's control thread under ``SCHED_RR`` preempts every ordinary task, but not the kernel's own
reservations for them: classic RT throttling (real-time threads may run
``kernel.sched_rt_runtime_us`` of every ``sched_rt_period_us``, 950 of 1000 ms) and, on kernels
6.12 and later, the *fair server*, which gives ordinary tasks starved by real-time ones up to 50 ms
of each second at a priority above every real-time thread. Either stops every real-time thread on
that CPU for up to 50 ms, whatever its priority.

Seen on this 2-core VM (kernel 6.18) on 2026-11-28 with an ordinary process spinning at nice 0
beside the fleet benchmark: in 9 of 22 runs a SCHED_FIFO 50 probe woke ~50 ms late once a second,
often for several seconds in a row, at the moments every robot missed 5 ticks (those runs: 34-572
missed ticks; the other 13: 0-49, at most 2 in 11). A kernel trace of one showed CPU 0 handed to
the ordinary tasks for 50 ms each second while real-time threads waited. Turning RT throttling off
(``kernel.sched_rt_runtime_us=-1``) did not stop it: blackouts in 2 of 10 runs with it off, 7 of 12
with it on. With the spinning process gone, 5 runs: no blackout, 11 / 0 / 0 / 0 / 0 missed ticks.

:class:`RtBlackoutProbe` runs that probe, a process of its own at ``SCHED_FIFO`` ``priority`` that
sleeps ``period_ms`` at a time and notes each wake-up later than ``threshold_ms``: a stall no
telerig thread, at any priority it uses, could have escaped, and a benchmark can tell its own
missed ticks from the host's. It needs the right to real-time scheduling (root or CAP_SYS_NICE);
without it :attr:`RtBlackoutProbe.refused` says why and the benchmark says it did not measure.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType

# The probe's loop: nothing imported beyond the standard library, one wake-up per period.
_PROBE = """
import json, os, signal, sys, time
out, period, threshold, priority = sys.argv[1], float(sys.argv[2]), float(sys.argv[3]), int(sys.argv[4])
try:
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
except OSError as exc:
    print(f"refused: {exc}", flush=True)
    sys.exit(3)
stop = []
signal.signal(signal.SIGTERM, lambda *_: stop.append(1))
print("ready", flush=True)
late = []
due = time.monotonic() + period
while not stop:
    time.sleep(max(0.0, due - time.monotonic()))
    now = time.monotonic()
    if now - due > threshold:
        late.append((time.time_ns(), (now - due) * 1e3))
    due = max(due + period, now)
with open(out, "w") as f:
    json.dump(late, f)
"""


@dataclass(frozen=True, slots=True)
class Blackout:
    """One late wake-up of the probe: from ``start_ns`` [ns, wall clock] for ``ms`` [ms]."""

    start_ns: int
    ms: float


def rt_throttle_text() -> str:
    """The kernel's RT throttling as a table cell: ``on (950 of 1000 ms)``, ``off`` or ``-`` (unknown)."""
    try:
        runtime = int(Path("/proc/sys/kernel/sched_rt_runtime_us").read_text())
        period = int(Path("/proc/sys/kernel/sched_rt_period_us").read_text())
    except (OSError, ValueError):
        return "-"
    return "off" if runtime < 0 else f"on ({runtime // 1000} of {period // 1000} ms)"


class RtBlackoutProbe:
    """Context manager: a ``SCHED_FIFO`` probe process while the block runs; :attr:`blackouts` after.

    Args:
        priority: The probe's real-time priority; above every thread of the rig.
        period_ms: How long it sleeps at a time [ms].
        threshold_ms: A wake-up later than this is a blackout [ms].
    """

    def __init__(self, priority: int = 50, period_ms: float = 5.0, threshold_ms: float = 10.0) -> None:
        if not (1 <= priority <= 99 and period_ms > 0 and threshold_ms > 0):
            raise ValueError(
                f"priority must be 1..99 and the times > 0, got {priority}, {period_ms}, {threshold_ms}"
            )
        self._args = (period_ms / 1e3, threshold_ms / 1e3, priority)
        self._dir = tempfile.TemporaryDirectory(prefix="telerig-rt-probe-")
        self._out = Path(self._dir.name) / "late.json"
        self._process: subprocess.Popen[str] | None = None
        #: Why the probe did not run (no right to real-time scheduling), or None.
        self.refused: str | None = None
        #: The probe's late wake-ups, by time; empty until the block ends.
        self.blackouts: list[Blackout] = []

    @property
    def running(self) -> bool:
        """Whether the probe runs (inside the block, unless it was refused)."""
        return self._process is not None

    @property
    def pid(self) -> int | None:
        """The probe process's id while it runs."""
        return None if self._process is None else self._process.pid

    def __enter__(self) -> RtBlackoutProbe:
        period, threshold, priority = self._args
        process = subprocess.Popen(
            [sys.executable, "-c", _PROBE, str(self._out), str(period), str(threshold), str(priority)],
            stdout=subprocess.PIPE,
            text=True,
        )
        assert process.stdout is not None
        line = process.stdout.readline().strip()
        if line != "ready":
            process.wait()
            process.stdout.close()
            self.refused = line or f"the probe exited with {process.returncode}"
        else:
            self._process = process
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        process, self._process = self._process, None
        try:
            if process is not None:
                process.terminate()
                process.wait(timeout=10)
                if process.stdout is not None:
                    process.stdout.close()
                late = json.loads(self._out.read_text()) if self._out.exists() else []
                self.blackouts = [Blackout(int(t) - round(ms * 1e6), float(ms)) for t, ms in late]
        finally:
            self._dir.cleanup()

    def overlapping(self, start_ns: int, end_ns: int) -> list[Blackout]:
        """The blackouts that overlap ``[start_ns, end_ns]`` [ns, wall clock]."""
        return [b for b in self.blackouts if b.start_ns <= end_ns and b.start_ns + b.ms * 1e6 >= start_ns]


def blackout_text(probe: RtBlackoutProbe, start_ns: int, end_ns: int) -> str:
    """One line on the real-time blackouts in ``[start_ns, end_ns]`` for a benchmark's report."""
    if probe.refused is not None:
        return f"real-time blackouts: not measured (the probe was refused SCHED_FIFO: {probe.refused})"
    seen = probe.overlapping(start_ns, end_ns)
    if not seen:
        return f"real-time blackouts: none (kernel RT throttling {rt_throttle_text()})"
    longest = max(b.ms for b in seen)
    return (
        f"real-time blackouts: {len(seen)}, longest {longest:.0f} ms: the kernel stopped every real-time "
        f"thread at once to run ordinary tasks (RT throttling {rt_throttle_text()}, or the fair server "
        "of kernels 6.12+): look for a busy ordinary process on the host"
    )


if __name__ == "__main__":  # a quick look at this host: 5 s of probing
    import time

    with RtBlackoutProbe() as p:
        t0 = time.time_ns()
        time.sleep(5.0)
    print(blackout_text(p, t0, time.time_ns()))
