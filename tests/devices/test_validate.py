"""Sample validation: each check drops what it should, counts it, and never locks a stream out."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from telerig.bus.catalogue import device_stream
from telerig.devices.validate import (
    DROP_REASONS,
    REJECT_REASONS,
    ConfidenceCheck,
    FiniteCheck,
    GapCheck,
    JumpCheck,
    MonotonicCheck,
    RangeCheck,
    SampleGate,
    SampleValidator,
    StampCheck,
    Track,
    ValidationConfig,
    position_of,
    stream_of,
)
from telerig.errors import ConfigError
from telerig.ir.types import (
    BaseVelocity,
    BodySkeleton,
    ControllerState,
    HandPose,
    JointCommand,
    JointState,
    Pose,
    Stamp,
    Twist,
)

T0 = 1_700_000_000_000_000_000
PERIOD = 10_000_000  # 100 Hz [ns]
FORWARD = (0.0, math.sqrt(0.5), 0.0, math.sqrt(0.5))


def stamp(i: int, *, source: str = "vr0/right", confidence: float = 1.0, ns: int | None = None) -> Stamp:
    t = T0 + i * PERIOD if ns is None else ns
    return Stamp(source, i, t, t, confidence=confidence)


def controller(
    i: int,
    position: tuple[float, float, float] = (0.4, 0.0, 1.1),
    *,
    source: str = "vr0/right",
    confidence: float = 1.0,
    ns: int | None = None,
    trigger: float = 0.5,
    grip: float = 0.0,
    joystick: tuple[float, float] = (0.0, 0.0),
) -> ControllerState:
    return ControllerState(
        stamp(i, source=source, confidence=confidence, ns=ns),
        "right",
        position,
        FORWARD,
        "operator",
        trigger=trigger,
        grip=grip,
        joystick=joystick,
    )


def hand(i: int, *, keypoints: object = None, keypoint_confidence: object = None) -> HandPose:
    kp = np.full((21, 3), 0.4) if keypoints is None else keypoints
    conf = np.full(21, 0.9) if keypoint_confidence is None else keypoint_confidence
    return HandPose(stamp(i), "right", (0.4, 0.0, 1.1), FORWARD, kp, conf, "operator")  # type: ignore[arg-type]


def feed(v: SampleValidator, n: int, start: int = 0) -> None:
    for i in range(start, start + n):
        assert v.validate(controller(i)) is None


def test_valid_stream_is_accepted_and_held_as_last_valid() -> None:
    v = SampleValidator.default()
    feed(v, 10)
    held = v.last_valid("vr0/right", "right_controller")
    assert isinstance(held, ControllerState)
    assert held.stamp.seq == 9
    assert v.received == v.accepted == 10
    assert v.stats().dropped == dict.fromkeys(DROP_REASONS, 0)


def test_dropped_sample_keeps_the_previous_last_valid() -> None:
    v = SampleValidator.default()
    feed(v, 3)
    assert v.validate(controller(3, position=(math.nan, 0.0, 1.0))) == "non_finite"
    held = v.last_valid("vr0/right", "right_controller")
    assert held is not None
    assert held.stamp.seq == 2


@pytest.mark.parametrize(
    "sample",
    [
        controller(0, position=(math.nan, 0.0, 1.0)),
        controller(0, trigger=math.inf),
        controller(0, joystick=(0.0, -math.inf)),
        controller(0, confidence=math.nan),
        hand(0, keypoints=np.where(np.eye(21, 3) > 0, math.nan, 0.3)),
        hand(0, keypoint_confidence=np.r_[np.full(20, 0.9), math.inf]),
        Pose(stamp(0), (0.0, 0.0, 0.0), (math.nan, 0.0, 0.0, 1.0), "operator"),
        Twist(stamp(0), (0.0, math.inf, 0.0), (0.0, 0.0, 0.0), "operator"),
        BaseVelocity(stamp(0), 0.1, math.nan, 0.0),
        BodySkeleton(stamp(0), ("a", "b"), [[0, 0, 1], [0, math.inf, 1]], [[1, 0, 0, 0]] * 2, "operator"),
        JointCommand(stamp(0), ("j1",), [math.nan]),
    ],
    ids=lambda s: type(s).__name__,
)
def test_non_finite_value_anywhere_is_dropped(sample: object) -> None:
    v = SampleValidator.default()
    assert v.validate(sample) == "non_finite"  # type: ignore[arg-type]
    assert v.dropped["non_finite"] == 1


@pytest.mark.parametrize(
    ("sample", "what"),
    [
        (controller(0, position=(6.0, 0.0, 0.0)), "beyond workspace radius"),
        (ControllerState(stamp(0), "right", (0, 0, 1), (0.9, 0, 0, 0), "operator"), "quaternion norm 0.9"),
        (controller(0, trigger=1.2), "trigger above 1"),
        (controller(0, grip=-0.1), "grip below 0"),
        (controller(0, joystick=(1.3, 0.0)), "joystick beyond 1"),
        (controller(0, confidence=1.5), "confidence above 1"),
        (controller(0, ns=0), "no capture time"),
        (hand(0, keypoint_confidence=np.full(21, 1.2)), "keypoint confidence above 1"),
        (hand(0, keypoints=np.r_[np.full((20, 3), 0.4), [[7.0, 0.0, 0.0]]]), "keypoint beyond radius"),
        (Twist(stamp(0), (20.0, 0.0, 0.0), (0.0, 0.0, 0.0), "operator"), "twist too fast"),
        (BaseVelocity(stamp(0), 0.0, 0.0, 50.0), "base yaw rate too fast"),
        (BodySkeleton(stamp(0), ("a",), [[0, 0, 1]], [[2, 0, 0, 0]], "operator"), "joint quaternion norm 2"),
    ],
    ids=lambda x: x if isinstance(x, str) else "",
)
def test_out_of_range_value_is_dropped(sample: object, what: str) -> None:
    v = SampleValidator.default()
    assert v.validate(sample) == "out_of_range", what  # type: ignore[arg-type]


def test_workspace_radius_is_configurable() -> None:
    v = SampleValidator.default(workspace_radius_m=10.0)
    assert v.validate(controller(0, position=(6.0, 0.0, 0.0))) is None


def test_far_keypoints_inside_the_radius_pass_the_exact_check() -> None:
    # Sum of squares above r^2 and |x|max * sqrt(3) above r: only the per-row test decides.
    check = RangeCheck(5.0)
    kp = np.zeros((21, 3))
    kp[:, 0] = 4.9
    assert check.check(hand(0, keypoints=kp), Track(("s", "right_hand"))) is None


def test_low_confidence_is_dropped() -> None:
    v = SampleValidator.default(min_confidence=0.6)
    assert v.validate(controller(0, confidence=0.59)) == "low_confidence"
    assert v.validate(controller(1, confidence=0.6)) is None


@pytest.mark.parametrize("ns", [T0 + 5 * PERIOD, T0 + 4 * PERIOD], ids=["equal", "earlier"])
def test_non_increasing_capture_time_is_dropped(ns: int) -> None:
    v = SampleValidator.default()
    feed(v, 6)
    assert v.validate(controller(6, ns=ns)) == "non_monotonic"
    assert v.validate(controller(7)) is None


def test_gap_drops_only_the_first_sample_after_an_outage() -> None:
    v = SampleValidator.default()
    feed(v, 10)
    assert v.validate(controller(30)) == "gap"  # 200 ms after a 10 ms period
    assert v.validate(controller(31)) is None
    assert v.dropped["gap"] == 1


def test_streams_sent_on_a_change_are_not_gap_checked() -> None:
    # Button presses of a script (the fleet's TIAGo mode button): pauses of 0.3 s and ~3 s. From
    # the first five the check learned a ~0.6 s "period" and dropped the next press after a 3 s
    # pause, one press lost in every episode; a stream sent on a change has no period at all.
    presses_s = [2.5, 2.8, 5.8, 6.1, 9.0, 9.3, 12.3, 12.6]

    def run(v: SampleValidator) -> list[str | None]:
        return [v.validate(controller(0, ns=T0 + round(t * 1e9))) for t in presses_s]

    assert run(SampleValidator.default()) == [None] * 6 + ["gap", None]  # what the soak found
    assert run(SampleValidator.default(on_change_streams={"right_controller"})) == [None] * 8
    # Only the streams named: a periodic stream of the same device is still checked.
    v = SampleValidator.default(on_change_streams={"left_controller"})
    feed(v, 10)
    assert v.validate(controller(30)) == "gap"


def test_gap_is_not_judged_before_the_period_is_learned() -> None:
    v = SampleValidator.default()
    feed(v, 2)
    assert v.validate(controller(50)) is None


def test_gap_with_expected_period_is_judged_from_the_second_sample() -> None:
    v = SampleValidator.default(expected_period_s=0.01)
    feed(v, 1)
    assert v.validate(controller(20)) == "gap"


def test_gap_below_the_floor_is_accepted_on_fast_devices() -> None:
    v = SampleValidator.default(expected_period_s=0.001)  # 1 kHz: 5 periods = 5 ms < 50 ms floor
    feed(v, 1)
    assert v.validate(controller(2)) is None  # 20 ms gap


def test_future_timestamp_glitch_does_not_lock_the_stream() -> None:
    v = SampleValidator.default()
    feed(v, 10)
    assert v.validate(controller(10, ns=T0 + 10**12)) == "gap"
    assert v.validate(controller(11)) is None


def test_jump_spike_costs_one_sample() -> None:
    v = SampleValidator.default()
    feed(v, 10)
    assert v.validate(controller(10, position=(1.4, 0.0, 1.1))) == "jump"  # 1 m in 10 ms
    assert v.validate(controller(11)) is None
    assert v.dropped["jump"] == 1


def test_jump_to_a_new_place_is_accepted_from_the_second_sample() -> None:
    v = SampleValidator.default()
    feed(v, 10)
    moved = (1.4, 0.0, 1.1)
    assert v.validate(controller(10, position=moved)) == "jump"
    assert v.validate(controller(11, position=moved)) is None
    assert v.validate(controller(12, position=moved)) is None


def test_fast_but_plausible_motion_is_accepted() -> None:
    v = SampleValidator.default(max_speed_m_s=10.0)
    feed(v, 10)
    assert v.validate(controller(10, position=(0.45, 0.0, 1.1))) is None  # 5 m/s


def test_streams_of_different_sources_are_independent() -> None:
    v = SampleValidator.default()
    feed(v, 10)
    assert v.validate(controller(3, source="vr0/left")) is None
    assert set(v.streams()) == {("vr0/right", "right_controller"), ("vr0/left", "right_controller")}


def test_reset_forgets_timing_but_keeps_counters() -> None:
    v = SampleValidator.default()
    feed(v, 10)
    v.validate(controller(10, position=(math.nan, 0, 0)))
    v.reset()
    assert v.validate(controller(500)) is None
    assert v.dropped["non_finite"] == 1
    assert v.received == 12


def test_custom_chain_runs_only_its_checks() -> None:
    v = SampleValidator([MonotonicCheck()])
    assert v.validate(controller(0, position=(math.nan, 0.0, 0.0))) is None


def test_chain_rejects_an_object_without_check() -> None:
    with pytest.raises(ConfigError, match=r"checks\[1\]"):
        SampleValidator([FiniteCheck(), object()])  # type: ignore[list-item]


@pytest.mark.parametrize(
    "build",
    [
        lambda: RangeCheck(0.0),
        lambda: RangeCheck(quaternion_tolerance=1.5),
        lambda: ConfidenceCheck(1.5),
        lambda: GapCheck(1.0),
        lambda: GapCheck(min_gap_s=-1.0),
        lambda: GapCheck(expected_period_s=0.0),
        lambda: GapCheck(warmup=0),
        lambda: JumpCheck(math.nan),
        lambda: JumpCheck(tolerance_m=-0.1),
    ],
)
def test_bad_threshold_is_a_config_error(build: object) -> None:
    with pytest.raises(ConfigError, match="must be"):
        build()  # type: ignore[operator]


def test_config_builds_the_same_validator() -> None:
    v = SampleValidator.from_config(ValidationConfig(min_confidence=0.9, workspace_radius_m=2.0))
    assert v.validate(controller(0, confidence=0.8)) == "low_confidence"
    assert v.validate(controller(1, position=(2.5, 0.0, 0.0))) == "out_of_range"


def test_stream_and_position_names() -> None:
    assert stream_of(controller(0)) == "right_controller"
    assert stream_of(hand(0)) == "right_hand"
    # A device's joint targets (a policy's action) are its 'joints' part; a joint state is no device sample.
    assert stream_of(JointCommand(Stamp("pi0", 0, 0, 0), ("j",), [0.0])) == "joints"
    assert stream_of(JointState(Stamp("arm0", 0, 0, 0), ("j",), np.zeros(1), np.zeros(1))) == "JointState"
    # The validator's stream names are the bus's (catalogue.device_stream): one rigid body per part.
    head = Pose(Stamp("quest/head", 0, 0, 0), np.zeros(3), np.array([1.0, 0, 0, 0]), "world")
    wand = Pose(Stamp("mocap/wand", 0, 0, 0), np.zeros(3), np.array([1.0, 0, 0, 0]), "world")
    assert (stream_of(head), stream_of(wand)) == ("head", "wand")
    assert (device_stream(head), device_stream(wand)) == ("head", "wand")
    assert position_of(hand(0)) is not None
    assert position_of(BaseVelocity(stamp(0), 0.0, 0.0, 0.0)) is None


@settings(max_examples=200, deadline=None)
@given(
    field=st.sampled_from(["position", "orientation", "joystick", "trigger", "grip"]),
    index=st.integers(0, 3),
    bad=st.sampled_from([math.nan, math.inf, -math.inf]),
)
def test_any_non_finite_controller_value_never_passes(field: str, index: int, bad: float) -> None:
    values: dict[str, object] = {
        "position": [0.4, 0.0, 1.1],
        "orientation": list(FORWARD),
        "joystick": [0.0, 0.0],
        "trigger": 0.5,
        "grip": 0.5,
    }
    value = values[field]
    if isinstance(value, list):
        value[index % len(value)] = bad
    else:
        values[field] = bad
    sample = ControllerState(stamp(0), "right", frame_id="operator", **values)  # type: ignore[arg-type]
    assert SampleValidator.default().validate(sample) == "non_finite"


# ---------------------------------------------------------------------------------------------
# The device-side stamp check and the consumer-side gate


def test_a_far_future_sample_never_becomes_the_streams_reference() -> None:
    now = T0 + 10 * PERIOD
    v = SampleValidator.default(max_future_s=0.5)
    v.checks = tuple(StampCheck(0.5, clock=lambda: now) if isinstance(c, StampCheck) else c for c in v.checks)
    feed(v, 10)
    assert v.validate(controller(10, ns=T0 + 3600 * 10**9)) == "future_stamp"
    assert v.validate(controller(11, ns=2**62)) == "future_stamp"
    assert v.validate(controller(12)) is None  # the real stream goes on
    assert v.dropped["future_stamp"] == 2


NOW = T0 + 100 * PERIOD
TOPIC = "telerig/v1/demo/vr0/right_controller"


def test_gate_admits_a_plausible_sample_unchanged() -> None:
    gate = SampleGate()
    s = controller(0, ns=NOW - PERIOD)
    assert gate.admit(TOPIC, s, NOW) is s
    assert gate.admitted == gate.received == 1
    assert gate.rejected == dict.fromkeys(REJECT_REASONS, 0)


@pytest.mark.parametrize(
    ("orientation", "reason"),
    [
        ((math.nan, 0.0, 0.0, 1.0), "non_finite"),
        ((0.0, 0.0, 0.0, 0.0), "bad_quaternion"),
        ((1e300, 0.0, 0.0, 0.0), "bad_quaternion"),
        ((1e10, 0.0, 0.0, 0.0), "bad_quaternion"),
        ((1e-5, 0.0, 0.0, 0.0), "bad_quaternion"),
    ],
)
def test_gate_rejects_degenerate_and_huge_quaternions(orientation: tuple[float, ...], reason: str) -> None:
    gate = SampleGate()
    s = ControllerState(Stamp("vr0/right", 0, NOW, NOW), "right", (0.4, 0.0, 1.1), orientation, "operator")
    assert gate.admit(TOPIC, s, NOW) == reason
    assert gate.rejected[reason] == 1


def test_gate_normalizes_a_plausible_quaternion() -> None:
    gate = SampleGate()
    s = ControllerState(Stamp("vr0/right", 0, NOW, NOW), "right", (0.4, 0.0, 1.1), (0.0, 0.0, 0.0, 1.3), "op")
    out = gate.admit(TOPIC, s, NOW)
    assert isinstance(out, ControllerState)
    np.testing.assert_allclose(out.orientation, (0.0, 0.0, 0.0, 1.0))
    orientations = [[1, 0, 0, 0], [0, 0.9, 0, 0]]
    body = BodySkeleton(Stamp("m", 0, NOW, NOW), ("a", "b"), [[0, 0, 1]] * 2, orientations, "o")
    admitted = gate.admit("body", body, NOW)
    assert isinstance(admitted, BodySkeleton)
    np.testing.assert_allclose(np.linalg.norm(admitted.orientations, axis=1), 1.0)


@pytest.mark.parametrize(
    ("sample", "reason"),
    [
        (controller(0, position=(math.inf, 0.0, 0.0), ns=NOW), "non_finite"),
        (controller(0, position=(1e300, 0.0, 0.0), ns=NOW), "out_of_range"),
        (controller(0, position=(2e3, 0.0, 0.0), ns=NOW), "out_of_range"),
        (controller(0, trigger=1e300, ns=NOW), "out_of_range"),
        (controller(0, joystick=(0.0, -2.0), ns=NOW), "out_of_range"),
        (controller(0, confidence=-1.0, ns=NOW), "out_of_range"),
        (Twist(Stamp("s", 0, NOW, NOW), (1e5, 0.0, 0.0), (0.0, 0.0, 0.0), "o"), "out_of_range"),
        (BaseVelocity(Stamp("s", 0, NOW, NOW), 0.0, 0.0, -1e4), "out_of_range"),
        (JointCommand(Stamp("s", 0, NOW, NOW), ("j1",), [math.nan]), "non_finite"),
        (controller(0, ns=NOW + 3600 * 10**9), "future_stamp"),
        (controller(0, ns=2**62), "future_stamp"),
        (controller(0, ns=NOW - 3600 * 10**9), "stale_stamp"),
        (controller(0, ns=-(2**62)), "stale_stamp"),
    ],
    ids=lambda x: x if isinstance(x, str) else "",
)
def test_gate_rejects_and_counts_implausible_samples(sample: object, reason: str) -> None:
    gate = SampleGate()
    assert gate.admit(TOPIC, sample, NOW) == reason  # type: ignore[arg-type]
    assert gate.rejected[reason] == 1
    assert gate.admitted == 0


def test_gate_future_sample_never_becomes_the_reference() -> None:
    gate = SampleGate()
    assert isinstance(gate.admit(TOPIC, controller(0, ns=NOW - 2 * PERIOD), NOW), ControllerState)
    assert gate.admit(TOPIC, controller(1, ns=NOW + 3600 * 10**9), NOW) == "future_stamp"
    assert isinstance(gate.admit(TOPIC, controller(2, ns=NOW - PERIOD), NOW), ControllerState)
    assert gate.admit(TOPIC, controller(3, ns=NOW - PERIOD), NOW) == "non_monotonic"  # not the same twice
    assert gate.rejected["future_stamp"] == gate.rejected["non_monotonic"] == 1


def test_gate_keeps_references_per_key() -> None:
    gate = SampleGate()
    assert isinstance(gate.admit("a", controller(0, ns=NOW), NOW), ControllerState)
    assert isinstance(gate.admit("b", controller(0, ns=NOW - PERIOD), NOW), ControllerState)


def test_gate_warns_once_per_interval_naming_the_source(caplog: pytest.LogCaptureFixture) -> None:
    gate = SampleGate("control arm0", warn_interval_s=60.0)
    with caplog.at_level("WARNING", logger="telerig.devices.validate"):
        for i in range(5):
            gate.admit(TOPIC, controller(i, source="rogue", ns=NOW + 3600 * 10**9), NOW)
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1
    assert "control arm0" in lines[0]
    assert "'rogue'" in lines[0]
    assert TOPIC in lines[0]
    assert "3.6e+03 s ahead" in lines[0]
    assert gate.rejected["future_stamp"] == 5


@pytest.mark.parametrize(
    "build",
    [
        lambda: SampleGate(max_position_m=0.0),
        lambda: SampleGate(quaternion_norm=(1.5, 2.0)),
        lambda: SampleGate(max_future_s=math.nan),
        lambda: SampleGate(max_age_s=-1.0),
        lambda: StampCheck(0.0),
    ],
)
def test_gate_bad_threshold_is_a_config_error(build: object) -> None:
    with pytest.raises(ConfigError):
        build()  # type: ignore[operator]
