"""Recorder over a real Mosquitto: only what the rig's nodes publish on catalogued streams is recorded.

Everything else (forged, oversized, undecodable, implausibly stamped, replayed) goes to the
counted ``rejected`` channel, with a capped payload head, and never into a data channel; one
rate-limited log line per reason, no traceback (issue 11, finding 3).
"""

from __future__ import annotations

import base64
import logging
import math
import os
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
from pydantic import JsonValue

from telerig.bus.broker import MosquittoBroker
from telerig.bus.catalogue import RigNodes
from telerig.bus.mqtt import MqttBus
from telerig.ir import wire
from telerig.ir._pb import ir_pb2
from telerig.ir.mcap_log import iter_raw, read_json
from telerig.ir.types import (
    ControllerState,
    ControlSource,
    JointCommand,
    JointState,
    Pose,
    RetargetResidual,
    Stamp,
    now_ns,
)
from telerig.record.recorder import REJECTED, Recorder

RIG = "rig"
NODES = RigNodes.of(devices=["vr0"], robots=["arm0"], stations=["station0"])
CONTROLLER = f"telerig/v1/{RIG}/vr0/right_controller"
SENT = f"telerig/v1/{RIG}/arm0/joint_command_sent"
REJECTED_TOPIC = f"telerig/v1/{RIG}/recorder/{REJECTED}"


def _controller(seq: int, capture_ns: int | None = None, *, frame_id: str = "operator") -> bytes:
    t = now_ns() if capture_ns is None else capture_ns
    stamp = Stamp("vr0/right", seq, t, t)
    return wire.encode(ControllerState(stamp, "right", np.zeros(3), np.array([1.0, 0, 0, 0]), frame_id))


def _sent(source: str, seq: int, q0: float = 0.0) -> bytes:
    t = now_ns()
    return wire.encode(JointCommand(Stamp(source, seq, t, t), ("j1", "j2"), np.array([q0, 0.0])))


class _Rig:
    """A recorder on a real broker, a publisher client, and what the recorder wrote."""

    def __init__(self, make_bus: Callable[..., MqttBus], path: Path) -> None:
        self.recorder = Recorder(RIG, make_bus("recorder"), {}, nodes=NODES)
        self.pub = make_bus("publisher", max_queued_messages=1024)
        self.path = path
        # The broker handles one client's subscriptions in order: once a later one delivers, the
        # recorder's is live too (a message published before that would be lost, not refused).
        live = threading.Event()
        self.recorder.bus.subscribe(f"telerig/v1/{RIG}/probe/live/x", lambda _: live.set())
        while not live.wait(0.05):
            self.pub.publish(f"telerig/v1/{RIG}/probe/live/x", b"", qos=1)
        self._done = threading.Event()
        self.recorder.bus.subscribe(f"telerig/v1/{RIG}/probe/done/x", lambda _: self._done.set())
        self.recorder.start(path)

    def publish(self, topic: str, payload: bytes) -> None:
        self.pub.publish(topic, payload, qos=1)

    def finish(self) -> None:
        """Wait until the recorder handled everything published so far, then stop it.

        The broker delivers one publisher's QoS 1 messages to a client in order, and the client runs
        its handlers in order: once a last marker arrives, the recorder has seen every message.
        """
        # Sent again each second: once, it went unanswered for 30 s in one full serial run of the
        # suite (the recorder had handled every message before it). Any copy that arrives still
        # comes after every earlier message.
        deadline = time.monotonic() + 30.0
        while True:
            self.pub.publish(f"telerig/v1/{RIG}/probe/done/x", b"", qos=1)
            if self._done.wait(1.0):
                break
            assert time.monotonic() < deadline, "the recorder's client got nothing within 30 s"
        self.summaries = {s.name: s for s in self.recorder.stop()}

    def data_topics(self) -> list[str]:
        return [topic for topic, *_ in iter_raw(self.path)]

    def rejected(self) -> list[dict[str, JsonValue]]:
        return [v for _, v, _ in read_json(self.path, topics=[REJECTED_TOPIC]) if isinstance(v, dict)]


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[_Rig]:
    # An external broker may accept any size (the embedded one stops at 2 MiB): the recorder's own
    # bounds must hold either way.
    buses: list[MqttBus] = []

    def make_bus(client_id: str, **options: object) -> MqttBus:
        bus = MqttBus(broker.url, client_id=client_id, **options).connect()  # type: ignore[arg-type]
        buses.append(bus)
        return bus

    with MosquittoBroker(message_size_limit=64 << 20) as broker:
        r = _Rig(make_bus, tmp_path / "episode.mcap")
        yield r
        r.recorder.close()
        for bus in buses:
            bus.close()


