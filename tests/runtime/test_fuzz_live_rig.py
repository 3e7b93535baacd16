"""Randomized valid-schema messages into a live demo rig through Mosquitto never break its control.

Hypothesis draws bursts of well-formed IR messages of every type (NaN, inf, 1e300, zero and huge
quaternions, far-future, far-past and negative stamps, sequence jumps) and publishes them on the
device streams of a recording demo rig (real broker, scripted VR device, MuJoCo arm, safety chain)
while its real operator input runs. Checked: the control loop stays alive and keeps commanding, no
tick faults, every sent joint command within the joint limits and the per-tick speed limit, an
e-stop and a reset over the bus resume control, and no traceback anywhere in the log.
"""

from __future__ import annotations

import itertools
import logging
import math
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from telerig.bus.base import Message
from telerig.bus.mqtt import MqttBus
from telerig.bus.ticks import picking
from telerig.bus.topics import Topic
from telerig.config import load_rig
from telerig.config.schema import RigConfig
from telerig.ir import wire
from telerig.ir.types import (
    BaseVelocity,
    BodySkeleton,
    CameraFrame,
    ControlKind,
    ControllerState,
    ControlMode,
    ControlSource,
    GripperCommand,
    HandPose,
    JointCommand,
    JointState,
    Pose,
    RetargetResidual,
    Sample,
    Stamp,
    Twist,
    now_ns,
)
from telerig.runtime import streams
from telerig.runtime.rig import RigRuntime
from telerig.safety.commands import SafetyCommand, safety_command_topic

pytestmark = [pytest.mark.sim, pytest.mark.broker, pytest.mark.slow]

RIG = "demo"
BOUND = str(Topic(RIG, "vr0", "right_controller"))  # what the arm and gripper consume
#: The bound stream, most of the time, and other device streams of the rig's device.
TOPICS = (
    BOUND,
    BOUND,
    BOUND,
    str(Topic(RIG, "vr0", "left_controller")),
    str(Topic(RIG, "vr0", "right_hand")),
)
PERIOD_S = 0.01  # the demo arm's control period

NAN, INF = math.nan, math.inf
EXTREMES = (NAN, INF, -INF, 1e300, -1e300, 1e154, 5e-324, 0.0, -0.0, 1.0, 2.0, -1.0, 0.5)

# -- strategies: every IR type, values and stamps from the extremes -------------------------------

floats = st.one_of(st.sampled_from(EXTREMES), st.floats(), st.floats(-2.0, 2.0))


def vectors(n: int) -> st.SearchStrategy[list[float]]:
    return st.lists(floats, min_size=n, max_size=n)


quaternions = st.one_of(
    st.sampled_from(
        [(0.0, 0.0, 0.0, 0.0), (1e300, 0.0, 0.0, 0.0), (NAN, 0.0, 0.0, 1.0), (1.0, 0.0, 0.0, 0.0)]
    ),
    vectors(4),
)
#: Capture time: ``now + offset`` [ns], or an absolute value.
offsets = st.one_of(
    st.sampled_from([0, -(10**7), 3 * 10**8, 3600 * 10**9, -3600 * 10**9]),
    st.integers(-(2**62), 2**62),
)
absolutes = st.sampled_from([2**62, -(2**62), 0, 1, 2**63 - 1, -(2**63)])
Build = Callable[[int], Sample]


@st.composite
def stamps(draw: st.DrawFn) -> Callable[[int], Stamp]:
    source = draw(st.sampled_from(["vr0/right", "rogue", ""]))
    seq = draw(st.one_of(st.integers(0, 10), st.integers(-(2**63), 2**63 - 1)))
    relative = draw(st.booleans())
    value = draw(offsets if relative else absolutes)
    device_ns = draw(st.integers(-(2**63), 2**63 - 1))
    confidence = draw(st.one_of(st.just(1.0), floats))

    def make(now: int) -> Stamp:
        capture = max(-(2**63), min(2**63 - 1, now + value)) if relative else value
        return Stamp(source, seq, device_ns, capture, 0, confidence)

    return make


