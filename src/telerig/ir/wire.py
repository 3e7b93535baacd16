"""Wire encoding of IR samples: one ``telerig.v1.Envelope`` protobuf message per sample."""

from __future__ import annotations

import functools
import re
import threading
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

import numpy as np
from google.protobuf import descriptor_pb2
from google.protobuf.descriptor import FileDescriptor
from google.protobuf.message import DecodeError, Message

from telerig.errors import WireError
from telerig.ir._pb import ir_pb2 as _pb
from telerig.ir.protowire import len_field, len_header
from telerig.ir.types import (
    HAND_KEYPOINTS,
    BaseVelocity,
    BodySkeleton,
    CameraFrame,
    ControlKind,
    ControllerState,
    ControlMode,
    ControlSource,
    FloatArray,
    GripperCommand,
    Handedness,
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

__all__ = [
    "ENVELOPE_SCHEMA_NAME",
    "MAX_BUNDLE_PARTS",
    "SCHEMA_VERSION",
    "WireError",
    "decode",
    "decode_bundle",
    "encode",
    "encode_bundle",
    "file_descriptor_set",
]

#: Version written to ``Envelope.schema_version``; the only version :func:`decode` accepts.
SCHEMA_VERSION = 1
#: Fully qualified protobuf name of the envelope, as MCAP schema name.
ENVELOPE_SCHEMA_NAME = "telerig.v1.Envelope"

_HAND_TO_PB: dict[str, int] = {"left": _pb.HANDEDNESS_LEFT, "right": _pb.HANDEDNESS_RIGHT}
_HAND_FROM_PB: dict[int, Handedness] = {_pb.HANDEDNESS_LEFT: "left", _pb.HANDEDNESS_RIGHT: "right"}
_KIND_TO_PB: dict[str, int] = {
    "none": _pb.CONTROL_KIND_NONE,
    "policy": _pb.CONTROL_KIND_POLICY,
    "operator": _pb.CONTROL_KIND_OPERATOR,
    "paused": _pb.CONTROL_KIND_PAUSED,
    "home": _pb.CONTROL_KIND_HOME,
}
_KIND_FROM_PB: dict[int, ControlKind] = {
    _pb.CONTROL_KIND_NONE: "none",
    _pb.CONTROL_KIND_POLICY: "policy",
    _pb.CONTROL_KIND_OPERATOR: "operator",
    _pb.CONTROL_KIND_PAUSED: "paused",
    _pb.CONTROL_KIND_HOME: "home",
}
_MODE_TO_PB: dict[str, int] = {
    "auto": _pb.CONTROL_MODE_AUTO,
    "operator": _pb.CONTROL_MODE_OPERATOR,
    "policy": _pb.CONTROL_MODE_POLICY,
}
_MODE_FROM_PB: dict[int, ControlMode] = {
    _pb.CONTROL_MODE_AUTO: "auto",
    _pb.CONTROL_MODE_OPERATOR: "operator",
    _pb.CONTROL_MODE_POLICY: "policy",
}


# --- encode -------------------------------------------------------------------------------------
#
# Each thread keeps one Envelope per IR type and overwrites it for the next sample of that type, so
# the control loop's five or six messages per tick allocate no protobuf message (upb: one arena per
# message, malloc'd and freed each time, and the upb runtime calls malloc_trim after many frees,
# see telerig.runtime.realtime). Every field of the body is written on every encode, so nothing of
# the previous sample survives: repeated numbers by slice assignment (upb resizes the array in
# place), texts only when they changed. upb copies every text written into the message's arena
# and frees it only with the message, so a slot is replaced after _TEXT_WRITES_PER_SLOT writes.
# Never Clear() a reused message: upb then drops the arrays into the arena and allocates new ones
# (measured: +580 bytes of RSS per encode of a JointState, +168 MiB over 300 000).

#: Text values (source ids, frame ids, joint names, buttons) written into one reused Envelope
#: before it is replaced; each write stays in the message's arena until then (a few kB at most).
_TEXT_WRITES_PER_SLOT = 1024


class _Slot:
    """One thread's reusable Envelope for one IR type, with the texts last written into it."""

    __slots__ = ("body", "busy", "env", "stamp", "texts", "writes")

    def __init__(self, field: str) -> None:
        self.env = _pb.Envelope()
        self.env.schema_version = SCHEMA_VERSION
        self.stamp = self.env.stamp
        self.body = getattr(self.env, field)
        self.body.SetInParent()  # an empty skeleton or default command is still that body
        self.texts: dict[str, object] = {}
        self.writes = 0
        self.busy = False

    def text(self, m: Any, name: str, value: str) -> None:
        """Write text field ``name`` of ``m`` unless it holds ``value`` already."""
        if self.texts.get(name) != value:
            setattr(m, name, value)
            self.texts[name] = value
            self.writes += 1

    def texts_of(self, m: Any, name: str, values: Sequence[str]) -> None:
        """Write repeated text field ``name`` of ``m`` unless it holds ``values`` already."""
        if self.texts.get(name) != tuple(values):
            getattr(m, name)[:] = values
            self.texts[name] = tuple(values)  # a copy: the caller may change its list afterwards
            self.writes += len(values) + 1


def _put_pose(slot: _Slot, s: Pose) -> None:
    m = slot.body
    m.position[:] = s.position.tolist()
    m.orientation[:] = s.orientation.tolist()
    slot.text(m, "frame_id", s.frame_id)


def _put_hand_pose(slot: _Slot, s: HandPose) -> None:
    m = slot.body
    m.handedness = _HAND_TO_PB[s.handedness]
    m.wrist_position[:] = s.wrist_position.tolist()
    m.wrist_orientation[:] = s.wrist_orientation.tolist()
    m.keypoints[:] = s.keypoints.ravel().tolist()
    m.keypoint_confidence[:] = s.keypoint_confidence.tolist()
    slot.text(m, "frame_id", s.frame_id)


def _put_body_skeleton(slot: _Slot, s: BodySkeleton) -> None:
    m = slot.body
    slot.texts_of(m, "joint_names", s.joint_names)
    m.positions[:] = s.positions.ravel().tolist()
    m.orientations[:] = s.orientations.ravel().tolist()
    slot.text(m, "frame_id", s.frame_id)


def _put_controller_state(slot: _Slot, s: ControllerState) -> None:
    m = slot.body
    m.hand = _HAND_TO_PB[s.hand]
    m.position[:] = s.position.tolist()
    m.orientation[:] = s.orientation.tolist()
    slot.text(m, "frame_id", s.frame_id)
    slot.texts_of(m, "buttons", sorted(s.buttons))
    m.trigger = s.trigger
    m.grip = s.grip
    m.joystick[:] = s.joystick.tolist()


def _put_twist(slot: _Slot, s: Twist) -> None:
    m = slot.body
    m.linear[:] = s.linear.tolist()
    m.angular[:] = s.angular.tolist()
    slot.text(m, "frame_id", s.frame_id)


def _put_joint_command(slot: _Slot, s: JointCommand) -> None:
    m = slot.body
    slot.texts_of(m, "names", s.names)
    m.positions[:] = s.positions.tolist()
    m.velocities[:] = s.velocities.tolist()


def _put_gripper_command(slot: _Slot, s: GripperCommand) -> None:
    m = slot.body
    m.opening = s.opening
    m.max_force = s.max_force


def _put_base_velocity(slot: _Slot, s: BaseVelocity) -> None:
    m = slot.body
    m.vx = s.vx
    m.vy = s.vy
    m.wz = s.wz


def _put_joint_state(slot: _Slot, s: JointState) -> None:
    m = slot.body
    slot.texts_of(m, "names", s.names)
    m.positions[:] = s.positions.tolist()
    m.velocities[:] = s.velocities.tolist()
    m.efforts[:] = s.efforts.tolist()


def _put_camera_frame(slot: _Slot, s: CameraFrame) -> None:
    m = slot.body
    slot.text(m, "camera_id", s.camera_id)
    m.frame_index = s.frame_index
    m.width = s.width
    m.height = s.height


def _put_wrench(slot: _Slot, s: Wrench) -> None:
    m = slot.body
    m.force[:] = s.force.tolist()
    m.torque[:] = s.torque.tolist()
    slot.text(m, "frame_id", s.frame_id)


def _put_control_source(slot: _Slot, s: ControlSource) -> None:
    m = slot.body
    slot.text(m, "source", s.source or "")  # None travels as "" (the dataclass never holds "")
    m.kind = _KIND_TO_PB[s.kind]
    m.mode = _MODE_TO_PB[s.mode]


def _put_retarget_residual(slot: _Slot, s: RetargetResidual) -> None:
    m = slot.body
    m.flagged = s.flagged
    slot.texts_of(m, "names", s.names)  # rewritten only when they change (a retargeter's do not)
    m.values[:] = s.values


#: IR type → (its Envelope body field, the function that writes a sample of it into a slot).
_PUTTERS: dict[type, tuple[str, Callable[[_Slot, Any], None]]] = {
    Pose: ("pose", _put_pose),
    HandPose: ("hand_pose", _put_hand_pose),
    BodySkeleton: ("body_skeleton", _put_body_skeleton),
    ControllerState: ("controller_state", _put_controller_state),
    Twist: ("twist", _put_twist),
    JointCommand: ("joint_command", _put_joint_command),
    GripperCommand: ("gripper_command", _put_gripper_command),
    BaseVelocity: ("base_velocity", _put_base_velocity),
    JointState: ("joint_state", _put_joint_state),
    CameraFrame: ("camera_frame", _put_camera_frame),
    Wrench: ("wrench", _put_wrench),
    ControlSource: ("control_source", _put_control_source),
    RetargetResidual: ("retarget_residual", _put_retarget_residual),
}

#: Per thread: IR type → its reused slot.
_local = threading.local()
#: Whether :func:`encode` reuses its messages (the benchmarks turn it off for the before figures).
_reuse = True


def encode(sample: Sample) -> bytes:
    """Serialize an IR sample as a ``telerig.v1.Envelope`` (schema version :data:`SCHEMA_VERSION`).

    Reuses this thread's Envelope of the sample's type (see the comment above): safe from any
    thread, and the bytes returned are the caller's.

    Raises:
        TypeError: ``sample`` is not an IR sample type.
        WireError: a value does not fit its wire field (e.g. a negative ``frame_index``).
    """
    kind = type(sample)
    entry = _PUTTERS.get(kind)
    if entry is None:
        raise TypeError(f"cannot encode {kind.__name__}: not an IR sample type")
    field, put = entry
    slots: dict[type, _Slot] | None = getattr(_local, "slots", None)
    if slots is None:
        slots = _local.slots = {}
    slot = slots.get(kind)
    if slot is None or slot.writes > _TEXT_WRITES_PER_SLOT or not _reuse:
        slot = slots[kind] = _Slot(field)
    elif slot.busy:  # re-entered on this thread (a signal handler): a message of its own
        slot = _Slot(field)
    slot.busy = True
    st, s = slot.stamp, sample.stamp
    try:
        slot.text(st, "source_id", s.source_id)
        st.seq = s.seq
        st.device_ns = s.device_ns
        st.capture_ns = s.capture_ns
        st.arrival_ns = s.arrival_ns
        st.confidence = s.confidence
        put(slot, sample)
        data: bytes = slot.env.SerializeToString()
    except (ValueError, TypeError, KeyError) as exc:
        slots.pop(kind, None)  # half written: the next sample starts from a fresh message
        raise WireError(f"cannot encode {kind.__name__}: {exc}") from None
    except BaseException:
        slots.pop(kind, None)
        raise
    finally:
        slot.busy = False
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


def _dec_control_source(st: Stamp, m: Any) -> ControlSource:
    kind = _KIND_FROM_PB.get(m.kind)
    if kind is None:
        raise WireError(f"control_source.kind is {m.kind}, expected CONTROL_KIND_NONE (1) to _HOME (5)")
    mode = _MODE_FROM_PB.get(m.mode)
    if mode is None:
        raise WireError(f"control_source.mode is {m.mode}, expected CONTROL_MODE_AUTO (1) to _POLICY (3)")
    return ControlSource(st, m.source or None, kind, mode)


def _dec_retarget_residual(st: Stamp, m: Any) -> RetargetResidual:
    if len(m.values) != len(m.names):
        raise WireError(f"retarget_residual has {len(m.values)} values for {len(m.names)} names")
    return RetargetResidual(st, m.flagged, tuple(m.names), tuple(m.values))


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
    "control_source": _dec_control_source,
    "retarget_residual": _dec_retarget_residual,
}