def _no_tracebacks(caplog: pytest.LogCaptureFixture, rig: _Rig) -> None:
    assert [r.getMessage() for r in caplog.records if r.exc_info] == []
    assert rig.recorder.bus.stats.handler_errors == 0


def test_forged_joint_commands_are_rejected_and_the_robots_own_recorded(
    rig: _Rig, caplog: pytest.LogCaptureFixture
) -> None:
    rig.publish(SENT, _sent("arm0", 1))
    rig.publish(SENT, _sent("intruder", 1, q0=5.46))  # the payload says someone else made it
    rig.publish(f"telerig/v1/{RIG}/intruder/joint_command_sent", _sent("intruder", 2, q0=5.46))
    # A device may send joint targets (a policy's action), but only on its own 'joints' stream.
    rig.publish(f"telerig/v1/{RIG}/vr0/joint_command_sent", _sent("vr0", 3, q0=5.46))
    rig.publish(CONTROLLER, _sent("vr0", 4, q0=5.46))  # a command where a controller streams
    rig.finish()
    assert rig.data_topics() == [SENT]
    assert [wire.decode(p).stamp.source_id for _, p, *_ in iter_raw(rig.path)] == ["arm0"]
    assert sorted(str(r["reason"]) for r in rig.rejected()) == [
        "unknown_stream",
        "wrong_source",
        "wrong_stream",
        "wrong_stream",
    ]
    assert rig.summaries[SENT].rejected == {"wrong_source": 1}
    assert rig.recorder.rejected == {"unknown_stream": 1, "wrong_source": 1, "wrong_stream": 2}
    _no_tracebacks(caplog, rig)


def test_oversized_payloads_are_rejected_with_a_capped_head(
    rig: _Rig, caplog: pytest.LogCaptureFixture
) -> None:
    big_valid = _controller(1, frame_id="x" * (2 << 20))  # a decodable 2 MB sample
    rig.publish(CONTROLLER, big_valid)
    for _ in range(4):
        rig.publish(CONTROLLER, os.urandom(10 << 20))
    rig.publish(CONTROLLER, _controller(2))
    rig.finish()
    assert rig.data_topics() == [CONTROLLER]
    rejected = rig.rejected()
    assert [(r["reason"], r["topic"], r["size"]) for r in rejected] == [
        ("oversized", CONTROLLER, len(big_valid)),
        *[("oversized", CONTROLLER, 10 << 20)] * 4,
    ]
    assert all(len(base64.b64decode(str(r["head_b64"]))) <= 256 for r in rejected)
    assert rig.path.stat().st_size < 1 << 20  # the episode holds no bulk
    assert rig.summaries[CONTROLLER].rejected == {"oversized": 5}
    assert rig.summaries[CONTROLLER].messages == 1
    _no_tracebacks(caplog, rig)


def test_implausible_stamps_are_rejected(rig: _Rig, caplog: pytest.LogCaptureFixture) -> None:
    rig.publish(CONTROLLER, _controller(1))
    rig.publish(CONTROLLER, _controller(2, capture_ns=2_800_000_000 * 10**9))  # 2.8e9 s: year 2058
    rig.publish(CONTROLLER, _controller(3, capture_ns=-5_000_000_000))  # negative capture time
    rig.publish(CONTROLLER, _controller(4, capture_ns=now_ns() - 3600 * 10**9))  # an hour old
    rig.finish()
    assert len(rig.data_topics()) == 1
    assert rig.recorder.rejected == {"future_stamp": 1, "negative_time": 1, "stale_stamp": 1}
    _no_tracebacks(caplog, rig)


def test_replayed_samples_are_rejected_by_sequence(rig: _Rig, caplog: pytest.LogCaptureFixture) -> None:
    first, second = _controller(1), _controller(2)
    rig.publish(CONTROLLER, first)
    rig.publish(CONTROLLER, second)
    rig.publish(CONTROLLER, first)  # replayed verbatim
    rig.publish(CONTROLLER, second)
    rig.publish(CONTROLLER, _controller(3))
    rig.finish()
    assert [wire.decode(p).stamp.seq for _, p, *_ in iter_raw(rig.path)] == [1, 2, 3]
    assert rig.recorder.rejected == {"replayed": 2}
    _no_tracebacks(caplog, rig)


