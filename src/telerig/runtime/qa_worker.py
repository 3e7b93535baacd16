"""The station's quality-gate worker: after each commit, the gates run in one low-priority child process.

The gates decode the episode's MCAP log and replay its joint states through the robot's collision
model: about 10 s of CPU per episode-minute that must not compete with the next episode's control
loops, recorder and encoders. So they run off the control path, in a separate process (no GIL
shared with the station), one episode at a time, never above the station: the process is started
from a dispatcher thread that has left the station's policy (``SCHED_RR`` included) for
``SCHED_OTHER`` at :data:`QA_NICE` steps nicer, and it drops again itself.

While an episode records (``qa.while_recording``):

* ``idle`` (the default): the process runs under ``SCHED_IDLE``, from its start: the kernel gives
  it only CPU time no other thread of the host wants, and a waking thread of any other policy
  preempts it at once. A station recording back to back keeps its verdicts coming.
* ``pause``: it is stopped (``SIGSTOP``) until the episode ends (:meth:`QaWorker.pause`), like
  the uploads. This was the only behaviour until the hour-long soak (``benchmarks/soak.py``,
  2026-11-27): a station recording 15 s episodes back to back with 0.5 s between them gave the
  gates 2.2 s of CPU in 34 minutes and no verdict at all after 128 episodes, the backlog growing
  without end. Before that, ``benchmarks/qa_background.py`` had found that at nice 10 alone the
  gates cost the episode recorded beside them 20 % of its robot states (75 instead of 95 per
  second on a loaded 2-core host).

The child writes ``qa.json``, moves a rejected episode to ``failures`` and writes the index
(:func:`telerig.qa.checker.check_episode`); a kill at any point leaves what ``telerig qa`` finishes.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import pickle
import queue
import signal
import subprocess
import sys
import threading
from concurrent.futures import CancelledError, Future
from pathlib import Path
from typing import IO, Any

from telerig.config.qa import QaThresholds
from telerig.qa.checker import QaOutcome

__all__ = ["QA_NICE", "QaWorker", "outcome_or_none"]

_log = logging.getLogger("telerig.runtime.qa_worker")

#: How much nicer than the station the gate process runs [Linux nice steps; capped at 19]. 10 steps
#: weigh about a tenth of the station's threads in the CFS scheduler when they compete, so a
#: recording never waits long for it; between episodes it has the machine.
QA_NICE = 10
_MAX_NICE = 19


def _lower_priority(nice: int, *, idle: bool = False, tid: int = 0) -> None:
    """Thread ``tid`` (0: the calling one; Linux: niceness and policy are per thread) to
    ``SCHED_OTHER`` (``SCHED_IDLE`` with ``idle``) at niceness ``nice`` (absolute), or stays where
    it is if already nicer; threads it starts afterwards inherit both."""
    tid = tid or threading.get_native_id()
    try:
        policy = os.SCHED_IDLE if idle else os.SCHED_OTHER
        if os.sched_getscheduler(tid) != policy:
            os.sched_setscheduler(tid, policy, os.sched_param(0))
    except (OSError, AttributeError) as exc:  # pragma: no cover - not Linux, or a sandbox without the call
        _log.debug("cannot change the scheduling policy: %s", exc)
    try:
        os.setpriority(os.PRIO_PROCESS, tid, max(os.getpriority(os.PRIO_PROCESS, tid), nice))
    except OSError as exc:  # pragma: no cover - raising niceness is always allowed on Linux
        _log.debug("cannot lower the priority: %s", exc)


def _lower_process(nice: int, *, idle: bool) -> None:
    """Every thread of this process (numpy's, started when the module's imports ran, too)."""
    me = threading.get_native_id()
    with contextlib.suppress(OSError):
        for tid in (int(t) for t in os.listdir("/proc/self/task")):
            if tid != me:
                with contextlib.suppress(OSError):  # ended meanwhile
                    _lower_priority(nice, idle=idle, tid=tid)
    _lower_priority(nice, idle=idle)


def _station_nice() -> int:
    return os.getpriority(os.PRIO_PROCESS, threading.get_native_id())


# --- in the child process ---------------------------------------------------------------------------
# The channel is pickles over the child's stdin/stdout (its own stdout goes to stderr, so a stray print
# cannot corrupt it). A plain subprocess, not multiprocessing: the latter's spawn also starts a resource
# tracker process that outlives the station by a moment, and a pool cannot cut one check short.


def _serve(channel_in: IO[bytes], channel_out: IO[bytes], nice: int, *, idle: bool = False) -> None:
    """The gate process: check each ``(root, id, thresholds, index)`` it receives, answer
    ``(True, outcome)`` or ``(False, message)``, until ``None`` or the pipe closes."""
    _lower_process(nice, idle=idle)
    from telerig.qa.checker import check_episode  # numpy, MuJoCo, the MCAP reader: now, not per episode
    from telerig.store.episodes import EpisodeStore
    from telerig.store.index import EpisodeIndex

    def send(message: object) -> None:
        pickle.dump(message, channel_out, protocol=pickle.HIGHEST_PROTOCOL)
        channel_out.flush()

    send((True, os.getpid()))
    indexes: dict[str, EpisodeIndex] = {}
    try:
        while (job := pickle.load(channel_in)) is not None:
            root, episode_id, thresholds_json, index_target = job
            try:
                index = None
                if index_target is not None:
                    if index_target not in indexes:
                        indexes[index_target] = EpisodeIndex.open(index_target)
                    index = indexes[index_target]
                thresholds = QaThresholds.model_validate_json(thresholds_json)
                outcome = check_episode(EpisodeStore(root), episode_id, thresholds, index=index)
            except Exception as exc:  # the station logs it; the episode stays unchecked
                send((False, f"{type(exc).__name__}: {exc}"))
            else:
                send((True, outcome))
    except (EOFError, OSError, KeyboardInterrupt):  # the station went away (or Ctrl-C reached the group)
        pass
    finally:
        for index in indexes.values():
            index.close()


_PR_SET_PDEATHSIG = 1  # linux/prctl.h


def _die_with_the_station(station_pid: int) -> None:
    """A stopped (paused) process never sees its stdin close, so a station killed while an episode
    records would leave it stopped forever: ask the kernel to SIGKILL it when the station's
    dispatcher thread dies (Linux ``PR_SET_PDEATHSIG``; SIGKILL ends a stopped process too), and
    end at once if the station is already gone."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    except (OSError, AttributeError):  # pragma: no cover - not Linux
        return
    if os.getppid() != station_pid:
        os._exit(0)


