"""Recorder: what a station records (its own nodes) and in which clock (the session's)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from telerig.bus.memory import InMemoryBus
from telerig.ir import wire
from telerig.ir.mcap_log import iter_raw, read_json
from telerig.ir.types import JointCommand, JointState, Pose, Stamp, now_ns
from telerig.record.recorder import BEFORE_START_SLACK_S, Recorder

_OFFSET_NS = 250_000_000  # this station's clock is 250 ms behind the coordinator's


def _pose(capture_ns: int) -> bytes:
    stamp = Stamp("vr0/head", 1, capture_ns, capture_ns)
    return wire.encode(Pose(stamp, np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]), "operator"))


def _joint_state(capture_ns: int) -> bytes:
    stamp = Stamp("arm0", 1, capture_ns, capture_ns)
    return wire.encode(JointState(stamp, ("j1",), np.zeros(1), np.zeros(1)))


def test_a_following_station_records_its_own_nodes_in_the_session_clock(tmp_path: Path) -> None:
    bus = InMemoryBus()
    recorder = Recorder(
        "rig",
        bus,
        {},
        node="recorder-operator",
        skip_nodes={"arm0"},
        to_session_ns=lambda local_ns: local_ns + _OFFSET_NS,
    )
    path = tmp_path / "episode.mcap"
    recorder.start(path)
    before = now_ns()
    captured = before - 1_000_000
    bus.publish("telerig/v1/rig/vr0/head", _pose(captured))
    after = now_ns()
    bus.publish("telerig/v1/rig/arm0/joint_state", _joint_state(captured))  # another station's node
    recorder.close()

    entries = list(iter_raw(path))
    assert [topic for topic, *_ in entries] == ["telerig/v1/rig/vr0/head"]
    _, payload, log_time_ns, publish_time_ns = entries[0]
    assert publish_time_ns == captured + _OFFSET_NS
    assert wire.decode(payload).stamp.capture_ns == captured  # payload stamps stay as made
    assert before + _OFFSET_NS <= log_time_ns <= after + _OFFSET_NS  # receive time shifted too


def test_the_coordinating_station_records_everything_unshifted(tmp_path: Path) -> None:
    bus = InMemoryBus()
    recorder = Recorder("rig", bus, {})
    path = tmp_path / "episode.mcap"
    recorder.start(path)
    captured = now_ns() - 1_000_000
    bus.publish("telerig/v1/rig/vr0/head", _pose(captured))
    bus.publish("telerig/v1/rig/arm0/joint_state", _joint_state(captured))
    recorder.close()
    entries = list(iter_raw(path))
    assert sorted(topic for topic, *_ in entries) == [
        "telerig/v1/rig/arm0/joint_state",
        "telerig/v1/rig/vr0/head",
    ]
    assert {publish for *_, publish in entries} == {captured}


def test_json_state_of_any_node_is_recorded_and_garbage_is_counted(tmp_path: Path) -> None:
    bus = InMemoryBus()
    recorder = Recorder("rig", bus, {})
    path = tmp_path / "episode.mcap"
    recorder.start(path)
    bus.publish("telerig/v1/rig/tiago0/wbc_mode", b'{"mode": "whole_body"}')
    bus.publish("telerig/v1/rig/tiago0/wbc_mode", b"{not json")
    recorder.close()
    assert recorder.malformed == {"telerig/v1/rig/tiago0/wbc_mode": 1}
    topic = "telerig/v1/rig/tiago0/wbc_mode"
    assert [value for t, value, _ in read_json(path, topics=[topic])] == [{"mode": "whole_body"}]


def test_samples_captured_well_before_the_episode_are_left_out_and_counted(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # A station short of CPU still receives the last episode's tail while the next one records:
    # those samples belong before this episode. What was in flight as it started is kept.
    bus = InMemoryBus()
    recorder = Recorder("rig", bus, {})
    path = tmp_path / "episode.mcap"
    start = now_ns() - 100_000_000
    recorder.start(path, since_ns=start)
    slack = round(BEFORE_START_SLACK_S * 1e9)
    captured = [start - 20 * slack, start - slack - 1, start - slack // 2, start + 1_000_000]
    for seq, t in enumerate(captured):
        stamp = Stamp("arm0", seq, t, t)
        bus.publish(
            "telerig/v1/rig/arm0/joint_state",
            wire.encode(JointState(stamp, ("j1",), np.zeros(1), np.zeros(1))),
        )
    with caplog.at_level(logging.WARNING, logger="telerig.record.recorder"):
        recorder.stop()
    assert recorder.before_start == 2
    assert [publish for *_, publish in iter_raw(path)] == captured[2:]
    assert "2 samples captured before the episode started" in caplog.text
    # The next episode counts its own.
    recorder.start(tmp_path / "next.mcap", since_ns=now_ns())
    recorder.close()
    assert recorder.before_start == 0


def test_a_command_stamped_by_its_input_counts_no_drop_where_the_loop_took_a_newer_input(
    tmp_path: Path,
) -> None:
    # The fleet soak's UR5e: two inputs arrived within one tick and the loop acted on the newer; the
    # requested command carries its input's stamp, so its seq skipped one. No loss, and no drop on
    # the health report or the stream summary; the robot's own streams still count theirs.
    bus = InMemoryBus()
    recorder = Recorder("rig", bus, {})
    recorder.start(tmp_path / "episode.mcap")
    requested_topic, sent_topic = (
        "telerig/v1/rig/arm0/joint_command_requested",
        "telerig/v1/rig/arm0/joint_command_sent",
    )
    for input_seq, sent_seq in [(0, 0), (1, 1), (3, 2), (4, 4)]:  # input 2 superseded; sent 3 lost
        t = now_ns()
        requested = JointCommand(Stamp("vr0/right", input_seq, t, t), ("j1",), np.zeros(1))
        sent = JointCommand(Stamp("arm0", sent_seq, t, t), ("j1",), np.zeros(1))
        parts = [
            ("joint_command_requested", wire.encode(requested)),
            ("joint_command_sent", wire.encode(sent)),
        ]
        bus.publish("telerig/v1/rig/arm0/tick", wire.encode_bundle(parts))
    recorder.newest("joint_command_sent")  # writes what is queued
    health = recorder.health.summary()["streams"]
    summaries = {s.name: s for s in recorder.stop()}
    assert (summaries[requested_topic].messages, summaries[requested_topic].drops) == (4, 0)
    assert health[requested_topic]["drops"] == 0
    assert (summaries[sent_topic].messages, summaries[sent_topic].drops) == (4, 1)
    assert health[sent_topic]["drops"] == 1