def test_a_source_that_restarts_its_sequence_is_still_recorded(rig: _Rig) -> None:
    rig.publish(CONTROLLER, _controller(7))
    time.sleep(0.002)
    rig.publish(CONTROLLER, _controller(0))  # the device restarted: seq from 0, but captured later
    rig.finish()
    assert [wire.decode(p).stamp.seq for _, p, *_ in iter_raw(rig.path)] == [7, 0]


def test_json_on_a_protobuf_stream_and_protobuf_on_a_json_stream_are_rejected(
    rig: _Rig, caplog: pytest.LogCaptureFixture
) -> None:
    rig.publish(CONTROLLER, _controller(1))
    rig.publish(CONTROLLER, b'{"forged": true}')
    state = f"telerig/v1/{RIG}/arm0/motion_scale"
    rig.publish(state, b'{"scale": 0.5}')
    rig.publish(state, _controller(2))
    rig.finish()
    assert rig.data_topics() == [CONTROLLER]
    assert [v for t, v, _ in read_json(rig.path) if t == state] == [{"scale": 0.5}]
    assert rig.recorder.rejected == {"malformed": 2}
    _no_tracebacks(caplog, rig)


def test_deeply_nested_json_is_rejected_without_a_recursion_error(
    rig: _Rig, caplog: pytest.LogCaptureFixture
) -> None:
    pong = f"telerig/v1/{RIG}/station0/clock_pong"
    rig.publish(pong, b"[" * 20_000 + b"]" * 20_000)  # within the size limit, 20 000 levels deep
    rig.publish(pong, b"[" * 200_000 + b"]" * 200_000)
    rig.publish(pong, b'{"seq": 1, "t1": 1, "t2": 2, "t3": 3}')
    rig.finish()
    assert [v for t, v, _ in read_json(rig.path) if t == pong] == [{"seq": 1, "t1": 1, "t2": 2, "t3": 3}]
    assert rig.recorder.rejected == {"malformed": 1, "oversized": 1}
    assert "levels deep" in str(rig.rejected()[0]["detail"])
    _no_tracebacks(caplog, rig)


def test_a_joint_state_of_another_type_is_rejected(rig: _Rig) -> None:
    topic = f"telerig/v1/{RIG}/arm0/joint_state"
    t = now_ns()
    rig.publish(topic, wire.encode(Pose(Stamp("arm0", 1, t, t), np.zeros(3), np.array([1.0, 0, 0, 0]), "w")))
    rig.publish(topic, wire.encode(JointState(Stamp("arm0", 2, t, t), ("j1",), np.zeros(1), np.zeros(1))))
    rig.finish()
    assert rig.data_topics() == [topic]
    assert rig.recorder.rejected == {"wrong_type": 1}


def test_many_bad_messages_log_one_line_per_reason(rig: _Rig, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="telerig.record.recorder")
    for _ in range(200):
        rig.publish(CONTROLLER, b"\x00garbage")
    rig.finish()
    assert rig.recorder.rejected == {"malformed": 200}
    lines = [r for r in caplog.records if r.name == "telerig.record.recorder"]
    assert 1 <= len(lines) <= 2
    assert "malformed" in lines[0].getMessage()
    assert CONTROLLER in lines[0].getMessage()
    _no_tracebacks(caplog, rig)