def _child_main() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the station's: it ends this process
    if len(sys.argv) > 2:
        _die_with_the_station(int(sys.argv[2]))
    channel_out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)  # print() in anything imported goes to stderr, not into the channel
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    nice = int(sys.argv[1]) if len(sys.argv) > 1 else QA_NICE
    _serve(sys.stdin.buffer, channel_out, nice, idle=len(sys.argv) > 3 and sys.argv[3] == "idle")


# --- in the station ---------------------------------------------------------------------------------


class QaWorker:
    """Runs :func:`telerig.qa.checker.check_episode` on each submitted episode, in submission order,
    in one child process :data:`QA_NICE` steps nicer than the station (under ``SCHED_IDLE`` with
    ``thresholds.while_recording == "idle"``).

    The constructor has no side effects; :meth:`start` starts the dispatcher thread, which starts
    the process, where the gates are imported before the first episode ends.

    Args:
        root: The station's data root.
        thresholds: The rig's ``qa:`` section.
        index_target: The index the verdicts go to (data root, file or URL); ``None`` for none.
        nice: How much nicer than the station the process runs [nice steps].
    """

    def __init__(
        self,
        root: Path,
        thresholds: QaThresholds,
        *,
        index_target: str | Path | None,
        nice: int = QA_NICE,
    ) -> None:
        self._root = str(root)
        self._thresholds = thresholds.model_dump_json()
        self._index = None if index_target is None else str(index_target)
        self._nice = nice
        # thresholds.while_recording: "idle" runs the process under SCHED_IDLE and pause() leaves
        # it running; "pause" makes pause() stop it (see the module docs).
        self._stops = thresholds.while_recording == "pause"
        self._idle = thresholds.while_recording == "idle"
        self._jobs: queue.SimpleQueue[tuple[str, Future[QaOutcome]] | None] = queue.SimpleQueue()
        self._thread: threading.Thread | None = None
        self._process: subprocess.Popen[bytes] | None = None
        self._closed = False
        self._paused = False
        self._signal_lock = threading.Lock()  # pause/resume vs. the process starting and ending
        self._stopped = threading.Event()  # the dispatcher has ended: nothing submitted runs any more
        #: Pid of the gate process once it is up (for tests and diagnostics).
        self.pid: int | None = None

    def start(self) -> None:
        """Start the dispatcher thread (idempotent)."""
        if self._thread is None and not self._closed:
            self._thread = threading.Thread(target=self._dispatch, name="telerig-qa", daemon=True)
            self._thread.start()

    def submit(self, episode_id: str) -> Future[QaOutcome]:
        """Queue a committed episode; the future gets its outcome, or the exception that stopped it."""
        future: Future[QaOutcome] = Future()
        if self._closed or self._stopped.is_set():
            future.cancel()
            return future
        self.start()
        self._jobs.put((episode_id, future))
        if self._stopped.is_set():  # it ended meanwhile (its process would not start)
            self._cancel_queued()
        return future

    def pause(self) -> None:
        """An episode starts recording: with ``thresholds.while_recording == "pause"``, stop the gate process
        (``SIGSTOP``) until :meth:`resume`; under ``SCHED_IDLE`` it runs on."""
        with self._signal_lock:
            self._paused = True
            if self._stops:
                self._signal(signal.SIGSTOP)

    def resume(self) -> None:
        """Let the gate process run again (``SIGCONT``)."""
        with self._signal_lock:
            self._paused = False
            self._signal(signal.SIGCONT)

    @property
    def paused(self) -> bool:
        """Whether :meth:`pause` is in effect."""
        return self._paused

    def _signal(self, signum: int) -> None:
        process = self._process
        if process is not None and process.returncode is None:
            with contextlib.suppress(ProcessLookupError):
                process.send_signal(signum)

    def close(self, grace_s: float = 2.0) -> None:
        """Cancel the episodes not started; a check still running after ``grace_s`` [s] is cut short
        (its process terminated: the check is crash-safe and ``telerig qa`` finishes it). Idempotent."""
        if self._closed:
            return
        self._closed = True
        self.resume()  # a stopped process can neither finish nor end
        self._jobs.put(None)
        thread, self._thread = self._thread, None
        if thread is None:
            return
        thread.join(grace_s)
        process = self._process
        if thread.is_alive() and process is not None:
            _log.info("quality gates cut short at close; telerig qa checks that episode")
            process.terminate()
        thread.join(10.0)

    def __enter__(self) -> QaWorker:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _dispatch(self) -> None:
        target = min(_MAX_NICE, _station_nice() + self._nice)
        _lower_priority(target)  # the process starts from this thread and inherits its priority
        process: subprocess.Popen[bytes] | None = None
        try:
            # A fresh interpreter (no fork: the station has threads whose locks a fork would copy held).
            process = subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "telerig.runtime.qa_worker",
                    str(target),
                    str(os.getpid()),
                    "idle" if self._idle else "other",
                ],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                close_fds=True,
            )
            with self._signal_lock:
                self._process = process
                if self._paused and self._stops:  # an episode started while it was starting
                    self._signal(signal.SIGSTOP)
            channel_in, channel_out = process.stdout, process.stdin
            if channel_in is None or channel_out is None:  # pragma: no cover - PIPE was asked for
                raise RuntimeError("no pipe to the quality-gate process")
            _, self.pid = _receive(channel_in)
            while (job := self._jobs.get()) is not None:
                episode_id, future = job
                if self._closed:
                    future.cancel()
                if not future.set_running_or_notify_cancel():
                    continue
                try:
                    pickle.dump((self._root, episode_id, self._thresholds, self._index), channel_out)
                    channel_out.flush()
                    ok, value = _receive(channel_in)
                except (EOFError, OSError, pickle.UnpicklingError) as exc:  # it died, or close() cut it short
                    future.set_exception(RuntimeError(f"the quality-gate process ended: {exc or 'EOF'}"))
                    break
                if ok:
                    future.set_result(value)
                else:
                    _log.warning("quality gates on %s failed: %s", episode_id, value)
                    future.set_exception(RuntimeError(value))
        except Exception as exc:  # the process could not start: every queued episode stays unchecked
            _log.warning("quality-gate worker stopped: %s", exc)
        finally:
            self._stopped.set()
            self._cancel_queued()
            if process is not None:
                with self._signal_lock:
                    self._signal(signal.SIGCONT)
                    self._process = None
                _end(process)

    def _cancel_queued(self) -> None:
        while True:
            try:
                job = self._jobs.get_nowait()
            except queue.Empty:
                return
            if job is not None:
                job[1].cancel()


def _receive(channel: IO[bytes]) -> Any:
    return pickle.load(channel)  # our own child, over a private pipe


def _end(process: subprocess.Popen[bytes]) -> None:
    """Ask the child to stop (EOF on its stdin), then terminate it if it does not; always reaped."""
    for stream in (process.stdin, process.stdout):
        if stream is not None:
            with contextlib.suppress(OSError):
                stream.close()
    try:
        process.wait(5.0)
    except subprocess.TimeoutExpired:
        process.terminate()
        try:
            process.wait(5.0)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def outcome_or_none(future: Future[QaOutcome], timeout_s: float) -> QaOutcome | None:
    """The future's outcome within ``timeout_s``; ``None`` when it is not ready, failed or was cancelled."""
    try:
        return future.result(timeout_s)
    except (CancelledError, TimeoutError, Exception):
        return None


if __name__ == "__main__":
    _child_main()
