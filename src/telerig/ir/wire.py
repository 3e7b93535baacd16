"""Wire encoding of IR samples: one ``telerig.v1.Envelope`` protobuf message per sample."""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import numpy as np
from google.protobuf import descriptor_pb2
from google.protobuf.descriptor import FileDescriptor
from google.protobuf.message import DecodeError

from telerig.errors import WireError
from telerig.ir._pb import ir_pb2 as _pb
from telerig.ir.types import (
    HAND_KEYPOINTS,
    BaseVelocity,
    BodySkeleton,
    CameraFrame,
    ControllerState,
    FloatArray,
    GripperCommand,
    Handedness,
    HandPose,
    JointCommand,
    JointState,
    Pose,
    Sample,
    Stamp,
    Twist,
    Wrench,
)

__all__ = [
    "ENVELOPE_SCHEMA_NAME",
    "SCHEMA_VERSION",
    "WireError",
    "decode",
    "encode",
    "file_descriptor_set",
]

#: Version written to ``Envelope.schema_version``; the only version :func:`decode` accepts.
SCHEMA_VERSION = 1
#: Fully qualified protobuf name of the envelope, as MCAP schema name.
ENVELOPE_SCHEMA_NAME = "telerig.v1.Envelope"

_HAND_TO_PB: dict[str, int] = {"left": _pb.HANDEDNESS_LEFT, "right": _pb.HANDEDNESS_RIGHT}
_HAND_FROM_PB: dict[int, Handedness] = {_pb.HANDEDNESS_LEFT: "left", _pb.HANDEDNESS_RIGHT: "right"}


# --- encode -------------------------------------------------------------------------------------


def _enc_pose(env: Any, s: Pose) -> None:
    m = env.pose
    m.position.extend(s.position.tolist())
    m.orientation.extend(s.orientation.tolist())
    m.frame_id = s.frame_id


def _enc_hand_pose(env: Any, s: HandPose) -> None:
    m = env.hand_pose
    m.handedness = _HAND_TO_PB[s.handedness]
    m.wrist_position.extend(s.wrist_position.tolist())
    m.wrist_orientation.extend(s.wrist_orientation.tolist())
    m.keypoints.extend(s.keypoints.ravel().tolist())
    m.keypoint_confidence.extend(s.keypoint_confidence.tolist())
    m.frame_id = s.frame_id


def _enc_body_skeleton(env: Any, s: BodySkeleton) -> None:
    m = env.body_skeleton
    m.SetInParent()  # an empty skeleton is still a body
    m.joint_names.extend(s.joint_names)
    m.positions.extend(s.positions.ravel().tolist())
    m.orientations.extend(s.orientations.ravel().tolist())
    m.frame_id = s.frame_id


def _enc_controller_state(env: Any, s: ControllerState) -> None:
    m = env.controller_state
    m.hand = _HAND_TO_PB[s.hand]
    m.position.extend(s.position.tolist())
    m.orientation.extend(s.orientation.tolist())
    m.frame_id = s.frame_id
    m.buttons.extend(sorted(s.buttons))
    m.trigger = s.trigger
    m.grip = s.grip
    m.joystick.extend(s.joystick.tolist())


def _enc_twist(env: Any, s: Twist) -> None:
    m = env.twist
    m.linear.extend(s.linear.tolist())
    m.angular.extend(s.angular.tolist())
    m.frame_id = s.frame_id


def _enc_joint_command(env: Any, s: JointCommand) -> None:
    m = env.joint_command
    m.SetInParent()
    m.names.extend(s.names)
    m.positions.extend(s.positions.tolist())
    m.velocities.extend(s.velocities.tolist())


def _enc_gripper_command(env: Any, s: GripperCommand) -> None:
    m = env.gripper_command
    m.SetInParent()
    m.opening = s.opening
    m.max_force = s.max_force


def _enc_base_velocity(env: Any, s: BaseVelocity) -> None:
    m = env.base_velocity
    m.SetInParent()
    m.vx = s.vx
    m.vy = s.vy
    m.wz = s.wz


def _enc_joint_state(env: Any, s: JointState) -> None:
    m = env.joint_state
    m.SetInParent()
    m.names.extend(s.names)
    m.positions.extend(s.positions.tolist())
    m.velocities.extend(s.velocities.tolist())
    m.efforts.extend(s.efforts.tolist())


def _enc_camera_frame(env: Any, s: CameraFrame) -> None:
    m = env.camera_frame
    m.SetInParent()
    m.camera_id = s.camera_id
    m.frame_index = s.frame_index
    m.width = s.width
    m.height = s.height


