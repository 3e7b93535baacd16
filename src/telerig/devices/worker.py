"""The thread a device runs on: start / stop / running, and sink delivery that never raises."""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable, Iterator
from typing import Protocol, TypeVarTuple

from telerig.devices.base import SampleSink
from telerig.errors import DeviceError
from telerig.ir.types import Sample, now_ns

__all__ = ["DeviceWorker", "FixedRate", "Launch", "PlaybackClock", "wait_until"]

Ts = TypeVarTuple("Ts")


class Launch(Protocol):
    """Starts the worker thread: ``launch(target, *args)`` runs ``target(*args, stop)`` on it.

    Returns the run's stop event (set by :meth:`DeviceWorker.stop`), for helper threads of the run.
    """

    def __call__(self, target: Callable[[*Ts, threading.Event], None], /, *args: *Ts) -> threading.Event: ...


class DeviceWorker:
    """One device's worker thread, owned by the device (composition: the device keeps its own API).

    ``start`` raises :class:`DeviceError` while a thread runs, else runs ``target(*args, stop)`` on
    a new daemon thread with a fresh stop event per run, so a late ``stop()`` of an old run never
    leaks into a new one. ``stop`` sets the event and joins the thread (unless called from it);
    it is idempotent. ``deliver`` hands a sample to the sink and never raises: it counts
    :attr:`samples` (attempts) and :attr:`sink_errors`, and logs the first sink error of each run.
    """

    def __init__(self, device_id: str, *, kind: str, thread_name: str, log: logging.Logger) -> None:
        """Args:
        device_id: The owning device's id, for messages and logs.
        kind: What the device is, e.g. ``"glove"``: "glove 'g0' is already running; ...".
        thread_name: Name of the thread, e.g. ``"telerig-glove-g0"``.
        log: The device module's logger; sink errors are logged there.
        """
        self._id = device_id
        self._kind = kind
        self._thread_name = thread_name
        self._log = log
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._sink_logged = False
        #: Samples handed to :meth:`deliver` since construction (including those the sink raised on).
        self.samples = 0
        #: Exceptions the sink raised since construction.
        self.sink_errors = 0

    @property
    def running(self) -> bool:
        """Whether the thread is running (false once its target returned)."""
        thread = self._thread
        return thread is not None and thread.is_alive()

    def start(self, target: Callable[[*Ts, threading.Event], None], *args: *Ts) -> None:
        """Run ``target(*args, stop)`` on a new thread.

        Raises:
            DeviceError: If the thread is already running.
        """
        with self.starting() as launch:
            launch(target, *args)

    @contextlib.contextmanager
    def starting(self) -> Iterator[Launch]:
        """Hold the start lock and yield ``launch``, for a start that prepares something first.

        The body opens what the run needs (a socket, a device node) and then calls ``launch``;
        if it raises before that, the device stays stopped.

        Raises:
            DeviceError: If the thread is already running.
        """
        with self._lock:
            if self._thread is not None:
                raise DeviceError(f"{self._kind} '{self._id}' is already running; call stop() first")
            yield self._launch

    def _launch(self, target: Callable[[*Ts, threading.Event], None], /, *args: *Ts) -> threading.Event:
        stop = self._stop = threading.Event()
        self._sink_logged = False
        self._thread = threading.Thread(
            target=target, args=(*args, stop), name=self._thread_name, daemon=True
        )
        self._thread.start()
        return stop

    def stop(self, wake: Callable[[], None] | None = None) -> None:
        """Set the stop event and join the thread. Idempotent.

        Args:
            wake: Called after the event is set and before joining, when a thread runs, to
                interrupt a wait the event cannot (e.g. cancel an asyncio task).
        """
        with self._lock:
            thread, self._thread = self._thread, None
            self._stop.set()
        if thread is None:
            return
        if wake is not None:
            wake()
        if thread is not threading.current_thread():
            thread.join()

    def wait(self, timeout: float | None = None) -> bool:
        """Block until the thread's target returns; ``timeout`` [s]. True when no thread runs."""
        thread = self._thread
        if thread is not None:
            thread.join(timeout)
            return not thread.is_alive()
        return True

    def deliver(self, sink: SampleSink, sample: Sample) -> bool:
        """Call ``sink(sample)``; an exception is counted, logged the first time in a run, not raised.

        Returns:
            Whether the sink returned without raising.
        """
        self.samples += 1
        try:
            sink(sample)
        except Exception:
            self.sink_errors += 1
            if not self._sink_logged:
                self._sink_logged = True
                self._log.exception("%s: sample sink raised; continuing", self._id)
            return False
        return True


def wait_until(deadline: float, stop: threading.Event) -> bool:
    """Sleep until ``deadline`` [s, ``time.perf_counter()`` clock] unless ``stop`` is set first.

    Returns:
        Whether ``stop`` is set (the caller returns instead of emitting).
    """
    delay = deadline - time.perf_counter()
    if delay > 0.0 and stop.wait(delay):
        return True
    return stop.is_set()


class PlaybackClock:
    """Paces a recorded stream in real time and stamps each sample with the moment it fell due.

    It sleeps on ``time.perf_counter`` (monotonic) and stamps on the common clock
    (:func:`~telerig.ir.types.now_ns`), both read once at construction. A thread that wakes late (a
    stalled host) emits the samples it owes back to back, each stamped with its own due time, so the
    stream keeps its recorded spacing: the validator sees the recorded motion, not a burst of
    jumps. A stamp is never later than the time it is read (a common clock slewed behind the
    monotonic one is clamped to now).
    """

    __slots__ = ("_t0", "_t0_ns")

    def __init__(self) -> None:
        self._t0 = time.perf_counter()
        self._t0_ns = now_ns()

    def wait(self, offset_s: float, stop: threading.Event) -> int | None:
        """Sleep until ``offset_s`` [s] after construction unless ``stop`` is set first.

        Returns:
            The common-clock time [ns] at which the moment fell due, or ``None`` once ``stop`` is set.
        """
        if wait_until(self._t0 + offset_s, stop):
            return None
        return min(self._t0_ns + round(offset_s * 1e9), now_ns())


class FixedRate:
    """A device thread's fixed-rate tick loop: absolute deadlines, no drift, no bursts.

    Tick ``k`` is due ``k / rate_hz`` seconds after the loop starts; a late tick skips the ticks it
    missed (counted in :attr:`overruns`) instead of firing them in a burst.
    """

    def __init__(self, rate_hz: float) -> None:
        """Args:
        rate_hz: Tick rate [Hz] (> 0; the device checks its own upper bound).
        """
        if not rate_hz > 0.0:
            raise ValueError(f"rate_hz must be > 0, got {rate_hz}")
        self.period_s = 1.0 / rate_hz
        #: Ticks skipped because a tick ran late, since construction (all runs).
        self.overruns = 0

    def ticks(self, stop: threading.Event) -> Iterator[tuple[int, float]]:
        """Yield ``(device_ns, t_s)`` at each deadline until ``stop`` is set.

        ``device_ns`` is ``time.perf_counter_ns()`` at the tick; ``t_s`` [s] is the time since the
        loop started, on the same clock.
        """
        period = self.period_s
        t0 = time.perf_counter()
        k = 0
        while True:
            # Absolute deadlines from t0: no drift; a late tick skips ahead instead of bursting.
            if wait_until(t0 + k * period, stop):
                return
            device_ns = time.perf_counter_ns()
            yield device_ns, device_ns * 1e-9 - t0
            k += 1
            behind = int((time.perf_counter() - t0) / period) - k
            if behind > 0:
                self.overruns += behind
                k += behind
