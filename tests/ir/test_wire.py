"""Wire encoding: every IR type round-trips exactly; malformed bytes raise a one-line WireError."""

from __future__ import annotations

import dataclasses
import math
import typing

import numpy as np
import pytest
from google.protobuf import descriptor_pb2

from telerig.errors import WireError
from telerig.ir import protogen, wire
from telerig.ir._pb import ir_pb2
from telerig.ir.types import (
    BaseVelocity,
    BodySkeleton,
    CameraFrame,
    ControllerState,
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
    Wrench,
)

_RNG = np.random.default_rng(7)
_ST = Stamp(
    "vr0/right", 42, device_ns=-5, capture_ns=1_700_000_000_123_456_789, arrival_ns=17, confidence=0.25
)
_Q = (1.0, 0.0, 0.0, 0.0)

SAMPLES: dict[str, Sample] = {
    "pose": Pose(_ST, (0.1, -0.2, 0.3), _Q, "operator"),
    "pose_nan": Pose(_ST, (math.nan, math.inf, -0.0), (0.5, 0.5, 0.5, 0.5), "ü/frame"),
    "hand_pose": HandPose(
        _ST, "left", (1, 2, 3), _Q, _RNG.normal(size=(21, 3)), _RNG.uniform(size=21), "operator"
    ),
    "body_skeleton": BodySkeleton(
        _ST, ("pelvis", "spine"), _RNG.normal(size=(2, 3)), _RNG.normal(size=(2, 4)), "mocap"
    ),
    "body_skeleton_empty": BodySkeleton(_ST, (), np.zeros((0, 3)), np.zeros((0, 4)), ""),
    "controller_state": ControllerState(
        _ST, "right", (1, 2, 3), _Q, "operator", frozenset({"b", "a"}), 0.5, 0.75, (0.1, -1.0)
    ),
    "controller_state_empty_buttons": ControllerState(Stamp("c", 0, 0, 0), "left", (0, 0, 0), _Q, "op"),
    "twist": Twist(_ST, (1, 2, 3), (-1, -2, -3), "base"),
    "joint_command": JointCommand(_ST, ("j1", "j2", "j3"), (0.1, 0.2, 0.3), (1.0, 2.0, 3.0)),
    "joint_command_no_velocities": JointCommand(_ST, ("j1",), (0.1,)),
    "joint_command_empty": JointCommand(_ST, (), ()),
    "gripper_command": GripperCommand(_ST, 0.3, 40.0),
    "gripper_command_zero": GripperCommand(Stamp("", 0, 0, 0, 0, 0.0), 0.0),
    "base_velocity": BaseVelocity(_ST, 0.5, -0.1, 1.5),
    "joint_state": JointState(_ST, ("a", "b"), (1, 2), (3, 4), (5, 6)),
    "joint_state_no_efforts": JointState(_ST, ("a", "b"), (1, 2), (3, 4)),
    "camera_frame": CameraFrame(_ST, "wrist", 123_456, 1280, 720),
    "wrench": Wrench(_ST, (1.5, -2.0, 9.81), (0.0, 0.25, -0.125), "arm0/ft_sensor"),
    "wrench_nan": Wrench(_ST, (math.nan, math.inf, -0.0), (0.0, 0.0, 0.0), ""),
    "control_source": ControlSource(_ST, "pi0", "policy", "auto"),
    "control_source_operator": ControlSource(_ST, "vr0", "operator", "operator"),
    "control_source_paused": ControlSource(_ST, "ü/vr0", "paused", "policy"),
    "control_source_home": ControlSource(_ST, "home", "home", "auto"),
    "control_source_none": ControlSource(Stamp("", 0, 0, 0, 0, 0.0), None, "none", "auto"),
    "residual_arm": RetargetResidual(_ST, True, ("position_error_m", "orientation_error_rad"), (0.07, 0.5)),
    "residual_extreme": RetargetResidual(
        _ST,
        False,
        ("nan_m", "inf_m", "-inf_s", "1e308_m", "-0_m", "ü_tiny"),
        (math.nan, math.inf, -math.inf, 1e308, -0.0, 5e-324),
    ),
    "residual_empty": RetargetResidual(Stamp("", 0, 0, 0, 0, 0.0), False, (), ()),
}


