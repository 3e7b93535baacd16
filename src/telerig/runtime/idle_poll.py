"""Idle CPUs that poll instead of halting while a rig runs, so a woken control thread starts at once.

A CPU with nothing to run halts until an interrupt wakes it. On bare metal that takes from a
microsecond (C1) to a few hundred (deep C-states); in a virtual machine the halt hands the vCPU
back to the hypervisor, and waking it means the host must schedule that vCPU's thread again.
Measured with the kernel's ``sched_switch``/``sched_wakeup`` trace on a 2-core VM during the
fleet benchmark (six robot processes): a thread woken onto an idle CPU started within 4 us at
p50, 0.26 ms at p90, but 20 ms at p99 and up to 228 ms; the robots' late ticks were such wake-ups
(the control thread woken on time, the CPU it was sent to idle, and nothing running on it for
18 ms). The same trace never showed such a delay on a CPU that was running something.

Real-time Linux hosts keep idle CPUs polling: ``idle=poll`` on the kernel command line, or a
PM QoS CPU latency request of 0 (``/dev/cpu_dma_latency``, held open), which makes the cpuidle
governor pick its polling state. :class:`IdlePoll` makes that request where the kernel has a
cpuidle driver and the request is allowed (root). Where it has none (virtual machines, which
halt through the architecture's default idle routine, and ignore the request) or the request is
refused, it runs one poller per CPU instead: a process pinned to that CPU under ``SCHED_IDLE``
that spins, so the CPU never halts and any thread that wakes preempts the poller at once. The
pollers need no privilege, take only CPU time nothing else wants, and end within milliseconds of
the process that started them (they watch their parent).

The price: the CPUs read 100 % busy and draw full power while the rig runs. Off by default
(``runtime.idle_poll`` in the rig); the fleet rig turns it on (benchmarks/fleet.py measures it).
"""

from __future__ import annotations

import logging
import os
import struct
import subprocess
import sys
import threading
from pathlib import Path
from subprocess import DEVNULL

__all__ = ["IdlePoll"]

log = logging.getLogger(__name__)

#: The PM QoS CPU latency request: a native int [us], in force while the file stays open.
PM_QOS = Path("/dev/cpu_dma_latency")
#: Which cpuidle driver the kernel runs (``none``, or missing, without one).
CPUIDLE_DRIVER = Path("/sys/devices/system/cpu/cpuidle/current_driver")

#: The poller: drops to SCHED_IDLE, pins itself, and spins until its parent is gone (checked every
#: few milliseconds: it is then reparented). It starts from a thread at SCHED_BATCH nice 19, so
#: it never runs above anything, not even while the interpreter starts.
_POLLER = """
import os, sys
cpu, parent = int(sys.argv[1]), int(sys.argv[2])
os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
os.sched_setaffinity(0, {cpu})
while os.getppid() == parent:
    for _ in range(100_000):
        pass
"""


class IdlePoll:
    """Keep this machine's CPUs from halting until :meth:`close` (see the module docs).

    Args:
        pm_qos: The PM QoS latency device; :data:`PM_QOS` by default.
        cpuidle_driver: The file naming the cpuidle driver; :data:`CPUIDLE_DRIVER` by default.
    """

    def __init__(self, *, pm_qos: Path = PM_QOS, cpuidle_driver: Path = CPUIDLE_DRIVER) -> None:
        self._pm_qos = pm_qos
        self._driver = cpuidle_driver
        self._request: int | None = None  # the open PM QoS file
        self._pollers: list[subprocess.Popen[bytes]] = []
        self._how = "off"  # what start() did; with pollers, why they were needed

    @property
    def how(self) -> str:
        """What keeps the CPUs awake, e.g. ``"PM QoS cpu_dma_latency 0 us (intel_idle)"`` or ``"2
        SCHED_IDLE pollers (no cpuidle driver)"`` (``"1 of 2 ..."`` once one has exited, as one
        refused ``SCHED_IDLE`` does); ``"off"`` before :meth:`start` and after :meth:`close`."""
        if not self._pollers:
            return self._how
        started = len(self._pollers)
        running = len(self.pollers)
        count = str(started) if running == started else f"{running} of {started}"
        return f"{count} SCHED_IDLE pollers ({self._how})"

    @property
    def pollers(self) -> tuple[int, ...]:
        """Process ids of the pollers still running."""
        return tuple(p.pid for p in self._pollers if p.poll() is None)

    def start(self) -> IdlePoll:
        """Make the PM QoS request, or start the pollers. Never raises: where a poller cannot
        start, the CPUs stay as they were, with one warning (a poller refused ``SCHED_IDLE`` exits
        at once rather than spin above it)."""
        if self.how != "off":
            return self
        if sys.platform != "linux":
            self._how = "unavailable (not Linux)"
            return self
        driver = _read(self._driver)
        reason = "no cpuidle driver" if driver in ("", "none") else ""
        if not reason:
            try:
                self._request = os.open(self._pm_qos, os.O_WRONLY)
                os.write(self._request, struct.pack("=i", 0))
                self._how = f"PM QoS {self._pm_qos.name} 0 us ({driver})"
                log.info("idle CPUs poll: %s", self.how)
                return self
            except OSError as exc:
                self._close_request()
                reason = f"PM QoS refused: {exc.strerror}"
        try:
            self._pollers = _spawn_pollers(sorted(os.sched_getaffinity(0)))
        except OSError as exc:
            self.close()
            log.warning("idle CPUs will halt (runtime.idle_poll): cannot start a poller: %s", exc)
            self._how = f"refused ({exc})"
            return self
        self._how = reason
        log.info("idle CPUs poll: %s", self.how)
        return self

    def close(self) -> None:
        """Withdraw the request and stop the pollers. Idempotent."""
        self._close_request()
        for poller in self._pollers:
            poller.kill()
            poller.wait()
        self._pollers.clear()
        self._how = "off"

    def _close_request(self) -> None:
        if self._request is not None:
            os.close(self._request)
            self._request = None

    def __enter__(self) -> IdlePoll:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()


def _spawn_pollers(cpus: list[int]) -> list[subprocess.Popen[bytes]]:
    """Start a poller per CPU in ``cpus`` from a thread of its own at ``SCHED_BATCH`` nice 19 (a
    process starts with its creator thread's policy, and the station's threads may be real-time).

    Raises:
        OSError: a poller did not start (the ones that did are stopped).
    """
    pollers: list[subprocess.Popen[bytes]] = []
    failed: list[OSError] = []

    def spawn() -> None:
        try:
            os.sched_setscheduler(0, os.SCHED_BATCH, os.sched_param(0))
            os.setpriority(os.PRIO_PROCESS, 0, 19)
            for cpu in cpus:
                argv = [sys.executable, "-I", "-S", "-c", _POLLER, str(cpu), str(os.getpid())]
                pollers.append(subprocess.Popen(argv, stdin=DEVNULL, stdout=DEVNULL, stderr=DEVNULL))
        except OSError as exc:
            failed.append(exc)

    thread = threading.Thread(target=spawn, name="idle-poll-spawn")
    thread.start()
    thread.join()
    if failed:
        for poller in pollers:
            poller.kill()
            poller.wait()
        raise failed[0]
    return pollers


def _read(path: Path) -> str:
    try:
        return path.read_text().strip()
    except OSError:
        return ""
