"""The episode waits, bounded, for each robot's joint state from after its recording window."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest

from telerig.bus.memory import InMemoryBus
from telerig.config import load_rig
from telerig.config.qa import QaThresholds
from telerig.ir import wire
from telerig.ir.types import JointState, Stamp, now_ns
from telerig.qa import evaluate
from telerig.record.recorder import Recorder
from telerig.runtime import recording
from telerig.runtime.rig import RigRuntime
from telerig.store.episodes import EpisodeStore

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


@pytest.mark.sim
@pytest.mark.broker
@pytest.mark.slow
def test_a_slow_stop_sequence_neither_lengthens_the_episode_nor_fails_its_streams(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A full host takes over a second between the recording window's end and the log's close
    # (devices stop, the tails arrive). The episode is the window: its end and duration are the
    # window's, and no stream stops "early" against the moment the station got round to closing.
    waited = recording._await_tails

    def slow(recorder: Recorder, end_ns: int) -> None:
        waited(recorder, end_ns)
        time.sleep(1.5)

    monkeypatch.setattr(recording, "_await_tails", slow)
    rig = load_rig("demo").model_copy(update={"cameras": []})
    with RigRuntime(rig, data_root=tmp_path) as runtime:
        result = runtime.run_episode(1.5)
    manifest = EpisodeStore(tmp_path).get(result.episode_id)
    assert manifest.duration_s is not None
    assert 1.5 <= manifest.duration_s < 2.0
    sync = evaluate(result.path, QaThresholds(gates=("sync",))).verdict("sync")
    assert sync is not None
    assert "stopped" not in sync.detail, sync.detail
