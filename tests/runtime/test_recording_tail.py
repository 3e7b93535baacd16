"""The episode waits, bounded, for each robot's joint state from after its recording window."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np

from telerig.bus.memory import InMemoryBus
from telerig.ir import wire
from telerig.ir.types import JointState, Stamp, now_ns
from telerig.record.recorder import Recorder
from telerig.runtime import recording

STATE = "telerig/v1/rig/{}/joint_state"


def _state(robot: str, seq: int, capture_ns: int) -> bytes:
    stamp = Stamp(robot, seq, capture_ns, capture_ns)
    return wire.encode(JointState(stamp, ("j1",), np.zeros(1), np.zeros(1)))


def _recorder(tmp_path: Path) -> tuple[InMemoryBus, Recorder]:
    bus = InMemoryBus()
    recorder = Recorder("rig", bus, {})
    recorder.start(tmp_path / "episode.mcap")
    return bus, recorder


def _timed(recorder: Recorder, end_ns: int) -> float:
    t0 = time.monotonic()
    recording._await_tails(recorder, end_ns)
    return time.monotonic() - t0


def test_a_late_state_is_waited_for_until_it_passes_the_window(tmp_path: Path) -> None:
    bus, recorder = _recorder(tmp_path)
    end = now_ns()
    bus.publish(STATE.format("arm0"), _state("arm0", 1, end - 50_000_000))
    bus.publish(STATE.format("arm1"), _state("arm1", 1, end + 1))  # already past the window

    def late() -> None:  # the station receives arm0's states half a second late, one per 10 ms
        for seq in range(2, 60):
            time.sleep(0.01)
            bus.publish(STATE.format("arm0"), _state("arm0", seq, end - 500_000_000 + seq * 10_000_000))

    feeder = threading.Thread(target=late)
    feeder.start()
    waited = _timed(recorder, end)
    feeder.join()
    newest = recorder.newest("joint_state")
    recorder.stop()
    assert 0.45 <= waited < recording._TAIL_WAIT_S
    assert set(newest) == {STATE.format("arm0"), STATE.format("arm1")}


def test_a_robot_whose_state_stopped_is_not_waited_for_and_the_wait_is_bounded(tmp_path: Path) -> None:
    bus, recorder = _recorder(tmp_path)
    end = now_ns()
    bus.publish(STATE.format("arm0"), _state("arm0", 1, end - 5_000_000_000))  # died 5 s ago
    assert _timed(recorder, end) < recording._TAIL_QUIET_S + 0.2

    stop = threading.Event()

    def behind() -> None:  # arriving all the time, but never catching up
        seq = 1
        while not stop.wait(0.01):
            seq += 1
            bus.publish(STATE.format("arm0"), _state("arm0", seq, end - 10_000_000_000 + seq))

    feeder = threading.Thread(target=behind)
    feeder.start()
    try:
        waited = _timed(recorder, end)
    finally:
        stop.set()
        feeder.join()
    recorder.stop()
    assert recording._TAIL_WAIT_S <= waited < recording._TAIL_WAIT_S + 0.3


def test_no_robot_no_wait(tmp_path: Path) -> None:
    _, recorder = _recorder(tmp_path)
    assert _timed(recorder, now_ns()) < 0.05
    recorder.stop()