_M = TypeVar("_M", bound=Message)


def _parse(message: _M, data: bytes) -> _M:
    """``message`` parsed from ``data``, of this schema version (an Envelope or a Bundle)."""
    name = type(message).__name__
    try:
        message.ParseFromString(data)
    except (DecodeError, TypeError) as exc:
        raise WireError(
            f"cannot decode {name} ({len(data)} bytes): truncated or not protobuf ({exc})"
        ) from None
    version = message.schema_version  # type: ignore[attr-defined]
    if version != SCHEMA_VERSION:
        raise WireError(f"unsupported {name} schema_version {version}; this telerig reads {SCHEMA_VERSION}")
    return message


def decode(data: bytes, *, arrival_ns: int | None = None) -> Sample:
    """Parse ``telerig.v1.Envelope`` bytes back into the IR dataclass they were encoded from.

    ``arrival_ns`` [ns], when given, replaces the stamp's arrival time (a receiver stamps the
    sample while decoding it, instead of rebuilding the sample afterwards).

    Raises:
        WireError: the bytes are truncated or not an Envelope, the schema version is not
            :data:`SCHEMA_VERSION`, the stamp or body is missing, or an array has the wrong length.
    """
    env = _parse(_pb.Envelope(), data)
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


# --- bundles ------------------------------------------------------------------------------------
#
# A Bundle is encoded by hand: its layout is fixed (field 1 the version, field 2 one part per
# sample, each part field 1 the stream and field 2 the Envelope bytes) and writing those bytes
# straight is a join of a few slices, where building the protobuf message would copy every Envelope
# into a fresh arena per tick (the churn the reused envelopes above avoid). Decoding goes through
# protobuf, which checks the bytes. tests/ir/test_wire_bundle.py pins the two against each other.