@st.composite
def messages(draw: st.DrawFn) -> tuple[str, Build]:
    """A topic and a builder of a well-formed sample stamped relative to ``now``."""
    topic = draw(st.sampled_from(TOPICS))
    stamp = draw(stamps())
    kind = draw(st.sampled_from(["controller"] * 4 + ["pose", "hand", "body", "twist", "base", "other"]))
    hand = draw(st.sampled_from(["left", "right"]))
    p, q = draw(vectors(3)), draw(quaternions)
    build: Build
    if kind == "controller":
        buttons = draw(st.frozensets(st.sampled_from(["a", "b", "x", "grip", "menu"])))
        trig, grip, stick = draw(floats), draw(floats), draw(vectors(2))
        build = lambda now: ControllerState(stamp(now), hand, p, q, "operator", buttons, trig, grip, stick)  # noqa: E731
    elif kind == "pose":
        build = lambda now: Pose(stamp(now), p, q, "operator")  # noqa: E731
    elif kind == "hand":
        kp = np.array(draw(st.one_of(st.just([0.3] * 63), vectors(63)))).reshape(21, 3)
        conf = draw(st.one_of(st.just([0.9] * 21), vectors(21)))
        build = lambda now: HandPose(stamp(now), hand, p, q, kp, conf, "operator")  # noqa: E731
    elif kind == "body":
        n = draw(st.integers(0, 3))
        pos = np.array(draw(vectors(3 * n))).reshape(n, 3)
        rot = np.array(draw(vectors(4 * n))).reshape(n, 4)
        build = lambda now: BodySkeleton(stamp(now), tuple(f"j{i}" for i in range(n)), pos, rot, "operator")  # noqa: E731
    elif kind == "twist":
        angular = draw(vectors(3))
        build = lambda now: Twist(stamp(now), p, angular, "operator")  # noqa: E731
    elif kind == "base":
        vx, vy, wz = draw(vectors(3))
        build = lambda now: BaseVelocity(stamp(now), vx, vy, wz)  # noqa: E731
    else:
        kinds = ["joint_command", "joint_state", "gripper", "camera", "control", "residual"]
        other = draw(st.sampled_from(kinds))
        values = draw(vectors(6))
        names = tuple(f"joint{i}" for i in range(6))
        if other == "joint_command":
            build = lambda now: JointCommand(stamp(now), names, values)  # noqa: E731
        elif other == "joint_state":
            build = lambda now: JointState(stamp(now), names, values, values)  # noqa: E731
        elif other == "gripper":
            build = lambda now: GripperCommand(stamp(now), values[0], values[1])  # noqa: E731
        elif other == "camera":
            build = lambda now: CameraFrame(stamp(now), "scene", 3, 640, 480)  # noqa: E731
        elif other == "residual":  # a robot's IK residual, where a device streams
            metrics = ("position_error_m", "orientation_error_rad")
            errors = (float(values[0]), float(values[1]))
            build = lambda now: RetargetResidual(stamp(now), values[2] > 0, metrics, errors)  # noqa: E731
        else:  # a robot's record of who drove, where a device streams
            drivers: list[tuple[str | None, ControlKind]] = [
                ("vr0", "operator"),
                ("pi0", "policy"),
                ("vr0", "paused"),
                (None, "none"),
                ("home", "home"),
            ]
            driver = draw(st.sampled_from(drivers))
            modes: list[ControlMode] = ["auto", "operator", "policy"]
            mode = draw(st.sampled_from(modes))
            build = lambda now: ControlSource(stamp(now), driver[0], driver[1], mode)  # noqa: E731
    return topic, build


# -- the live rig -----------------------------------------------------------------------------------


class SentCommands:
    """Every joint command the rig reports as sent to the arm: (arrival monotonic s, positions)."""

    def __init__(self) -> None:
        self.items: list[tuple[float, np.ndarray]] = []
        self._lock = threading.Lock()

    def __call__(self, message: Message) -> None:
        command = wire.decode(message.payload)
        assert isinstance(command, JointCommand)
        with self._lock:
            self.items.append((time.monotonic(), np.array(command.positions)))

    def since(self, t: float) -> int:
        with self._lock:
            return sum(1 for at, _ in self.items if at >= t)

    def snapshot(self) -> list[tuple[float, np.ndarray]]:
        with self._lock:
            return list(self.items)


