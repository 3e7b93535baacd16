"""Fuzzing the VrFrame parser: only WireError escapes; no NaN, inf or out-of-range value reaches the IR."""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from telerig.devices.udp_vr.fake import typical_payload
from telerig.devices.udp_vr.protocol import FUZZ_TARGET, MAX_POSITION_M
from telerig.errors import WireError
from telerig.ir._pb import vr_stream_pb2 as pb
from telerig.ir.types import ControllerState, HandPose, Pose

FUZZ = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])

floats32 = st.floats(width=32)  # includes NaN, inf, huge and subnormal values
near_unit = st.floats(-1.25, 1.25, width=32)
TYPICAL = typical_payload()
BASE = pb.VrFrame.FromString(TYPICAL)


def check(result: object) -> None:
    """Every sample the parser produced is finite, in range and unit where it must be."""
    assert isinstance(result, list)
    for s in result:
        assert 0.0 <= s.stamp.confidence <= 1.0
        if isinstance(s, Pose | ControllerState):
            assert np.all(np.abs(s.position) <= MAX_POSITION_M)
            assert abs(float(np.linalg.norm(s.orientation)) - 1.0) < 1e-9
        if isinstance(s, ControllerState):
            assert 0.0 <= s.trigger <= 1.0
            assert 0.0 <= s.grip <= 1.0
            assert np.all(np.abs(s.joystick) <= 1.0)
        if isinstance(s, HandPose):
            assert np.all(np.abs(s.keypoints) <= MAX_POSITION_M)
            assert np.all(np.abs(s.wrist_position) <= MAX_POSITION_M)
            assert abs(float(np.linalg.norm(s.wrist_orientation)) - 1.0) < 1e-9
            assert np.all((s.keypoint_confidence >= 0.0) & (s.keypoint_confidence <= 1.0))


def parse(data: bytes) -> None:
    message = ""
    try:
        result = FUZZ_TARGET(data)
    except WireError as exc:
        message = str(exc)
    else:
        check(result)
        return
    assert message
    assert "\n" not in message  # one line


def corrupt(draw: st.DrawFn) -> bool:
    """True for about one draw in four: replace a plausible value by an arbitrary float."""
    return draw(st.integers(0, 3)) == 0


def value(draw: st.DrawFn, plausible: st.SearchStrategy[float]) -> float:
    return draw(floats32) if corrupt(draw) else draw(plausible)


def poses(draw: st.DrawFn, msg: pb.VrPose) -> None:
    msg.px, msg.py, msg.pz = (value(draw, near_unit) for _ in range(3))
    q = np.array([draw(near_unit) for _ in range(4)])
    n = float(np.linalg.norm(q))
    if not corrupt(draw) and n > 1e-3:  # mostly a unit quaternion, so the rest gets exercised too
        q = q / n
    msg.qx, msg.qy, msg.qz, msg.qw = q.tolist()
    if corrupt(draw):
        setattr(msg, draw(st.sampled_from(["qx", "qy", "qz", "qw"])), draw(floats32))


def edited(draw: st.DrawFn, base: list[float], size: int, values: st.SearchStrategy[float]) -> list[float]:
    out = (base * 2)[:size]
    for _ in range(draw(st.integers(0, 3)) if size and corrupt(draw) else 0):
        out[draw(st.integers(0, size - 1))] = draw(values)
    return out


@st.composite
def frames(draw: st.DrawFn) -> bytes:
    msg = pb.VrFrame(
        format_version=draw(st.integers(0, 3)) if corrupt(draw) else 1,
        stream_id=draw(st.integers(0, 2**64 - 1)),
        seq=draw(st.integers(0, 2**64 - 1)),
        device_time_ns=draw(st.integers(-(2**63), 2**63 - 1) if corrupt(draw) else st.integers(0, 2**63 - 1)),
        head_tracked=draw(st.booleans()),
    )
    poses(draw, msg.head)
    for ctl in (msg.left, msg.right):
        ctl.tracked = draw(st.booleans())
        poses(draw, ctl.grip)
        ctl.buttons = draw(st.integers(0, 2**32 - 1))
        ctl.trigger, ctl.squeeze = (value(draw, st.floats(0.0, 1.0, width=32)) for _ in range(2))
        ctl.thumbstick_x, ctl.thumbstick_y = (value(draw, st.floats(-1.0, 1.0, width=32)) for _ in range(2))
    for hand, base in ((msg.left_hand, BASE.left_hand), (msg.right_hand, BASE.right_hand)):
        hand.tracked = draw(st.booleans())
        size = 26 if not corrupt(draw) else draw(st.sampled_from([25, 27, 0]))
        # A realistic hand with a few values replaced keeps each example cheap to generate.
        hand.joint_positions.extend(edited(draw, list(base.joint_positions), 3 * size, floats32))
        hand.joint_orientations.extend(edited(draw, list(base.joint_orientations), 4 * size, near_unit))
        hand.joint_radii.extend([0.01] * (0 if corrupt(draw) else 26))
        hand.joint_invalid_mask = draw(st.integers(0, 2**32 - 1))
    return msg.SerializeToString()


@FUZZ
@given(st.binary(max_size=5000))
def test_random_bytes_raise_only_wire_error(data: bytes) -> None:
    parse(data)


@FUZZ
@given(frames())
def test_random_frames_never_put_bad_values_in_the_ir(data: bytes) -> None:
    parse(data)


@FUZZ
@given(st.lists(st.tuples(st.integers(0, len(TYPICAL) - 1), st.integers(0, 255)), min_size=1, max_size=8))
def test_corrupted_typical_payload_raises_only_wire_error(edits: list[tuple[int, int]]) -> None:
    data = bytearray(TYPICAL)
    for index, value in edits:
        data[index] = value
    parse(bytes(data))


@FUZZ
@given(st.integers(0, len(TYPICAL)))
def test_truncated_typical_payload_raises_only_wire_error(length: int) -> None:
    parse(TYPICAL[:length])