#: Most parts a bundle may carry (a control tick has at most a dozen streams).
MAX_BUNDLE_PARTS = 64
_STREAM_NAME = re.compile(r"[A-Za-z0-9_.\-]{1,64}")
_BUNDLE_HEAD = b"\x08" + bytes([SCHEMA_VERSION])  # field 1 (varint): schema_version


@functools.cache
def _part_head(stream: str) -> bytes:
    """Field 1 of a BundlePart (the stream name, length-prefixed), the same for every tick."""
    if _STREAM_NAME.fullmatch(stream) is None:
        raise ValueError(
            f"bundle stream name {stream!r} is not a topic level (letters, digits, '_', '-', '.')"
        )
    return len_field(1, stream.encode())


def encode_bundle(parts: Sequence[tuple[str, bytes]]) -> bytes:
    """Serialize ``(stream, envelope bytes)`` pairs as one ``telerig.v1.Bundle``.

    Raises:
        ValueError: more than :data:`MAX_BUNDLE_PARTS` parts, or a stream name that is not a topic level.
    """
    if len(parts) > MAX_BUNDLE_PARTS:
        raise ValueError(f"a bundle carries at most {MAX_BUNDLE_PARTS} parts, got {len(parts)}")
    chunks = [_BUNDLE_HEAD]
    for stream, envelope in parts:
        head, body = _part_head(stream), len_header(2, len(envelope))
        chunks += (len_header(2, len(head) + len(body) + len(envelope)), head, body, envelope)
    return b"".join(chunks)


def decode_bundle(data: bytes) -> list[tuple[str, bytes]]:
    """Parse ``telerig.v1.Bundle`` bytes into ``(stream, envelope bytes)`` pairs, in order.

    The envelopes are not decoded here (:func:`decode` each one that is wanted).

    Raises:
        WireError: the bytes are not a Bundle, the schema version is not :data:`SCHEMA_VERSION`,
            it has no part or more than :data:`MAX_BUNDLE_PARTS`, or a stream name is not a topic level.
    """
    bundle = _parse(_pb.Bundle(), data)
    n = len(bundle.parts)
    if not 0 < n <= MAX_BUNDLE_PARTS:
        raise WireError(f"a Bundle carries 1 to {MAX_BUNDLE_PARTS} parts, this one {n}")
    parts = []
    for part in bundle.parts:
        stream = part.stream
        if _STREAM_NAME.fullmatch(stream) is None:
            raise WireError(f"Bundle part stream {stream[:64]!r} is not a topic level")
        parts.append((stream, part.envelope))
    return parts


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