def assert_same_sample(a: Sample, b: Sample) -> None:
    """Equal type and fields; arrays equal in shape, dtype and value (NaN equals NaN), read-only."""
    assert type(a) is type(b)
    for f in dataclasses.fields(a):
        va, vb = getattr(a, f.name), getattr(b, f.name)
        if isinstance(va, np.ndarray):
            assert isinstance(vb, np.ndarray), f.name
            assert vb.dtype == np.float64, f.name
            assert vb.shape == va.shape, f.name
            assert np.array_equal(va, vb, equal_nan=True), f.name
            assert np.array_equal(np.signbit(va), np.signbit(vb)), f.name
            assert not vb.flags.writeable, f.name
        elif isinstance(va, tuple) and va and all(isinstance(v, float) for v in va):  # NaN equals NaN
            assert isinstance(vb, tuple), f.name
            assert all(isinstance(v, float) for v in vb), f.name
            assert np.array_equal(va, vb, equal_nan=True), f.name
            assert np.array_equal(np.signbit(va), np.signbit(vb)), f.name
        else:
            assert va == vb, f.name
            assert type(va) is type(vb), f.name


@pytest.mark.parametrize("name", list(SAMPLES))
def test_round_trip_restores_the_dataclass(name: str) -> None:
    sample = SAMPLES[name]
    assert_same_sample(wire.decode(wire.encode(sample)), sample)


def test_samples_cover_every_ir_type() -> None:
    assert {type(s) for s in SAMPLES.values()} == set(typing.get_args(Sample))


def test_encode_is_deterministic_for_buttons() -> None:
    a = dataclasses.replace(SAMPLES["controller_state"], buttons=frozenset(["x", "a", "m"]))
    b = dataclasses.replace(SAMPLES["controller_state"], buttons=frozenset(["m", "x", "a"]))
    assert wire.encode(a) == wire.encode(b)


def test_encode_rejects_non_samples() -> None:
    with pytest.raises(TypeError, match="not an IR sample"):
        wire.encode(_ST)  # type: ignore[arg-type]


def test_encode_rejects_values_outside_the_wire_range() -> None:
    with pytest.raises(WireError, match="CameraFrame"):
        wire.encode(CameraFrame(_ST, "c", -1, 1, 1))


def _envelope(**body: object) -> ir_pb2.Envelope:
    env = ir_pb2.Envelope(schema_version=wire.SCHEMA_VERSION, **body)
    env.stamp.source_id = "s"
    return env


def _decode_error(data: bytes) -> str:
    with pytest.raises(WireError) as info:
        wire.decode(data)
    message = str(info.value)
    assert "\n" not in message
    return message


@pytest.mark.parametrize("name", ["hand_pose", "control_source", "control_source_none"])
def test_every_truncation_raises_wire_error(name: str) -> None:
    data = wire.encode(SAMPLES[name])
    for n in range(len(data)):
        _decode_error(data[:n])


@pytest.mark.parametrize("data", [b"\xff\xff\xff\xff", b"\x0a\x80", b"hello world", bytes(range(256))])
def test_garbage_raises_wire_error(data: bytes) -> None:
    _decode_error(data)


def test_unknown_schema_version_is_named() -> None:
    env = ir_pb2.Envelope.FromString(wire.encode(SAMPLES["twist"]))
    env.schema_version = 2
    assert "schema_version 2" in _decode_error(env.SerializeToString())


def test_missing_body_is_named() -> None:
    assert "no body" in _decode_error(_envelope().SerializeToString())


def test_missing_stamp_is_named() -> None:
    env = ir_pb2.Envelope(schema_version=1, base_velocity=ir_pb2.BaseVelocity(vx=1.0))
    assert "no stamp" in _decode_error(env.SerializeToString())


@pytest.mark.parametrize(
    ("body", "expected"),
    [
        ({"pose": ir_pb2.Pose(position=[1, 2], orientation=[1, 0, 0, 0])}, "pose.position has 2 values"),
        (
            {
                "hand_pose": ir_pb2.HandPose(
                    handedness=1, wrist_position=[0] * 3, wrist_orientation=[1, 0, 0, 0]
                )
            },
            "hand_pose.keypoints has 0 values",
        ),
        (
            {"body_skeleton": ir_pb2.BodySkeleton(joint_names=["a"], positions=[1, 2, 3], orientations=[1])},
            "body_skeleton.orientations has 1 values",
        ),
        (
            {"joint_command": ir_pb2.JointCommand(names=["a", "b"], positions=[1, 2], velocities=[1])},
            "joint_command.velocities has 1 values, expected 2 or 0",
        ),
        (
            {"joint_state": ir_pb2.JointState(names=["a"], positions=[1], velocities=[])},
            "joint_state.velocities has 0 values",
        ),
        (
            {"controller_state": ir_pb2.ControllerState(position=[0] * 3, orientation=[1, 0, 0, 0])},
            "controller_state.hand is 0",
        ),
        ({"wrench": ir_pb2.Wrench(force=[1, 2, 3], torque=[1, 2])}, "wrench.torque has 2 values"),
        (
            {"retarget_residual": ir_pb2.RetargetResidual(names=["a_m", "b_m"], values=[0.1])},
            "retarget_residual has 1 values for 2 names",
        ),
        (
            {"retarget_residual": ir_pb2.RetargetResidual(names=["a_m", "a_m"], values=[0.1, 0.2])},
            "invalid retarget_residual body: metric names must be unique and not empty",
        ),
        (
            {"retarget_residual": ir_pb2.RetargetResidual(names=[""], values=[0.1])},
            "invalid retarget_residual body: metric names must be unique",
        ),
        ({"control_source": ir_pb2.ControlSource(source="pi0", mode=1)}, "control_source.kind is 0"),
        (
            {"control_source": ir_pb2.ControlSource(source="pi0", kind=99, mode=1)},
            "control_source.kind is 99",
        ),
        ({"control_source": ir_pb2.ControlSource(source="pi0", kind=2)}, "control_source.mode is 0"),
        (
            {"control_source": ir_pb2.ControlSource(source="pi0", kind=2, mode=-7)},
            "control_source.mode is -7",
        ),
        (
            {"control_source": ir_pb2.ControlSource(kind=2, mode=1)},
            "invalid control_source body: source None",
        ),
        (
            {"control_source": ir_pb2.ControlSource(source="pi0", kind=1, mode=1)},
            "invalid control_source body: source 'pi0' with kind 'none'",
        ),
    ],
)
def test_wrong_body_is_named(body: dict[str, object], expected: str) -> None:
    assert expected in _decode_error(_envelope(**body).SerializeToString())


