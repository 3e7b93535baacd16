"""Recorder: the bus delivery thread only queues; a writer thread below the control loops records.

A writer that runs behind (a station short of CPU) must lose nothing received during the episode,
raise no stall for messages it still holds, and bound what it holds.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from telerig import priority
from telerig.bus.base import Message
from telerig.bus.memory import InMemoryBus
from telerig.ir import wire
from telerig.ir.mcap_log import iter_raw
from telerig.ir.types import JointState, Stamp, now_ns
from telerig.record import recorder as recorder_module
from telerig.record.recorder import Recorder

_TOPIC = "telerig/v1/rig/arm0/joint_state"


def _joint_state(seq: int) -> bytes:
    t = now_ns()
    stamp = Stamp("arm0", seq, t, t)
    return wire.encode(JointState(stamp, ("j1",), np.zeros(1), np.zeros(1)))


def _recording(tmp_path: Path) -> tuple[InMemoryBus, Recorder, Path]:
    """A recorder on an in-memory bus, recording an episode to ``tmp_path / "episode.mcap"``."""
    bus = InMemoryBus()
    recorder = Recorder("rig", bus, {})
    path = tmp_path / "episode.mcap"
    recorder.start(path)
    return bus, recorder, path


def _seqs(path: Path) -> list[int]:
    """Sequence numbers of the joint states recorded in ``path``, in log order."""
    return [wire.decode(payload).stamp.seq for topic, payload, *_ in iter_raw(path) if topic == _TOPIC]


def _await_writer(recorder: Recorder) -> None:
    """Until the writer thread has taken every queued message (5 s at most)."""
    deadline = time.monotonic() + 5.0
    while recorder._oldest_queued_ns() is not None and time.monotonic() < deadline:
        time.sleep(0.005)
    with recorder._lock:  # and finished the batch it took
        pass


def test_newest_counts_what_the_writer_has_not_reached(tmp_path: Path) -> None:
    bus = InMemoryBus()
    recorder = Recorder("rig", bus, {})
    recorder.start(tmp_path / "episode.mcap")
    recorder._closed = True  # end the writer thread: only newest() itself can write now
    recorder._queued.set()
    recorder._writer.join(timeout=5.0)
    for seq in range(1, 11):
        bus.publish(_TOPIC, _joint_state(seq))
    count = recorder.newest("joint_state")[_TOPIC][1]  # the episode's end waits on this
    recorder.close()
    assert count == 10


def test_messages_the_writer_has_not_reached_are_written_when_the_episode_stops(tmp_path: Path) -> None:
    bus, recorder, path = _recording(tmp_path)
    with recorder._lock:  # the writer thread cannot write while the test holds the recorder's lock
        for seq in range(1, 501):
            bus.publish(_TOPIC, _joint_state(seq))
        queued = len(recorder._queue)
    recorder.close()
    assert queued >= 500  # all of them were still waiting for the writer (and the health reports)
    seqs = _seqs(path)
    assert seqs == list(range(1, 501))
    assert not recorder._writer.is_alive()


def test_the_writer_thread_records_while_the_episode_runs(tmp_path: Path) -> None:
    bus = InMemoryBus()
    recorder = Recorder("rig", bus, {})
    recorder.start(tmp_path / "episode.mcap")
    for seq in range(1, 101):
        bus.publish(_TOPIC, _joint_state(seq))
    _await_writer(recorder)
    with recorder._lock:
        assert len(recorder.capture_times.times[_TOPIC]) == 100  # written before stop(), by the writer
    recorder.close()


def test_the_health_monitor_learns_the_oldest_message_the_writer_still_holds(tmp_path: Path) -> None:
    bus = InMemoryBus()
    recorder = Recorder("rig", bus, {})
    recorder.start(tmp_path / "episode.mcap")
    assert recorder._oldest_queued_ns() is None
    with recorder._lock:  # the writer is held
        first = Message(_TOPIC, _joint_state(1), now_ns())
        recorder._on_message(first)
        recorder._on_message(Message(_TOPIC, _joint_state(2), now_ns()))
        assert recorder._oldest_queued_ns() == first.received_ns
    recorder.close()
    assert recorder._oldest_queued_ns() is None


def test_the_queue_is_bounded_and_what_it_refuses_is_counted(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(recorder_module, "MAX_QUEUED", 50)
    bus, recorder, path = _recording(tmp_path)
    with recorder._lock:
        for seq in range(1, 81):
            bus.publish(_TOPIC, _joint_state(seq))
    recorder.close()
    seqs = _seqs(path)
    # The first ones in order (the recorder's own health report may take a place), the rest refused.
    assert 49 <= len(seqs) <= 50
    assert seqs == list(range(1, len(seqs) + 1))
    assert recorder.queue_overflow >= 80 - len(seqs)


def test_what_arrives_between_episodes_goes_into_none(tmp_path: Path) -> None:
    bus = InMemoryBus()
    recorder = Recorder("rig", bus, {})
    recorder.start(tmp_path / "one.mcap")
    bus.publish(_TOPIC, _joint_state(1))
    recorder.stop()
    bus.publish(_TOPIC, _joint_state(2))  # no episode: not queued
    # A message the writer still held as stop() closed the log (it arrived during the close).
    recorder._queue.append(Message(_TOPIC, _joint_state(3), now_ns()))
    recorder.start(tmp_path / "two.mcap")
    bus.publish(_TOPIC, _joint_state(4))
    recorder.close()
    first = _seqs(tmp_path / "one.mcap")
    second = _seqs(tmp_path / "two.mcap")
    assert (first, second) == ([1], [4])


def test_a_bug_while_writing_one_message_leaves_the_writer_running(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    bus, recorder, path = _recording(tmp_path)
    real = recorder._record
    calls = iter(range(1_000_000))

    def record_failing_once(mcap, message, node):  # type: ignore[no-untyped-def]
        if next(calls) == 0:
            raise KeyError("a bug")
        real(mcap, message, node)

    monkeypatch.setattr(recorder, "_record", record_failing_once)
    for seq in range(1, 4):
        bus.publish(_TOPIC, _joint_state(seq))
    _await_writer(recorder)
    assert recorder._writer.is_alive()
    assert recorder.write_bugs == 1  # counted by the writer thread, before stop()
    recorder.close()
    assert recorder.write_bugs == 1
    seqs = _seqs(path)
    assert seqs == [2, 3]


def test_the_queue_is_bounded_in_bytes_too(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    payload = _joint_state(1)
    monkeypatch.setattr(recorder_module, "MAX_QUEUED_BYTES", 10 * len(payload))
    bus, recorder, path = _recording(tmp_path)
    with recorder._lock:
        for seq in range(1, 21):
            bus.publish(_TOPIC, _joint_state(seq))
        assert recorder._bytes_in - recorder._bytes_out <= 10 * len(payload)
    recorder.close()
    seqs = _seqs(path)
    assert 1 <= len(seqs) <= 10
    assert seqs == list(range(1, len(seqs) + 1))
    assert recorder.queue_overflow >= 10
    assert recorder._bytes_in == recorder._bytes_out  # every queued byte written or left


@pytest.mark.skipif(sys.platform != "linux", reason="thread priorities are Linux's")
def test_the_writer_thread_runs_at_the_work_role(tmp_path: Path) -> None:
    recorder = Recorder("rig", InMemoryBus(), {})
    policy, nice = priority.settings().of("work")
    wanted = {"other": os.SCHED_OTHER, "batch": os.SCHED_BATCH, "idle": os.SCHED_IDLE}[policy]
    tid = recorder._writer.native_id
    assert tid is not None
    deadline = time.monotonic() + 5.0
    while os.sched_getscheduler(tid) != wanted and time.monotonic() < deadline:
        time.sleep(0.005)
    got = (os.sched_getscheduler(tid), os.getpriority(os.PRIO_PROCESS, tid))
    recorder.close()
    assert got == (wanted, max(nice, os.getpriority(os.PRIO_PROCESS, 0)))