def _enc_wrench(env: Any, s: Wrench) -> None:
    m = env.wrench
    m.force.extend(s.force.tolist())
    m.torque.extend(s.torque.tolist())
    m.frame_id = s.frame_id


_ENCODERS: dict[type, Callable[[Any, Any], None]] = {
    Pose: _enc_pose,
    HandPose: _enc_hand_pose,
    BodySkeleton: _enc_body_skeleton,
    ControllerState: _enc_controller_state,
    Twist: _enc_twist,
    JointCommand: _enc_joint_command,
    GripperCommand: _enc_gripper_command,
    BaseVelocity: _enc_base_velocity,
    JointState: _enc_joint_state,
    CameraFrame: _enc_camera_frame,
    Wrench: _enc_wrench,
}


def encode(sample: Sample) -> bytes:
    """Serialize an IR sample as a ``telerig.v1.Envelope`` (schema version :data:`SCHEMA_VERSION`).

    Raises:
        TypeError: ``sample`` is not an IR sample type.
        WireError: a value does not fit its wire field (e.g. a negative ``frame_index``).
    """
    encoder = _ENCODERS.get(type(sample))
    if encoder is None:
        raise TypeError(f"cannot encode {type(sample).__name__}: not an IR sample type")
    env = _pb.Envelope()
    env.schema_version = SCHEMA_VERSION
    st = env.stamp
    s = sample.stamp
    try:
        st.source_id = s.source_id
        st.seq = s.seq
        st.device_ns = s.device_ns
        st.capture_ns = s.capture_ns
        st.arrival_ns = s.arrival_ns
        st.confidence = s.confidence
        encoder(env, sample)
    except (ValueError, TypeError, KeyError) as exc:
        raise WireError(f"cannot encode {type(sample).__name__}: {exc}") from None
    data: bytes = env.SerializeToString()
    return data


# --- decode -------------------------------------------------------------------------------------


# ``values[:]`` turns a protobuf repeated field into a list, which NumPy converts ~3x faster.


def _vec(values: Any, n: int, name: str) -> FloatArray:
    if len(values) != n:
        raise WireError(f"{name} has {len(values)} values, expected {n}")
    return np.array(values[:], dtype=np.float64)


def _mat(values: Any, rows: int, cols: int, name: str) -> FloatArray:
    if len(values) != rows * cols:
        raise WireError(f"{name} has {len(values)} values, expected {rows} x {cols} = {rows * cols}")
    return np.array(values[:], dtype=np.float64).reshape(rows, cols)


def _opt_vec(values: Any, n: int, name: str) -> FloatArray:
    if len(values) not in (0, n):
        raise WireError(f"{name} has {len(values)} values, expected {n} or 0")
    return np.array(values[:], dtype=np.float64)


def _hand(value: int, name: str) -> Handedness:
    hand = _HAND_FROM_PB.get(value)
    if hand is None:
        raise WireError(f"{name} is {value}, expected HANDEDNESS_LEFT (1) or HANDEDNESS_RIGHT (2)")
    return hand


def _dec_pose(st: Stamp, m: Any) -> Pose:
    return Pose(
        st, _vec(m.position, 3, "pose.position"), _vec(m.orientation, 4, "pose.orientation"), m.frame_id
    )


def _dec_hand_pose(st: Stamp, m: Any) -> HandPose:
    return HandPose(
        st,
        _hand(m.handedness, "hand_pose.handedness"),
        _vec(m.wrist_position, 3, "hand_pose.wrist_position"),
        _vec(m.wrist_orientation, 4, "hand_pose.wrist_orientation"),
        _mat(m.keypoints, HAND_KEYPOINTS, 3, "hand_pose.keypoints"),
        _vec(m.keypoint_confidence, HAND_KEYPOINTS, "hand_pose.keypoint_confidence"),
        m.frame_id,
    )


def _dec_body_skeleton(st: Stamp, m: Any) -> BodySkeleton:
    n = len(m.joint_names)
    return BodySkeleton(
        st,
        tuple(m.joint_names),
        _mat(m.positions, n, 3, "body_skeleton.positions"),
        _mat(m.orientations, n, 4, "body_skeleton.orientations"),
        m.frame_id,
    )


def _dec_controller_state(st: Stamp, m: Any) -> ControllerState:
    return ControllerState(
        st,
        _hand(m.hand, "controller_state.hand"),
        _vec(m.position, 3, "controller_state.position"),
        _vec(m.orientation, 4, "controller_state.orientation"),
        m.frame_id,
        frozenset(m.buttons),
        m.trigger,
        m.grip,
        _vec(m.joystick, 2, "controller_state.joystick"),
    )


