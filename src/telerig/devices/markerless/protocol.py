"""Markerless wire v1 parsing: tracker datagrams → validated messages → ``HandPose`` / ``BodySkeleton``.

Frames. MediaPipe world landmarks are metric [m] in image-aligned axes (x image-right, y
image-down, z away from the camera); hands are centred on the hand, the pose on the midpoint of
the hips. telerig assumes the operator faces the camera and re-expresses them in operator axes
(x forward toward the camera, y operator's left, z up; the axes of the ``"operator"`` frame in
:mod:`telerig.devices.scripted`): ``(x, y, z)_op = (-z, x, -y)_mp`` for an ordinary (unmirrored)
image. A mirrored (selfie preview) image is unmirrored first (``x_mp -> -x_mp``). The origins stay
MediaPipe's, so hand keypoints are in the ``hand_frame_id`` frame (operator axes, origin at the
hand's centre) and body joints in the ``body_frame_id`` frame (operator axes, origin between the
hips); a camera tilt is not compensated.

Handedness. MediaPipe labels hands as if the image were mirrored, so for an unmirrored image its
"Left" is the operator's right hand; for a mirrored one its label is right as is. Pose landmark
names follow the person in an unmirrored image, so for a mirrored image left and right swap.

Wrist orientation (w, x, y, z) rotates the wrist frame into operator axes: +x from the wrist
toward the middle-finger knuckle (keypoint 9), +z out of the back of the hand, +y = z cross x
(toward the thumb for a right hand, toward the little finger for a left hand).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from telerig.devices.floats import f32_to_f64
from telerig.devices.markerless.tracker import (
    EVENT_END,
    EVENT_ERROR,
    EVENT_HEAD,
    EVENT_STARTED,
    FLAG_MIRRORED,
    FRAME_BODY,
    FRAME_SIZE,
    HAND_HEAD,
    HAND_POINTS,
    HAND_SIZE,
    HEADER,
    KIND_EVENT,
    KIND_FRAME,
    KIND_HAND,
    KIND_POSE,
    MAGIC,
    MAX_EVENT_TEXT,
    POSE_POINTS,
    POSE_SIZE,
    VERSION,
)
from telerig.errors import WireError
from telerig.ir.frames import cross3, quat_normalize
from telerig.ir.types import BodySkeleton, FloatArray, Handedness, HandPose, Stamp

__all__ = [
    "FUZZ_TARGET",
    "HAND_LIMIT_M",
    "POSE_JOINTS",
    "POSE_LIMIT_M",
    "EventMessage",
    "FrameMessage",
    "HandMessage",
    "Header",
    "Message",
    "PoseMessage",
    "body_confidence",
    "body_skeleton",
    "decode",
    "hand_pose",
    "wrist_orientation",
]

#: Largest accepted |coordinate| of a hand world landmark [m] (the origin is the hand's centre).
HAND_LIMIT_M = 1.0
#: Largest accepted |coordinate| of a pose world landmark [m] (the origin is between the hips).
POSE_LIMIT_M = 3.0
# MediaPipe's scores are sigmoids in [0, 1]; tolerate float32 rounding, reject anything else.
_SCORE_SLACK = 1e-3

#: The 33 MediaPipe pose landmarks, in wire order (person's left/right in an unmirrored image).
POSE_JOINTS: tuple[str, ...] = (
    "nose",
    "left_eye_inner",
    "left_eye",
    "left_eye_outer",
    "right_eye_inner",
    "right_eye",
    "right_eye_outer",
    "left_ear",
    "right_ear",
    "mouth_left",
    "mouth_right",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
    "left_pinky",
    "right_pinky",
    "left_index",
    "right_index",
    "left_thumb",
    "right_thumb",
    "left_hip",
    "right_hip",
    "left_knee",
    "right_knee",
    "left_ankle",
    "right_ankle",
    "left_heel",
    "right_heel",
    "left_foot_index",
    "right_foot_index",
)


def _mirror_permutation() -> FloatArray:
    index = {name: i for i, name in enumerate(POSE_JOINTS)}
    perm = []
    for name in POSE_JOINTS:
        if "left" in name:
            perm.append(index[name.replace("left", "right")])
        elif "right" in name:
            perm.append(index[name.replace("right", "left")])
        else:
            perm.append(index[name])
    return np.array(perm, dtype=np.intp)


_MIRROR_PERM = _mirror_permutation()
# Shoulders, elbows, wrists: the joints arm teleoperation uses; their mean visibility is the
# skeleton's confidence (legs are often out of the picture at a desk).
_CONFIDENCE_JOINTS = np.arange(11, 17)
_IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


@dataclass(frozen=True, slots=True)
class Header:
    """Fields common to every message.

    Attributes:
        kind: Message kind (1 hand, 2 pose, 3 frame, 4 event).
        mirrored: Whether the tracked frames were a mirror image.
        capture_ns: Frame capture time in the common clock [ns].
        device_ns: Frame presentation time in the source's own clock [ns].
        frame: Index of the frame in the tracker's stream, from 0.
        width: Frame width [px].
        height: Frame height [px].
    """

    kind: int
    mirrored: bool
    capture_ns: int
    device_ns: int
    frame: int
    width: int
    height: int


@dataclass(frozen=True, slots=True)
class HandMessage:
    """One detected hand, already in operator axes.

    Attributes:
        handedness: The operator's hand, after the mirror convention is applied.
        index: Index of the hand among the frame's detections.
        score: MediaPipe's handedness score in [0, 1].
        keypoints: Keypoints [m], operator axes, origin at the hand's centre. Shape (21, 3).
        confidence: Per-keypoint confidence in [0, 1]. Shape (21,).
    """

    header: Header
    handedness: Handedness
    index: int
    score: float
    keypoints: FloatArray
    confidence: FloatArray


@dataclass(frozen=True, slots=True)
class PoseMessage:
    """One detected body, already in operator axes and with the mirror convention applied.

    Attributes:
        positions: Joint positions [m], operator axes, origin between the hips, in
            :data:`POSE_JOINTS` order. Shape (33, 3).
        visibility: Per-joint visibility in [0, 1]. Shape (33,).
        presence: Per-joint presence in [0, 1]. Shape (33,).
    """

    header: Header
    positions: FloatArray
    visibility: FloatArray
    presence: FloatArray


@dataclass(frozen=True, slots=True)
class FrameMessage:
    """End-of-frame summary: how many hands and bodies the frame had and what it cost.

    Attributes:
        hands: Hands detected in the frame.
        poses: Bodies detected in the frame (0 or 1).
        processing_ms: Tracker time for the frame (decode to RGB + MediaPipe) [ms].
    """

    header: Header
    hands: int
    poses: int
    processing_ms: float


@dataclass(frozen=True, slots=True)
class EventMessage:
    """A tracker lifecycle event.

    Attributes:
        code: ``"started"``, ``"end"`` (the file ended) or ``"error"``.
        text: One-line description.
    """

    header: Header
    code: str
    text: str


Message = HandMessage | PoseMessage | FrameMessage | EventMessage

_EVENT_CODES = {EVENT_STARTED: "started", EVENT_END: "end", EVENT_ERROR: "error"}


def _operator_axes(world: FloatArray, mirrored: bool) -> FloatArray:
    """MediaPipe image-aligned world coordinates (N, 3) → operator axes (N, 3)."""
    out = np.empty_like(world)
    out[:, 0] = -world[:, 2]
    out[:, 1] = -world[:, 0] if mirrored else world[:, 0]
    out[:, 2] = -world[:, 1]
    return out


def _scores(values: FloatArray, what: str) -> FloatArray:
    if not np.all(np.isfinite(values)):
        raise WireError(f"{what} must be finite")
    if values.min() < -_SCORE_SLACK or values.max() > 1.0 + _SCORE_SLACK:
        raise WireError(f"{what} must be in [0, 1], got [{values.min():.4g}, {values.max():.4g}]")
    return np.clip(values, 0.0, 1.0)


def _points(values: FloatArray, limit: float, what: str) -> FloatArray:
    if not np.all(np.isfinite(values)):
        raise WireError(f"{what} must be finite")
    peak = float(np.abs(values).max())
    if peak > limit:
        raise WireError(f"{what} must be within {limit} m of the origin, got {peak:.4g} m")
    return values


def _header(data: bytes) -> Header:
    if len(data) < HEADER.size:
        raise WireError(f"datagram is {len(data)} bytes; a markerless message has at least {HEADER.size}")
    magic, version, kind, flags, capture_ns, device_ns, frame, width, height = HEADER.unpack_from(data)
    if magic != MAGIC:
        raise WireError(f"bad magic {magic!r}; markerless messages start with {MAGIC!r}")
    if version != VERSION:
        raise WireError(f"wire version {version} is not supported; this telerig speaks {VERSION}")
    if flags & ~FLAG_MIRRORED:
        raise WireError(f"unknown flag bits 0x{flags:04x}; only bit 0 (mirrored) is defined")
    if capture_ns <= 0 or device_ns < 0:
        raise WireError(f"capture_ns must be > 0 and device_ns >= 0, got {capture_ns} and {device_ns}")
    if kind in (KIND_HAND, KIND_POSE, KIND_FRAME) and (width == 0 or height == 0):
        raise WireError(f"frame size must be non-zero, got {width}x{height}")
    return Header(kind, bool(flags & FLAG_MIRRORED), capture_ns, device_ns, frame, width, height)


def _expect_size(data: bytes, size: int, what: str) -> None:
    if len(data) != size:
        raise WireError(f"{what} message must be {size} bytes, got {len(data)}")


def decode(data: bytes) -> Message:
    """Decode and validate one datagram; coordinates come out in operator axes (see module doc).

    Raises:
        WireError: On a wrong size, magic, version, kind or flag, a non-finite value, a score
            outside [0, 1] or a landmark farther than :data:`HAND_LIMIT_M` / :data:`POSE_LIMIT_M`.
    """
    head = _header(data)
    kind = head.kind
    if kind == KIND_HAND:
        _expect_size(data, HAND_SIZE, "hand")
        label, index, score = HAND_HEAD.unpack_from(data, HEADER.size)
        if label > 1:
            raise WireError(f"hand label must be 0 (Left) or 1 (Right), got {label}")
        if not (math.isfinite(score) and -_SCORE_SLACK <= score <= 1.0 + _SCORE_SLACK):
            raise WireError(f"hand score must be in [0, 1], got {score}")
        body = f32_to_f64(np.frombuffer(data, dtype="<f4", offset=HEADER.size + HAND_HEAD.size))
        world = _points(body[: HAND_POINTS * 3].reshape(HAND_POINTS, 3), HAND_LIMIT_M, "hand landmarks")
        confidence = _scores(body[HAND_POINTS * 3 :], "hand keypoint confidence")
        # MediaPipe labels as if mirrored: on an unmirrored image its "Right" is the operator's left.
        is_right = (label == 1) == head.mirrored
        return HandMessage(
            head,
            "right" if is_right else "left",
            index,
            min(max(score, 0.0), 1.0),
            _operator_axes(world, head.mirrored),
            confidence,
        )
    if kind == KIND_POSE:
        _expect_size(data, POSE_SIZE, "pose")
        rows = f32_to_f64(np.frombuffer(data, dtype="<f4", offset=HEADER.size)).reshape(POSE_POINTS, 5)
        world = _points(rows[:, :3], POSE_LIMIT_M, "pose landmarks")
        visibility = _scores(rows[:, 3], "pose visibility")
        presence = _scores(rows[:, 4], "pose presence")
        positions = _operator_axes(world, head.mirrored)
        if head.mirrored:
            positions, visibility, presence = (
                positions[_MIRROR_PERM],
                visibility[_MIRROR_PERM],
                presence[_MIRROR_PERM],
            )
        return PoseMessage(head, positions, visibility, presence)
    if kind == KIND_FRAME:
        _expect_size(data, FRAME_SIZE, "frame")
        hands, poses, ms = FRAME_BODY.unpack_from(data, HEADER.size)
        if not (math.isfinite(ms) and 0.0 <= ms < 1e6):
            raise WireError(f"frame processing time must be in [0, 1e6) ms, got {ms}")
        return FrameMessage(head, hands, poses, ms)
    if kind == KIND_EVENT:
        least = HEADER.size + EVENT_HEAD.size
        if not least <= len(data) <= least + MAX_EVENT_TEXT:
            raise WireError(
                f"event message must be {least} to {least + MAX_EVENT_TEXT} bytes, got {len(data)}"
            )
        (code,) = EVENT_HEAD.unpack_from(data, HEADER.size)
        if code not in _EVENT_CODES:
            raise WireError(f"event code must be one of {sorted(_EVENT_CODES)}, got {code}")
        text = data[HEADER.size + EVENT_HEAD.size :].decode("utf-8", errors="replace")
        return EventMessage(head, _EVENT_CODES[code], text.replace("\n", " "))
    raise WireError(f"unknown message kind {kind}; valid: 1 hand, 2 pose, 3 frame, 4 event")


def _quat_from_matrix(r: FloatArray) -> FloatArray:
    """Unit quaternion (w, x, y, z) of a rotation matrix (3, 3) (Shepperd's method)."""
    trace = r[0, 0] + r[1, 1] + r[2, 2]
    if trace > 0.0:
        s = 2.0 * math.sqrt(1.0 + trace)
        q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        q = [(r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s]
    elif r[1, 1] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        q = [(r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        q = [(r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s]
    return quat_normalize(np.array(q))


def wrist_orientation(keypoints: FloatArray, handedness: Handedness) -> FloatArray:
    """Wrist orientation (w, x, y, z) from 21 keypoints (21, 3) in a right-handed frame.

    See the module docstring for the wrist frame's axes.

    Raises:
        WireError: If the wrist, index, middle and little knuckles are (nearly) collinear.
    """
    wrist = keypoints[0]
    x = keypoints[9] - wrist
    to_index = keypoints[5] - wrist
    to_little = keypoints[17] - wrist
    normal = cross3(to_little, to_index) if handedness == "right" else cross3(to_index, to_little)
    nx = float(np.linalg.norm(x))
    if not nx > 1e-6:
        raise WireError("hand is degenerate: the middle knuckle coincides with the wrist")
    x = x / nx
    z = normal - float(np.dot(normal, x)) * x
    nz = float(np.linalg.norm(z))
    if not nz > 1e-9:
        raise WireError("hand is degenerate: wrist and knuckles are collinear")
    z = z / nz
    y = cross3(z, x)
    return _quat_from_matrix(np.column_stack((x, y, z)))


def hand_pose(msg: HandMessage, stamp: Stamp, frame_id: str) -> HandPose:
    """The ``HandPose`` of a decoded hand; wrist position is keypoint 0 [m] in ``frame_id``.

    Raises:
        WireError: If the hand is degenerate (see :func:`wrist_orientation`).
    """
    return HandPose(
        stamp=stamp,
        handedness=msg.handedness,
        wrist_position=msg.keypoints[0],
        wrist_orientation=wrist_orientation(msg.keypoints, msg.handedness),
        keypoints=msg.keypoints,
        keypoint_confidence=msg.confidence,
        frame_id=frame_id,
    )


def body_confidence(msg: PoseMessage) -> float:
    """Skeleton confidence in [0, 1]: mean visibility of the shoulders, elbows and wrists."""
    return float(np.mean(msg.visibility[_CONFIDENCE_JOINTS]))


def body_skeleton(msg: PoseMessage, stamp: Stamp, frame_id: str) -> BodySkeleton:
    """The ``BodySkeleton`` (33 :data:`POSE_JOINTS`) of a decoded pose.

    Orientations are identity quaternions: MediaPipe gives joint positions only.
    """
    return BodySkeleton(
        stamp=stamp,
        joint_names=POSE_JOINTS,
        positions=msg.positions,
        orientations=np.broadcast_to(_IDENTITY, (POSE_POINTS, 4)),
        frame_id=frame_id,
    )


def _fuzz(data: bytes) -> object:
    msg = decode(data)
    stamp = Stamp("fuzz", 0, msg.header.device_ns, msg.header.capture_ns)
    if isinstance(msg, HandMessage):
        return hand_pose(msg, stamp, "hand")
    if isinstance(msg, PoseMessage):
        return body_skeleton(msg, stamp, "hips")
    return msg


#: Parses one datagram into IR (or a frame / event message); raises only ``WireError``.
FUZZ_TARGET: Callable[[bytes], object] = _fuzz