def test_file_descriptor_set_holds_the_envelope() -> None:
    fds = descriptor_pb2.FileDescriptorSet.FromString(wire.file_descriptor_set())
    files = {f.name: f for f in fds.file}
    assert "telerig/v1/ir.proto" in files
    ir = files["telerig/v1/ir.proto"]
    assert ir.package == "telerig.v1"
    assert "Envelope" in {m.name for m in ir.message_type}
    assert ir_pb2.Envelope.DESCRIPTOR.full_name == wire.ENVELOPE_SCHEMA_NAME


def test_generated_code_is_up_to_date(capsys: pytest.CaptureFixture[str]) -> None:
    assert protogen.main(["--check"]) == 0, capsys.readouterr().err


def test_decode_stamps_the_arrival_time_when_given() -> None:
    sample = GripperCommand(Stamp("g", 3, 10, 20, 0, 1.0), opening=0.5)
    assert wire.decode(wire.encode(sample), arrival_ns=99).stamp.arrival_ns == 99
    assert wire.decode(wire.encode(sample)).stamp.arrival_ns == 0


#: A Wrench envelope as bytes (protobuf, schema version 1), pinned so a change to the wire format of
#: a recorded force/torque stream shows here: 08 01 schema_version 1; 12 17 the stamp; a2 01 44
#: body field 20 (wrench), 68 bytes: 0a 18 force (3 packed doubles), 12 18 torque, 1a 0e frame_id.
_WRENCH_BYTES = bytes.fromhex(
    "080112170a0461726d30100718e80720d00f31000000000000f03f"
    "a201440a18000000000000f03f00000000000000c01f85eb51b89e2340"
    "12180000000000000000000000000000e03f000000000000d0bf"
    "1a0e61726d302f66745f73656e736f72"
)


def test_a_wrench_has_its_pinned_bytes_on_the_wire() -> None:
    wrench = Wrench(Stamp("arm0", 7, 1000, 2000), (1.0, -2.0, 9.81), (0.0, 0.5, -0.25), "arm0/ft_sensor")
    assert wire.encode(wrench) == _WRENCH_BYTES
    assert_same_sample(wire.decode(_WRENCH_BYTES), wrench)


def test_control_source_rejects_what_the_wire_cannot_carry() -> None:
    st = Stamp("arm0", 1, 0, 0)
    for source, kind, mode in [
        ("pi0", "driver", "auto"),
        ("pi0", "policy", "manual"),
        ("", "policy", "auto"),  # "" means None on the wire
        (None, "policy", "auto"),
        ("pi0", "none", "auto"),
    ]:
        with pytest.raises(ValueError, match=r"kind|mode|source"):
            ControlSource(st, source, kind, mode)  # type: ignore[arg-type]


def test_control_source_extreme_values_round_trip() -> None:
    long = "p" * 60_000  # within the catalogue's 64 KiB IR limit
    stamp = Stamp(long, 2**63 - 1, -(2**63), 2**63 - 1, 2**63 - 1, math.nan)
    sample = ControlSource(stamp, long, "operator", "policy")
    back = wire.decode(wire.encode(sample))
    assert isinstance(back, ControlSource)
    assert back.source == long
    assert back.stamp.seq == 2**63 - 1
    assert math.isnan(back.stamp.confidence)