def _dec_twist(st: Stamp, m: Any) -> Twist:
    return Twist(st, _vec(m.linear, 3, "twist.linear"), _vec(m.angular, 3, "twist.angular"), m.frame_id)


def _dec_joint_command(st: Stamp, m: Any) -> JointCommand:
    n = len(m.names)
    return JointCommand(
        st,
        tuple(m.names),
        _vec(m.positions, n, "joint_command.positions"),
        _opt_vec(m.velocities, n, "joint_command.velocities"),
    )


def _dec_gripper_command(st: Stamp, m: Any) -> GripperCommand:
    return GripperCommand(st, m.opening, m.max_force)


def _dec_base_velocity(st: Stamp, m: Any) -> BaseVelocity:
    return BaseVelocity(st, m.vx, m.vy, m.wz)


def _dec_joint_state(st: Stamp, m: Any) -> JointState:
    n = len(m.names)
    return JointState(
        st,
        tuple(m.names),
        _vec(m.positions, n, "joint_state.positions"),
        _vec(m.velocities, n, "joint_state.velocities"),
        _opt_vec(m.efforts, n, "joint_state.efforts"),
    )


def _dec_camera_frame(st: Stamp, m: Any) -> CameraFrame:
    return CameraFrame(st, m.camera_id, m.frame_index, m.width, m.height)


def _dec_wrench(st: Stamp, m: Any) -> Wrench:
    return Wrench(st, _vec(m.force, 3, "wrench.force"), _vec(m.torque, 3, "wrench.torque"), m.frame_id)


_DECODERS: dict[str, Callable[[Stamp, Any], Sample]] = {
    "pose": _dec_pose,
    "hand_pose": _dec_hand_pose,
    "body_skeleton": _dec_body_skeleton,
    "controller_state": _dec_controller_state,
    "twist": _dec_twist,
    "joint_command": _dec_joint_command,
    "gripper_command": _dec_gripper_command,
    "base_velocity": _dec_base_velocity,
    "joint_state": _dec_joint_state,
    "camera_frame": _dec_camera_frame,
    "wrench": _dec_wrench,
}


def decode(data: bytes, *, arrival_ns: int | None = None) -> Sample:
    """Parse ``telerig.v1.Envelope`` bytes back into the IR dataclass they were encoded from.

    ``arrival_ns`` [ns], when given, replaces the stamp's arrival time (a receiver stamps the
    sample while decoding it, instead of rebuilding the sample afterwards).

    Raises:
        WireError: the bytes are truncated or not an Envelope, the schema version is not
            :data:`SCHEMA_VERSION`, the stamp or body is missing, or an array has the wrong length.
    """
    env = _pb.Envelope()
    try:
        env.ParseFromString(data)
    except (DecodeError, TypeError) as exc:
        raise WireError(
            f"cannot decode Envelope ({len(data)} bytes): truncated or not protobuf ({exc})"
        ) from None
    if env.schema_version != SCHEMA_VERSION:
        raise WireError(
            f"unsupported Envelope schema_version {env.schema_version}; this telerig reads {SCHEMA_VERSION}"
        )
    if not env.HasField("stamp"):
        raise WireError("Envelope has no stamp")
    kind = env.WhichOneof("body")
    if kind is None:
        raise WireError("Envelope has no body")
    s = env.stamp
    arrival = s.arrival_ns if arrival_ns is None else arrival_ns
    stamp = Stamp(s.source_id, s.seq, s.device_ns, s.capture_ns, arrival, s.confidence)
    try:
        return _DECODERS[kind](stamp, getattr(env, kind))
    except ValueError as exc:  # the dataclass rejected a value the schema allows
        raise WireError(f"invalid {kind} body: {exc}") from None


# --- schema -------------------------------------------------------------------------------------


@functools.cache
def file_descriptor_set() -> bytes:
    """Serialized ``google.protobuf.FileDescriptorSet`` with ``ir.proto`` and all its dependencies.

    Dependencies come before the files that import them, as MCAP ``protobuf`` schemas expect.
    """
    fds = descriptor_pb2.FileDescriptorSet()
    seen: set[str] = set()

    def add(fd: FileDescriptor) -> None:
        if fd.name in seen:
            return
        seen.add(fd.name)
        for dep in fd.dependencies:
            add(dep)
        fd.CopyToProto(fds.file.add())

    add(_pb.DESCRIPTOR)
    data: bytes = fds.SerializeToString()
    return data
