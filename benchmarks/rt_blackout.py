"""Moments the kernel stopped every real-time thread at once, seen by a probe above all of them.

A robot's control thread under ``SCHED_RR`` preempts every ordinary task, but not the kernel's own
reservations for them: classic RT throttling (real-time threads may run
``kernel.sched_rt_runtime_us`` of every ``sched_rt_period_us``, 950 of 1000 ms) and, on kernels
6.12 and later, the *fair server*, which gives ordinary tasks starved by real-time ones up to 50 ms
of each second at a priority above every real-time thread. Either stops every real-time thread on
that CPU for up to 50 ms, whatever its priority.

Seen on this 2-core VM (kernel 6.18) on 2026-11-28 with an ordinary process spinning at nice 0
beside the fleet benchmark: in 9 of 22 runs a SCHED_FIFO 50 probe (one, unpinned) woke ~50 ms late
once a second, often for several seconds in a row, within 0.1 s of every robot missing ~5 ticks
(those runs: 34-572 missed ticks; the other 13: 0-49, at most 2 in 11). A kernel trace of one
showed CPU 0 handed to the ordinary tasks for 50 ms each second while real-time threads waited, the
probe among them. Turning RT throttling off (``kernel.sched_rt_runtime_us=-1``) did not stop it:
blackouts in 2 of 10 runs with it off, 7 of 12 with it on. With the spinning process gone, 10 runs:
no blackout, 0 missed ticks in 8.

:class:`RtBlackoutProbe` runs such a probe on each CPU, a process of its own pinned there at
``SCHED_FIFO`` ``priority``, that sleeps ``period_ms`` at a time and notes each wake-up later than
``threshold_ms``: a stall no telerig thread on that CPU, at any priority it uses, could have
escaped, and a benchmark can tell its own missed ticks from the host's. It needs the right to
real-time scheduling (root or CAP_SYS_NICE); without it :attr:`RtBlackoutProbe.not_measured` says why and
the benchmark says it did not measure.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType

# The probe's loop: nothing imported beyond the standard library, pinned to one CPU, one wake-up
# per period.
_PROBE = """
import json, os, signal, sys, time
out, period, threshold = sys.argv[1], float(sys.argv[2]), float(sys.argv[3])
priority, cpu = int(sys.argv[4]), int(sys.argv[5])
try:
    os.sched_setaffinity(0, {cpu})
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
except OSError as exc:
    print(exc, flush=True)
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
    """One late wake-up of the probe on ``cpu``: from ``start_ns`` [ns, wall clock] for ``ms`` [ms]."""

    cpu: int
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
    """Context manager: a ``SCHED_FIFO`` probe process on each CPU while the block runs;
    :attr:`blackouts` after.

    One per CPU, pinned: a real-time thread on a CPU the kernel has given to ordinary tasks is not
    moved to the other one (a kernel trace showed the other CPU running an RR 10 thread for the whole
    50 ms while the FIFO 50 probe waited), so a single probe sees only its own CPU's blackouts.

    Args:
        priority: The probes' real-time priority; above every thread of the rig.
        period_ms: How long each sleeps at a time [ms].
        threshold_ms: A wake-up later than this is a blackout [ms].
    """

    def __init__(self, priority: int = 50, period_ms: float = 5.0, threshold_ms: float = 10.0) -> None:
        if not (1 <= priority <= 99 and period_ms > 0 and threshold_ms > 0):
            raise ValueError(
                f"priority must be 1..99 and the times > 0, got {priority}, {period_ms}, {threshold_ms}"
            )
        self._args = (period_ms / 1e3, threshold_ms / 1e3, priority)
        self._dir = tempfile.TemporaryDirectory(prefix="telerig-rt-probe-")
        self._processes: dict[int, subprocess.Popen[str]] = {}
        #: Why the probes did not watch every CPU to the end (no right to real-time scheduling, a
        #: probe that died), or None.
        self.not_measured: str | None = None
        #: The probes' late wake-ups, by time; empty until the block ends.
        self.blackouts: list[Blackout] = []

    @property
    def running(self) -> bool:
        """Whether the probes run (inside the block, unless they were refused)."""
        return bool(self._processes)

    @property
    def pids(self) -> dict[int, int]:
        """The probe process on each CPU, by CPU, while they run."""
        return {cpu: process.pid for cpu, process in self._processes.items()}

    def _out(self, cpu: int) -> Path:
        return Path(self._dir.name) / f"late-{cpu}.json"

    def __enter__(self) -> RtBlackoutProbe:
        period, threshold, priority = self._args
        for cpu in sorted(os.sched_getaffinity(0)):
            args = [str(self._out(cpu)), str(period), str(threshold), str(priority), str(cpu)]
            process = subprocess.Popen(
                [sys.executable, "-c", _PROBE, *args], stdout=subprocess.PIPE, text=True
            )
            assert process.stdout is not None
            line = process.stdout.readline().strip()
            if line != "ready":
                process.wait()
                process.stdout.close()
                why = line or f"exit {process.returncode}"
                self.not_measured = f"a probe could not pin itself to CPU {cpu} or take SCHED_FIFO: {why}"
                self._stop()
                break
            self._processes[cpu] = process
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        try:
            self._stop()
        finally:
            self._dir.cleanup()

    def _stop(self) -> None:
        processes, self._processes = self._processes, {}
        for process in processes.values():
            process.terminate()
        for cpu, process in processes.items():
            try:
                process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
            if process.stdout is not None:
                process.stdout.close()
            try:
                late = json.loads(self._out(cpu).read_text())
                self.blackouts += [Blackout(cpu, int(t) - round(ms * 1e6), float(ms)) for t, ms in late]
            except (OSError, ValueError, TypeError):
                # A probe that died (killed, out of memory) wrote nothing: its CPU was not watched
                # to the end, and "no blackout" would be a claim nobody measured.
                self.not_measured = self.not_measured or (
                    f"the probe on CPU {cpu} ended without its result (exit {process.returncode})"
                )
        self.blackouts.sort(key=lambda b: b.start_ns)

    def overlapping(self, start_ns: int, end_ns: int) -> list[Blackout]:
        """The blackouts that overlap ``[start_ns, end_ns]`` [ns, wall clock]."""
        return [b for b in self.blackouts if b.start_ns <= end_ns and b.start_ns + b.ms * 1e6 >= start_ns]


def blackout_text(probe: RtBlackoutProbe, start_ns: int, end_ns: int) -> str:
    """One line on the real-time blackouts in ``[start_ns, end_ns]`` for a benchmark's report."""
    if probe.not_measured is not None:
        return f"real-time blackouts: not measured ({probe.not_measured})"
    seen = probe.overlapping(start_ns, end_ns)
    if not seen:
        return f"real-time blackouts: none (kernel RT throttling {rt_throttle_text()})"
    longest = max(b.ms for b in seen)
    cpus = ", ".join(str(c) for c in sorted({b.cpu for b in seen}))
    return (
        f"real-time blackouts: {len(seen)} (CPU {cpus}), longest {longest:.0f} ms: the kernel stopped every "
        f"real-time thread on a CPU to run ordinary tasks (RT throttling {rt_throttle_text()}, or the "
        "fair server of kernels 6.12+): look for a busy ordinary process on the host"
    )


if __name__ == "__main__":  # a quick look at this host: 5 s of probing
    import time

    with RtBlackoutProbe() as p:
        t0 = time.time_ns()
        time.sleep(5.0)
    print(blackout_text(p, t0, time.time_ns()))