def test_control_source_garbage_forgeries_and_the_old_json_form_are_rejected(
    rig: _Rig, caplog: pytest.LogCaptureFixture
) -> None:
    topic = f"telerig/v1/{RIG}/arm0/control_source"

    def control(source_id: str, seq: int, source: str | None = "pi0", **stamp: int) -> bytes:
        t = stamp.get("capture_ns", now_ns())
        kind = "policy" if source is not None else "none"
        return wire.encode(ControlSource(Stamp(source_id, seq, t, t), source, kind, "auto"))

    def raw(kind: int, mode: int, source: str = "pi0") -> bytes:
        env = ir_pb2.Envelope(schema_version=wire.SCHEMA_VERSION)
        env.stamp.source_id, env.stamp.seq, env.stamp.capture_ns = "arm0", 99, now_ns()
        env.control_source.source, env.control_source.kind, env.control_source.mode = source, kind, mode
        return env.SerializeToString()

    rig.publish(topic, control("arm0", 1))
    rig.publish(topic, control("intruder", 2))  # only the robot says who drove it
    rig.publish(topic, b'{"capture_ns": 1, "source": "pi0", "kind": "policy", "mode": "auto"}')  # old form
    rig.publish(topic, b"\x00garbage")
    rig.publish(topic, raw(kind=42, mode=1))  # an enum value this telerig does not know
    rig.publish(topic, raw(kind=2, mode=0))  # mode unset
    rig.publish(topic, raw(kind=1, mode=1))  # nobody drove, yet a source is named
    rig.publish(topic, control("arm0", 3, source="p" * (70 << 10)))  # over the 64 KiB IR limit
    rig.publish(topic, control("arm0", 4, capture_ns=2**63 - 1))  # far future
    t = now_ns()
    rig.publish(topic, control("arm0", 2**63 - 1, capture_ns=t))  # the largest seq: still a sample
    rig.publish(topic, control("arm0", 2**63 - 1, capture_ns=t))  # the same again: replayed
    rig.publish(topic, control("arm0", 2**63 - 1, capture_ns=t + 1))  # captured later: recorded
    rig.publish(topic, wire.encode(JointState(Stamp("arm0", 5, now_ns(), now_ns()), ("j",), [0.0], [0.0])))
    rig.publish(topic, control("arm0", 6, source=None))
    rig.finish()
    recorded = [wire.decode(p) for _, p, *_ in iter_raw(rig.path)]
    assert all(isinstance(s, ControlSource) and s.stamp.source_id == "arm0" for s in recorded)
    assert [(s.stamp.seq, s.kind) for s in recorded if isinstance(s, ControlSource)] == [
        (1, "policy"),
        (2**63 - 1, "policy"),
        (2**63 - 1, "policy"),
        (6, "none"),
    ]
    assert rig.recorder.rejected == {
        "wrong_source": 1,
        "malformed": 5,
        "oversized": 1,
        "future_stamp": 1,
        "wrong_type": 1,
        "replayed": 1,
    }
    _no_tracebacks(caplog, rig)


def test_residual_garbage_forgeries_and_the_old_json_form_are_rejected(
    rig: _Rig, caplog: pytest.LogCaptureFixture
) -> None:
    topic = f"telerig/v1/{RIG}/arm0/residual"
    names = ("position_error_m", "orientation_error_rad")

    def residual(source_id: str, seq: int, values: tuple[float, ...] = (0.01, 0.2), **stamp: int) -> bytes:
        t = stamp.get("capture_ns", now_ns())
        return wire.encode(RetargetResidual(Stamp(source_id, seq, t, t), False, names, values))

    def raw(names: list[str], values: list[float]) -> bytes:
        env = ir_pb2.Envelope(schema_version=wire.SCHEMA_VERSION)
        env.stamp.source_id, env.stamp.seq, env.stamp.capture_ns = "arm0", 99, now_ns()
        env.retarget_residual.names[:], env.retarget_residual.values[:] = names, values
        return env.SerializeToString()

    rig.publish(topic, residual("arm0", 1))
    rig.publish(topic, residual("intruder", 2))  # only the robot reports its residual
    rig.publish(topic, b'{"capture_ns": 1, "flagged": false, "position_error_m": 0.01}')  # the old form
    rig.publish(topic, residual("arm0", 3)[:-5])  # truncated
    rig.publish(topic, raw(["a_m", "b_m"], [0.1]))  # values do not match the names
    rig.publish(topic, raw(["a_m", "a_m"], [0.1, 0.2]))  # a repeated name
    rig.publish(topic, residual("arm0", 4, values=(math.nan, math.inf)))  # recorded as measured
    rig.publish(topic, residual("arm0", 5, values=(1e308, -1e308)))  # likewise
    many = tuple(f"m{i}_m" for i in range(5000))
    rig.publish(
        topic, wire.encode(RetargetResidual(Stamp("arm0", 6, now_ns(), now_ns()), False, many, (0.0,) * 5000))
    )
    rig.publish(topic, residual("arm0", 7, capture_ns=2**63 - 1))  # far future
    t = now_ns()
    rig.publish(topic, residual("arm0", 8, capture_ns=t))
    rig.publish(topic, residual("arm0", 8, capture_ns=t))  # the same again: replayed
    rig.publish(topic, wire.encode(JointState(Stamp("arm0", 9, now_ns(), now_ns()), ("j",), [0.0], [0.0])))
    rig.finish()
    recorded = [wire.decode(p) for _, p, *_ in iter_raw(rig.path)]
    assert all(isinstance(s, RetargetResidual) and s.stamp.source_id == "arm0" for s in recorded)
    assert [s.stamp.seq for s in recorded] == [1, 4, 5, 8]
    assert isinstance(recorded[1], RetargetResidual)
    assert math.isnan(recorded[1].values[0])
    assert recorded[1].values[1] == math.inf
    assert rig.recorder.rejected == {
        "wrong_source": 1,
        "malformed": 4,
        "oversized": 1,
        "future_stamp": 1,
        "wrong_type": 1,
        "replayed": 1,
    }
    _no_tracebacks(caplog, rig)


