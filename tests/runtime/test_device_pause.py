"""Per-device pause versus halt all (seed 000) on a real rig: two VR controllers drive two arms through
Mosquitto; pausing one device holds its arm while the other arm goes on, and its resume re-anchors
without a jump. The pause is an operator command on the coordinator's command topic: the broker's
ACL refuses it from a device's login, and garbage on that topic is counted and dropped."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from telerig.bus.base import Message
from telerig.bus.mqtt import MqttBus
from telerig.bus.ticks import TICK, picking
from telerig.bus.topics import Topic
from telerig.config import load_rig
from telerig.ir import wire
from telerig.ir.types import JointCommand
from telerig.runtime.rig import EpisodeResult, RigRuntime
from telerig.runtime.session import Coordinator
from telerig.store.episodes import EpisodeStore
from telerig.store.manifest_extra import EpisodeExtra

pytestmark = [pytest.mark.sim, pytest.mark.broker, pytest.mark.slow]

RIG = "bimanual"
COMMAND = str(Topic(RIG, "coordinator", "command"))


def _wait(predicate: object, timeout_s: float, what: str) -> None:
    assert callable(predicate)
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(0.02)


class _Sent:
    """Every ``joint_command_sent`` of each arm with its arrival time (monotonic [s])."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.by_robot: dict[str, list[tuple[float, np.ndarray]]] = {"left": [], "right": []}

    def __call__(self, message: Message) -> None:
        sample = wire.decode(message.payload)
        assert isinstance(sample, JointCommand)
        robot = message.topic.split("/")[3]
        with self.lock:
            self.by_robot[robot].append((time.monotonic(), np.array(sample.positions)))

    def between(self, robot: str, t0: float, t1: float) -> np.ndarray:
        with self.lock:
            return np.array([q for t, q in self.by_robot[robot] if t0 <= t < t1])


def _command(bus: MqttBus, **doc: object) -> None:
    bus.publish(COMMAND, json.dumps({"source": "test", **doc}).encode(), qos=1)


@pytest.fixture
def runtime(tmp_path: Path) -> Iterator[RigRuntime]:
    rig = load_rig(RIG)
    rig = rig.model_copy(update={"cameras": []})
    with RigRuntime(rig, data_root=tmp_path) as runtime:
        yield runtime


def test_pausing_one_device_holds_its_arm_while_the_other_goes_on(
    runtime: RigRuntime, tmp_path: Path
) -> None:
    broker = runtime.broker.embedded
    assert broker is not None
    coordinator = runtime.coordinator
    assert isinstance(coordinator, Coordinator)
    sent = _Sent()
    with (
        MqttBus(broker.url_for("cli"), client_id="test-cli").connect() as cli,
        MqttBus(broker.url_for("dev-vr_right"), client_id="test-dev").connect() as device,
        MqttBus(broker.url_for("station"), client_id="test-station").connect() as station,
    ):
        cli.subscribe(Topic.pattern(RIG, "+", TICK), picking({"joint_command_sent"}, sent))
        results: list[EpisodeResult] = []
        episode = threading.Thread(target=lambda: results.append(runtime.run_episode(90.0)))
        episode.start()
        try:
            _wait(lambda: len(sent.by_robot["left"]) > 50, 30.0, "the left arm to be commanded")
            time.sleep(0.5)

            # A device's login cannot reach the coordinator's command topic (the broker drops it).
            before = (coordinator.stats.accepted, coordinator.stats.malformed, coordinator.stats.refused)
            _command(device, command="pause_device", device="vr_left")
            # Garbage from an operator's login: counted and dropped, the rig goes on.
            for junk in (
                b"\xff\xfe",
                b"[]",
                b'{"command": "pause_device"}',  # no device
                b'{"command": "pause", "device": "vr_left"}',  # device only with device commands
                b'{"command": "pause_device", "device": "../x"}',
                b'{"command": "pause_device", "device": "vr_left", "extra": 1}',
                b'{"command": "pause_device", "device": "' + b"v" * 5000 + b'"}',
            ):
                cli.publish(COMMAND, junk, qos=1)
            _command(cli, command="pause_device", device="no_such_device")  # valid shape, refused
            _wait(lambda: coordinator.stats.malformed - before[1] >= 7, 5.0, "the garbage to be counted")
            _wait(lambda: coordinator.stats.refused - before[2] >= 1, 5.0, "the unknown device refused")
            assert list(coordinator.status.paused_devices) == []
            assert coordinator.stats.accepted == before[0]
            # A malformed (not retained) session status reaches the control nodes: counted, dropped.
            station.publish(str(Topic(RIG, "coordinator", "session")), b'{"state": 7}', qos=1)
            left, right = runtime.controls["left"], runtime.controls["right"]
            _wait(lambda: left.stats.bad_session >= 1 and right.stats.bad_session >= 1, 5.0, "bad status")

            _command(cli, command="pause_device", device="vr_left", reason="operator adjusts the headset")
            _wait(lambda: bool(left.paused_topics), 15.0, "the left arm's control node to pause")
            assert coordinator.status.paused_devices == ("vr_left",)
            assert not right.paused_topics
            paused_at = time.monotonic()
            time.sleep(3.0)
            # The arm brakes within its acceleration limits first (~0.3 s; longer on a loaded host,
            # where the chain's dt is capped at two periods): the last 1.5 s must be still.
            held_window = (time.monotonic() - 1.5, time.monotonic())
            assert held_window[0] > paused_at
            _command(cli, command="resume_device", device="vr_left")
            _wait(lambda: not left.paused_topics, 15.0, "the left arm's control node to resume")
            resumed_at = time.monotonic()
            _wait(lambda: len(sent.between("left", resumed_at, resumed_at + 60)) > 20, 10.0, "commands")
            _command(cli, command="stop")  # the operator ends the episode (kept)
        finally:
            episode.join(timeout=30.0)
    assert results
    assert results[0].status == "complete"

    # While paused the left arm holds its pose (commands keep flowing: no watchdog stop) ...
    held = sent.between("left", *held_window)
    assert len(held) > 20
    assert np.max(np.abs(held - held[0])) < 5e-3  # rad: it settles where the pause found it
    assert left.stats.paused_inputs > 20
    # ... while the right arm goes on following its controller.
    moving = sent.between("right", *held_window)
    assert len(moving) > 20
    assert np.max(np.ptp(moving, axis=0)) > 0.01
    # On resume the left arm restarts from where it held and goes back to its (absolute-mode) hand
    # through the chain's start-up ramp and limits: no jump (the scripted hand went far meanwhile),
    # never more per message than the velocity limit allows in the chain's longest tick.
    after = sent.between("left", resumed_at, resumed_at + 60)[:50]
    assert len(after) > 10
    assert np.max(np.abs(after[0] - held[-1])) < 0.01
    steps = np.abs(np.diff(np.vstack([held[-1:], after]), axis=0))
    chain = left.safety
    assert np.all(steps <= chain.limits.velocity * 2 * chain.period_s + 1e-6)
    # The episode's log says when the device was paused and resumed.
    extra = EpisodeExtra.of(EpisodeStore(tmp_path).get(results[0].episode_id))
    log = [e for e in extra.safety_log if e.code.startswith("device_")]
    assert [(e.code, e.reason.split(":")[0]) for e in log] == [
        ("device_paused", "vr_left"),
        ("device_resumed", "vr_left"),
    ]
    assert "operator adjusts the headset" in log[0].reason
    assert log[0].t_ns < log[1].t_ns