def test_control_source_reused_message_keeps_nothing_of_the_last_tick() -> None:
    # The encoder reuses one Envelope per type and thread: a tick with no source after one with a
    # source must not carry the old source id.
    named = ControlSource(Stamp("arm0", 1, 5, 5), "pi0", "policy", "policy")
    nobody = ControlSource(Stamp("arm0", 2, 6, 6), None, "none", "auto")
    for sample in (named, nobody, named, nobody):
        assert_same_sample(wire.decode(wire.encode(sample)), sample)
    assert wire.encode(nobody) == wire.encode(nobody)


#: A ControlSource envelope, pinned like the Wrench: aa 01 09 body field 21 (control_source), 9
#: bytes: 0a 03 source "pi0", 10 02 kind CONTROL_KIND_POLICY, 18 01 mode CONTROL_MODE_AUTO.
_CONTROL_SOURCE_BYTES = bytes.fromhex(
    "080112170a0461726d30100718e80720d00f31000000000000f03faa01090a0370693010021801"
)


def test_a_control_source_has_its_pinned_bytes_on_the_wire() -> None:
    sample = ControlSource(Stamp("arm0", 7, 1000, 2000), "pi0", "policy", "auto")
    assert wire.encode(sample) == _CONTROL_SOURCE_BYTES
    assert_same_sample(wire.decode(_CONTROL_SOURCE_BYTES), sample)


def test_residual_rejects_what_the_wire_cannot_carry() -> None:
    st = Stamp("arm0", 1, 0, 0)
    for names, values in [
        (("a_m", "a_m"), (1.0, 2.0)),
        (("",), (1.0,)),
        (("a_m",), (1.0, 2.0)),
        (("a_m",), ()),
    ]:
        with pytest.raises(ValueError, match=r"names|values"):
            RetargetResidual(st, False, names, values)
    with pytest.raises(ValueError, match="could not convert"):
        RetargetResidual(st, False, ("a_m",), ("x",))  # type: ignore[arg-type]


def test_residual_flag_is_a_python_bool_and_metrics_read_by_name() -> None:
    r = RetargetResidual(Stamp("arm0", 1, 0, 0), np.float64(0.2) > 0.1, ("position_error_m",), (0.2,))  # type: ignore[arg-type]
    assert r.flagged is True
    assert r.metrics() == {"position_error_m": 0.2}
    assert r.get("position_error_m") == 0.2
    assert math.isnan(r.get("orientation_error_rad"))
    assert r.get("orientation_error_rad", -1.0) == -1.0


def test_residual_reused_message_keeps_nothing_of_the_last_tick() -> None:
    # One reused Envelope per type and thread: a retargeter with other metrics (another robot
    # on the same thread, a whole-body mode switch) or none must not carry the last names or values.
    arm = RetargetResidual(
        Stamp("arm0", 1, 5, 5), True, ("position_error_m", "orientation_error_rad"), (0.1, 0.2)
    )
    hand = RetargetResidual(Stamp("hand0", 2, 6, 6), False, ("vector_error_m",), (0.01,))
    empty = RetargetResidual(Stamp("arm0", 3, 7, 7), False, (), ())
    for sample in (arm, hand, empty, arm, arm, hand):
        assert_same_sample(wire.decode(wire.encode(sample)), sample)
    assert wire.encode(hand) == wire.encode(hand)


def test_residual_over_the_ir_size_limit_still_encodes_and_the_recorder_limit_applies() -> None:
    # Encoding does not cap the size (the catalogue's 64 KiB IR limit is applied by every
    # receiver); 5000 metrics are ~100 KiB.
    names = tuple(f"m{i}_m" for i in range(5000))
    sample = RetargetResidual(Stamp("arm0", 1, 0, 0), False, names, tuple(np.arange(5000.0).tolist()))
    data = wire.encode(sample)
    assert len(data) > 64 * 1024
    assert_same_sample(wire.decode(data), sample)


#: A RetargetResidual envelope, pinned like the Wrench: b2 01 1e body field 22 (retarget_residual),
#: 30 bytes: 08 01 flagged, 12 10 names "position_error_m", 1a 08 values (packed double 0.125).
_RESIDUAL_BYTES = bytes.fromhex(
    "080112170a0461726d30100718e80720d00f31000000000000f03f"
    "b2011e08011210706f736974696f6e5f6572726f725f6d1a08000000000000c03f"
)


def test_a_residual_has_its_pinned_bytes_on_the_wire() -> None:
    sample = RetargetResidual(Stamp("arm0", 7, 1000, 2000), True, ("position_error_m",), (0.125,))
    assert wire.encode(sample) == _RESIDUAL_BYTES
    assert_same_sample(wire.decode(_RESIDUAL_BYTES), sample)