def _wait_until(predicate: Callable[[], bool], timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.02)
    return False


def _demo_without_camera() -> RigConfig:
    raw = load_rig(RIG).with_isolation("threads").model_dump(mode="json", exclude_none=True)
    raw["cameras"] = []
    return RigConfig.model_validate(raw)


def test_fuzzed_messages_never_break_the_live_rig(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, capfd: pytest.CaptureFixture[str]
) -> None:
    caplog.set_level(logging.WARNING)
    sent = SentCommands()
    published: dict[str, int] = {}
    with RigRuntime(_demo_without_camera(), data_root=tmp_path) as runtime:
        assert runtime.broker_url is not None
        client = MqttBus(runtime.broker_url, client_id="fuzz").connect()
        client.subscribe(str(Topic(RIG, "arm0", streams.TICK)), picking({streams.JOINT_SENT}, sent))
        control = runtime.controls["arm0"]
        limits = runtime.robots["arm0"].limits
        outcome: list[Any] = []
        episode = threading.Thread(target=lambda: outcome.append(runtime.run_episode(10.0)))
        episode.start()
        try:
            assert _wait_until(lambda: sent.since(0.0) > 50, 15.0), "the demo arm never got commands"

            @settings(
                max_examples=12,
                deadline=None,
                database=None,
                derandomize=True,
                phases=[Phase.generate],
                suppress_health_check=list(HealthCheck),
            )
            @given(st.lists(messages(), min_size=10, max_size=40))
            def burst(batch: list[tuple[str, Build]]) -> None:
                for topic, build in batch:
                    client.publish(topic, wire.encode(build(now_ns())))
                    published[topic] = published.get(topic, 0) + 1
                time.sleep(0.05)

            burst()
            after_fuzz = time.monotonic()
            time.sleep(1.0)
            alive_rate_hz = sent.since(after_fuzz) / 1.0
            # A dead loop sends nothing; a live one ticks at 100 Hz (less on a loaded machine).
            assert alive_rate_hz > 10, f"only {alive_rate_hz:.0f} commands/s after the fuzz burst"
            assert control.alive
            assert control.stats.tick_faults == 0

            # An e-stop and a reset over the bus, as `telerig safety estop|reset` sends them.
            command_topic = safety_command_topic(RIG)
            client.publish(
                command_topic, SafetyCommand(command="estop", source="test").model_dump_json().encode(), qos=1
            )
            assert _wait_until(lambda: control.stats.safety_status == "estopped", 3.0)
            client.publish(
                command_topic, SafetyCommand(command="reset", source="test").model_dump_json().encode(), qos=1
            )
            reset_at = time.monotonic()
            assert _wait_until(lambda: sent.since(reset_at) > 20, 4.0), "no commands after the reset"
            tracking = _wait_until(lambda: control.stats.safety_status in ("ok", "limited"), 4.0)
            assert tracking, "the arm does not follow the operator again after the reset"
        finally:
            episode.join(30.0)
            client.close()
    assert outcome, "the episode did not finish"
    rejected = dict(control.stats.rejected)
    assert sum(published.values()) >= 120
    assert sum(rejected.values()) > 0  # the gate saw and dropped the bad ones

    # Joint limits and rates: every command inside the limits, every step within one tick's speed.
    items = sent.snapshot()
    q = np.array([p for _, p in items])
    assert np.all(q >= limits.lower - 1e-9)
    assert np.all(q <= limits.upper + 1e-9)
    max_step = limits.velocity * 2 * PERIOD_S  # the chain bounds a tick's dt to two periods
    for (t0, q0), (t1, q1) in itertools.pairwise(items):
        if t1 - t0 < 0.05:  # consecutive ticks (not across the e-stop)
            assert np.all(np.abs(q1 - q0) <= max_step + 1e-9), f"joint step {np.abs(q1 - q0)} > {max_step}"

    tracebacks = [r for r in caplog.records if r.exc_info is not None or "Traceback" in r.getMessage()]
    assert not tracebacks, tracebacks[0].getMessage()
    out, err = capfd.readouterr()
    assert "Traceback" not in out + err