# --- a control tick: one Bundle message, recorded as the streams it carries ------------------------

TICK_TOPIC = f"telerig/v1/{RIG}/arm0/tick"
STATE = f"telerig/v1/{RIG}/arm0/joint_state"


def _state(source: str, seq: int) -> bytes:
    t = now_ns()
    stamp = Stamp(source, seq, t, t)
    return wire.encode(JointState(stamp, ("j1", "j2"), np.zeros(2), np.zeros(2)))


def test_a_tick_is_recorded_as_the_streams_it_carries(rig: _Rig, caplog: pytest.LogCaptureFixture) -> None:
    ticks = [(_sent("arm0", seq), _state("arm0", seq)) for seq in (1, 2, 3)]
    for sent, state in ticks:
        rig.publish(TICK_TOPIC, wire.encode_bundle([("joint_command_sent", sent), ("joint_state", state)]))
    rig.finish()
    recorded = [(topic, payload) for topic, payload, *_ in iter_raw(rig.path)]
    # The same channels and bytes as if each stream had its own message; no "tick" channel.
    assert recorded == [(t, p) for sent, state in ticks for t, p in ((SENT, sent), (STATE, state))]
    assert rig.summaries[SENT].messages == 3
    assert rig.summaries[STATE].messages == 3
    assert rig.recorder.rejected == {}
    _no_tracebacks(caplog, rig)


def test_garbage_in_a_tick_is_refused_part_by_part(rig: _Rig, caplog: pytest.LogCaptureFixture) -> None:
    good = _sent("arm0", 1)
    rig.publish(TICK_TOPIC, os.urandom(300))  # not a Bundle
    rig.publish(TICK_TOPIC, wire.encode_bundle([("joint_command_sent", b"\xff" * 40)]))  # not an Envelope
    too_many = [("joint_state", _state("arm0", 100 + i)) for i in range(wire.MAX_BUNDLE_PARTS)]
    rig.publish(TICK_TOPIC, wire.encode_bundle(too_many) + wire.encode_bundle([("joint_state", good)])[2:])
    bundle = ir_pb2.Bundle(schema_version=2, parts=[ir_pb2.BundlePart(stream="joint_state", envelope=good)])
    rig.publish(TICK_TOPIC, bundle.SerializeToString())  # a later schema
    rig.publish(
        TICK_TOPIC,
        wire.encode_bundle(
            [
                ("joint_command_sent", good),  # recorded: the other parts do not spoil it
                ("joint_state", _state("intruder", 2)),  # forged: only arm0 makes its joint state
                ("nonsense", good),  # no such stream
                ("status", b"ok"),  # a stream of the robot, but text: not in a tick
                ("tick", wire.encode_bundle([("joint_state", _state("arm0", 3))])),  # a tick in a tick
                ("joint_state", b"\x08\x01" + b"\x00" * (70 << 10)),  # over a sample's size limit
            ]
        ),
    )
    rig.publish(f"telerig/v1/{RIG}/vr0/tick", wire.encode_bundle([("joint_state", _state("vr0", 4))]))
    rig.finish()
    assert [(t, p) for t, p, *_ in iter_raw(rig.path)] == [(SENT, good)]
    reasons = sorted((str(r["reason"]), str(r["topic"]).rsplit("/", 2)[1:]) for r in rig.rejected())
    assert reasons == sorted(
        [
            ("malformed", ["arm0", "tick"]),  # random bytes
            ("malformed", ["arm0", "joint_command_sent"]),  # the part that is not an Envelope
            ("malformed", ["arm0", "tick"]),  # 65 parts
            ("malformed", ["arm0", "tick"]),  # schema version 2
            ("wrong_source", ["arm0", "joint_state"]),
            ("unknown_stream", ["arm0", "nonsense"]),
            ("wrong_stream", ["arm0", "status"]),
            ("wrong_stream", ["arm0", "tick"]),
            ("oversized", ["arm0", "joint_state"]),
            ("malformed", ["vr0", "tick"]),  # a device's "tick" is a device sample stream: no Envelope
        ]
    )
    _no_tracebacks(caplog, rig)
