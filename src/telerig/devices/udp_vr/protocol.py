"""The native VR datagram format (``telerig/v1/vr_stream.proto``): bytes -> validated IR samples, sequencing.

One UDP datagram carries one serialized ``telerig.v1.VrFrame`` (see the .proto for the full
contract). :func:`decode_datagram` validates it and converts every pose from OpenXR stage space
(+y up, -z forward, metres) into telerig's operator frame (x forward, y left, z up, metres);
:func:`datagram_samples` turns the result into IR samples; :class:`SequenceFilter` drops
duplicates and late datagrams and counts loss. Nothing here does I/O.

Body conventions of the emitted samples:

* ``ControllerState`` (source ``"<id>/left"``, ``"<id>/right"``): the scripted controller's
  convention (telerig.devices.scripted): +z the pointing axis, +x the controller's top. OpenXR's
  grip pose (-z pointing, +y top) is rotated into it by :data:`Q_GRIP_TO_CONTROLLER`.
* ``Pose`` of the head (source ``"<id>/head"``): x along the gaze, y left, z up out of the head
  (OpenXR's view space re-axed by :func:`telerig.ir.frames.openxr_to_operator_body_quat`).
* ``HandPose`` (source ``"<id>/left_hand"``, ``"<id>/right_hand"``): wrist pose from
  XR_HAND_JOINT_WRIST with body axes x towards the fingers, z out of the back of the hand; the 21
  keypoints are OpenXR joints picked by :data:`OPENXR_TO_MEDIAPIPE`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Final, Literal

import numpy as np
from google.protobuf.message import DecodeError

from telerig.errors import WireError
from telerig.ir._pb import vr_stream_pb2 as pb
from telerig.ir.types import (
    HAND_KEYPOINTS,
    ControllerState,
    FloatArray,
    Handedness,
    HandPose,
    Pose,
    Sample,
    Stamp,
)

__all__ = [
    "BUTTON_BITS",
    "FORMAT_VERSION",
    "FUZZ_TARGET",
    "MAX_DATAGRAM_BYTES",
    "MAX_POSITION_M",
    "OPENXR_HAND_JOINTS",
    "OPENXR_TO_MEDIAPIPE",
    "QUAT_NORM_TOLERANCE",
    "Q_GRIP_TO_CONTROLLER",
    "ControllerReading",
    "HandReading",
    "SequenceFilter",
    "SequenceVerdict",
    "StampFactory",
    "VrDatagram",
    "datagram_samples",
    "decode_datagram",
]

#: The only ``VrFrame.format_version`` this parser reads.
FORMAT_VERSION: Final = 1
#: Largest datagram accepted [bytes]; a full frame (head, 2 controllers, 2 hands) is about 1.9 KB.
MAX_DATAGRAM_BYTES: Final = 4096
#: Largest accepted |coordinate| of any position in stage space [m].
MAX_POSITION_M: Final = 50.0
#: Accepted deviation of a quaternion's norm from 1 (it is then renormalized).
QUAT_NORM_TOLERANCE: Final = 0.05
_MAX_POSITION_BITS = int(np.array(MAX_POSITION_M, dtype=np.float32).view(np.uint32))
# Analog values may overshoot their range by float noise; beyond this the datagram is rejected.
_ANALOG_TOLERANCE = 1e-3

#: Button names by ``VrButtonBit`` number, as they appear in ``ControllerState.buttons``.
BUTTON_BITS: Final[tuple[tuple[int, str], ...]] = (
    (pb.VR_BUTTON_BIT_A, "a"),
    (pb.VR_BUTTON_BIT_B, "b"),
    (pb.VR_BUTTON_BIT_X, "x"),
    (pb.VR_BUTTON_BIT_Y, "y"),
    (pb.VR_BUTTON_BIT_THUMBSTICK, "thumbstick"),
    (pb.VR_BUTTON_BIT_MENU, "menu"),
)
_BUTTON_MASK = sum(1 << bit for bit, _ in BUTTON_BITS)
# Every subset of the known buttons, precomputed: one lookup per controller on the hot path.
_BUTTON_SETS: tuple[frozenset[str], ...] = tuple(
    frozenset(name for bit, name in BUTTON_BITS if mask >> bit & 1) for mask in range(_BUTTON_MASK + 1)
)

#: XR_EXT_hand_tracking joint names in XR_HAND_JOINT_* order (26 joints).
OPENXR_HAND_JOINTS: Final[tuple[str, ...]] = (
    "palm",
    "wrist",
    "thumb_metacarpal",
    "thumb_proximal",
    "thumb_distal",
    "thumb_tip",
    *(
        f"{finger}_{bone}"
        for finger in ("index", "middle", "ring", "little")
        for bone in ("metacarpal", "proximal", "intermediate", "distal", "tip")
    ),
)
_N_JOINTS = len(OPENXR_HAND_JOINTS)

#: OpenXR joint index for each of the 21 MediaPipe keypoints. An OpenXR joint sits at the proximal
#: end of its bone, so e.g. INDEX_PROXIMAL is the index MCP knuckle. The palm and the four
#: finger metacarpal bases have no MediaPipe counterpart; the thumb metacarpal base is the CMC.
OPENXR_TO_MEDIAPIPE: Final[tuple[int, ...]] = (
    1,  # 0 wrist <- WRIST
    2, 3, 4, 5,  # 1-4 thumb CMC, MCP, IP, tip <- THUMB_METACARPAL, _PROXIMAL, _DISTAL, _TIP
    7, 8, 9, 10,  # 5-8 index MCP, PIP, DIP, tip <- INDEX_PROXIMAL, _INTERMEDIATE, _DISTAL, _TIP
    12, 13, 14, 15,  # 9-12 middle
    17, 18, 19, 20,  # 13-16 ring
    22, 23, 24, 25,  # 17-20 little
)  # fmt: skip
_KEYPOINT_GATHER = np.array([3 * j + axis for j in OPENXR_TO_MEDIAPIPE for axis in (2, 0, 1)])
_KEYPOINT_SIGN = np.tile([-1.0, -1.0, 1.0], HAND_KEYPOINTS)
_ALL_VALID = np.ones(HAND_KEYPOINTS)
_ALL_VALID.flags.writeable = False

_S = math.sqrt(0.5)
#: Quaternion (w, x, y, z) re-axing a grip pose into telerig's controller convention:
#: ``q_controller = openxr_to_operator_body_quat(q_grip) * Q_GRIP_TO_CONTROLLER`` (operator frame).
#: Net effect: controller +z (pointing) = grip -z, controller +x (top) = grip +y, controller +y =
#: grip +x; a grip at OpenXR rest (pointing forward, top up) points along operator +x, top up.
Q_GRIP_TO_CONTROLLER: Final[tuple[float, float, float, float]] = (0.0, _S, 0.0, _S)

SequenceVerdict = Literal["accepted", "restart", "duplicate", "reordered", "stale"]

#: ``(source suffix, confidence) -> Stamp``: the caller decides stamps (source id, seq, clocks).
StampFactory = Callable[[str, float], Stamp]


@dataclass(frozen=True, slots=True)
class ControllerReading:
    """One tracked controller in telerig conventions (see the module docstring).

    Attributes:
        hand: Which hand holds it.
        position: Grip position [m], operator frame. Shape (3,).
        orientation: Orientation (w, x, y, z), unit norm, controller -> operator frame. Shape (4,).
        buttons: Names of the held buttons (from :data:`BUTTON_BITS`).
        trigger: Index trigger in [0, 1].
        grip: Squeeze in [0, 1].
        joystick: Thumbstick (x right, y forward) in [-1, 1]. Shape (2,).
    """

    hand: Handedness
    position: tuple[float, float, float]
    orientation: tuple[float, float, float, float]
    buttons: frozenset[str]
    trigger: float
    grip: float
    joystick: tuple[float, float]


@dataclass(frozen=True, slots=True)
class HandReading:
    """One tracked hand in telerig conventions.

    Attributes:
        hand: ``"left"`` or ``"right"``.
        wrist_position: Wrist joint position [m], operator frame. Shape (3,).
        wrist_orientation: Wrist orientation (w, x, y, z), x towards the fingers, z out of the back
            of the hand, operator frame. Shape (4,).
        keypoints: MediaPipe-order keypoints [m], operator frame. Shape (21, 3).
        keypoint_confidence: 1 where the joint was valid, 0 where the sender flagged it invalid.
            Shape (21,).
        confidence: Fraction of valid keypoints, in [0, 1].
    """

    hand: Handedness
    wrist_position: FloatArray
    wrist_orientation: tuple[float, float, float, float]
    keypoints: FloatArray
    keypoint_confidence: FloatArray
    confidence: float


@dataclass(frozen=True, slots=True)
class VrDatagram:
    """One decoded and validated datagram, converted to the operator frame, not yet stamped.

    Attributes:
        stream_id: Sender's random stream id (0 if it has none).
        seq: Datagram sequence number within the stream.
        device_ns: Sender's clock when the poses were sampled [ns]; 0 if the sender has none.
        head: Head position [m] and orientation (w, x, y, z), operator frame; None if untracked.
            Shapes (3,) and (4,).
        controllers: Tracked controllers, left before right.
        hands: Tracked hands, left before right.
        device: Sender's informational device name.
    """

    stream_id: int
    seq: int
    device_ns: int
    head: tuple[tuple[float, float, float], tuple[float, float, float, float]] | None
    controllers: tuple[ControllerReading, ...]
    hands: tuple[HandReading, ...]
    device: str


def _position(x: float, y: float, z: float, where: str) -> tuple[float, float, float]:
    # abs() <= limit is False for NaN, so this one test rejects NaN, inf and out-of-range values.
    if not (abs(x) <= MAX_POSITION_M and abs(y) <= MAX_POSITION_M and abs(z) <= MAX_POSITION_M):
        raise WireError(
            f"{where} position must be finite metres within ±{MAX_POSITION_M:g} m, got ({x}, {y}, {z})"
        )
    return (-z, -x, y)  # openxr_to_operator_points, inlined


def _unit_xyzw(x: float, y: float, z: float, w: float, where: str) -> tuple[float, float, float, float]:
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if not abs(n - 1.0) <= QUAT_NORM_TOLERANCE:
        raise WireError(
            f"{where} orientation must be a unit quaternion (x, y, z, w) "
            f"(norm 1 ± {QUAT_NORM_TOLERANCE}), got norm {n}"
        )
    if w < 0.0:  # one canonical sign, as telerig.ir.frames.quat_normalize produces
        n = -n
    return x / n, y / n, z / n, w / n


def _analog(value: float, low: float, where: str) -> float:
    if not (low - _ANALOG_TOLERANCE <= value <= 1.0 + _ANALOG_TOLERANCE):
        raise WireError(f"{where} must be in [{low:g}, 1], got {value}")
    return min(1.0, max(low, value))


def _controller(msg: pb.VrController, hand: Handedness) -> ControllerReading:
    g = msg.grip
    where = f"{hand} controller"
    position = _position(g.px, g.py, g.pz, where)
    x, y, z, w = _unit_xyzw(g.qx, g.qy, g.qz, g.qw, where)
    # body(q) = (w, -z, -x, y) (openxr_to_operator_body_quat), then * Q_GRIP_TO_CONTROLLER.
    orientation = _grip_to_controller(w, -z, -x, y)
    return ControllerReading(
        hand=hand,
        position=position,
        orientation=orientation,
        buttons=_BUTTON_SETS[msg.buttons & _BUTTON_MASK],
        trigger=_analog(msg.trigger, 0.0, f"{where} trigger"),
        grip=_analog(msg.squeeze, 0.0, f"{where} squeeze"),
        joystick=(
            _analog(msg.thumbstick_x, -1.0, f"{where} thumbstick_x"),
            _analog(msg.thumbstick_y, -1.0, f"{where} thumbstick_y"),
        ),
    )


def _grip_to_controller(a: float, b: float, c: float, d: float) -> tuple[float, float, float, float]:
    """Hamilton product (a, b, c, d) * Q_GRIP_TO_CONTROLLER, scalar first, with w >= 0."""
    w = _S * (-b - d)
    x = _S * (a + c)
    y = _S * (d - b)
    z = _S * (a - c)
    return (-w, -x, -y, -z) if w < 0.0 else (w, x, y, z)


def _hand(msg: pb.VrHand, hand: Handedness) -> HandReading:
    where = f"{hand}_hand"
    positions, orientations = msg.joint_positions, msg.joint_orientations
    n_pos, n_ori, n_rad = len(positions), len(orientations), len(msg.joint_radii)
    if n_pos != 3 * _N_JOINTS or n_ori != 4 * _N_JOINTS or n_rad != _N_JOINTS:
        raise WireError(
            f"{where}: a tracked hand must carry {_N_JOINTS} joints: joint_positions length "
            f"{3 * _N_JOINTS}, joint_orientations {4 * _N_JOINTS}, joint_radii {_N_JOINTS}; "
            f"got {n_pos}, {n_ori}, {n_rad}"
        )
    # The wire floats are float32; compare their bit patterns: for |x| the IEEE order is the integer
    # order and NaN/inf sort above every finite value, so one integer max checks finiteness and range
    # without touching the FPU (a signalling NaN would raise numpy's "invalid value" warning).
    flat32 = np.asarray(positions, dtype=np.float32)
    magnitude = flat32.view(np.uint32) & np.uint32(0x7FFFFFFF)
    if int(magnitude.max()) > _MAX_POSITION_BITS:
        bad = int(np.argmax(magnitude > _MAX_POSITION_BITS)) // 3
        raise WireError(
            f"{where} joint {OPENXR_HAND_JOINTS[bad]} position must be finite metres within "
            f"±{MAX_POSITION_M:g} m, got {tuple(float(v) for v in positions[3 * bad : 3 * bad + 3])}"
        )
    flat = flat32.astype(np.float64)
    # One gather does the MediaPipe selection and the axis change (x, y, z) <- (-z, -x, y).
    keypoints = (flat[_KEYPOINT_GATHER] * _KEYPOINT_SIGN).reshape(HAND_KEYPOINTS, 3)
    x, y, z, w = _unit_xyzw(
        orientations[4], orientations[5], orientations[6], orientations[7], f"{where} wrist"
    )  # joint 1 = WRIST
    invalid = msg.joint_invalid_mask
    if invalid:
        confidence = np.array([0.0 if invalid >> j & 1 else 1.0 for j in OPENXR_TO_MEDIAPIPE])
        overall = float(confidence.mean())
    else:
        confidence, overall = _ALL_VALID, 1.0
    return HandReading(
        hand=hand,
        wrist_position=keypoints[0],
        wrist_orientation=(w, -z, -x, y),  # openxr_to_operator_body_quat, inlined
        keypoints=keypoints,
        keypoint_confidence=confidence,
        confidence=overall,
    )


def decode_datagram(data: bytes) -> VrDatagram:
    """Decode and validate one datagram; convert its poses to the operator frame.

    Args:
        data: One UDP payload: a serialized ``telerig.v1.VrFrame``, at most
            :data:`MAX_DATAGRAM_BYTES` bytes.

    Raises:
        WireError: Oversize or undecodable payload, wrong ``format_version``, negative
            ``device_time_ns``, a tracked part with a non-finite or out-of-range position
            (|coordinate| > :data:`MAX_POSITION_M`), a non-unit quaternion, an analog value out
            of range, or hand arrays of the wrong length. The whole datagram is rejected.
    """
    if len(data) > MAX_DATAGRAM_BYTES:
        raise WireError(f"datagram is {len(data)} bytes; the format allows at most {MAX_DATAGRAM_BYTES}")
    try:
        msg = pb.VrFrame.FromString(data)
    except (DecodeError, ValueError, TypeError) as exc:  # upb raises DecodeError; be defensive
        raise WireError(f"datagram is not a telerig.v1.VrFrame protobuf message ({exc})") from None
    if msg.format_version != FORMAT_VERSION:
        raise WireError(
            f"VrFrame.format_version must be {FORMAT_VERSION}, got {msg.format_version} "
            "(0 means the field is missing; update the sender or telerig)"
        )
    if msg.device_time_ns < 0:
        raise WireError(f"VrFrame.device_time_ns must be >= 0 (0 = none), got {msg.device_time_ns}")
    head = None
    if msg.head_tracked:
        h = msg.head
        x, y, z, w = _unit_xyzw(h.qx, h.qy, h.qz, h.qw, "head")
        head = (_position(h.px, h.py, h.pz, "head"), (w, -z, -x, y))  # openxr_to_operator_body_quat
    controllers: list[ControllerReading] = []
    hands: list[HandReading] = []
    if msg.left.tracked:
        controllers.append(_controller(msg.left, "left"))
    if msg.right.tracked:
        controllers.append(_controller(msg.right, "right"))
    if msg.left_hand.tracked:
        hands.append(_hand(msg.left_hand, "left"))
    if msg.right_hand.tracked:
        hands.append(_hand(msg.right_hand, "right"))
    return VrDatagram(
        stream_id=msg.stream_id,
        seq=msg.seq,
        device_ns=msg.device_time_ns,
        head=head,
        controllers=tuple(controllers),
        hands=tuple(hands),
        device=msg.device,
    )


def datagram_samples(datagram: VrDatagram, stamp: StampFactory, frame_id: str = "operator") -> list[Sample]:
    """IR samples of one decoded datagram: head ``Pose``, ``ControllerState`` and ``HandPose`` per part.

    Args:
        datagram: From :func:`decode_datagram`.
        stamp: Called once per sample with its source suffix (``"head"``, ``"left"``, ``"right"``,
            ``"left_hand"``, ``"right_hand"``) and confidence in [0, 1] (a hand's is the fraction of
            valid keypoints); returns the sample's stamp.
        frame_id: Frame the (operator-frame) poses are labelled with.

    Returns:
        Samples in the order head, left controller, right controller, left hand, right hand,
        skipping untracked parts.
    """
    out: list[Sample] = []
    if datagram.head is not None:
        position, orientation = datagram.head
        out.append(Pose(stamp("head", 1.0), np.array(position), np.array(orientation), frame_id))
    for c in datagram.controllers:
        out.append(
            ControllerState(
                stamp=stamp(c.hand, 1.0),
                hand=c.hand,
                position=np.array(c.position),
                orientation=np.array(c.orientation),
                frame_id=frame_id,
                buttons=c.buttons,
                trigger=c.trigger,
                grip=c.grip,
                joystick=np.array(c.joystick),
            )
        )
    for h in datagram.hands:
        out.append(
            HandPose(
                stamp=stamp(f"{h.hand}_hand", h.confidence),
                handedness=h.hand,
                wrist_position=h.wrist_position,
                wrist_orientation=np.array(h.wrist_orientation),
                keypoints=h.keypoints,
                keypoint_confidence=h.keypoint_confidence,
                frame_id=frame_id,
            )
        )
    return out


class SequenceFilter:
    """Order datagrams by sequence number: pass new ones, drop duplicates and late ones, count loss.

    Per stream (``stream_id``): a datagram newer than the newest seen is accepted, and the
    sequence numbers it skips are counted as ``lost``. An older one is dropped: as ``reordered``
    if it was missing (it then leaves ``lost``, so ``lost`` counts numbers never received), as a
    ``duplicate`` if it was already received, as ``stale`` if it is more than ``window`` behind.
    A new ``stream_id``, a jump forward by more than ``max_gap``, or ``restart_after``
    consecutive stale numbers in a row (a sender that restarted without a stream id) start the
    stream over and count a ``restart``.

    ``counts`` holds ``lost``, ``duplicate``, ``reordered``, ``stale`` and ``restart``.
    """

    def __init__(self, window: int = 1024, max_gap: int = 1 << 20, restart_after: int = 3) -> None:
        """Args:
        window: How many sequence numbers back a late datagram is told apart (>= 1).
        max_gap: Largest forward jump counted as loss rather than a restart (>= window).
        restart_after: Consecutive stale sequence numbers that mean the sender restarted (>= 1).
        """
        if window < 1 or max_gap < window or restart_after < 1:
            raise ValueError(
                "need window >= 1, max_gap >= window and restart_after >= 1, "
                f"got window={window}, max_gap={max_gap}, restart_after={restart_after}"
            )
        self.window = window
        self.max_gap = max_gap
        self.restart_after = restart_after
        self.counts: dict[str, int] = {"lost": 0, "duplicate": 0, "reordered": 0, "stale": 0, "restart": 0}
        self._stream: int | None = None
        self._newest = 0
        self._missing: set[int] = set()
        self._stale_next = -1
        self._stale_run = 0

    def reset(self) -> None:
        """Forget the stream (counts are kept); the next datagram is accepted as the first."""
        self._stream = None
        self._missing.clear()
        self._stale_run = 0

    def accept(self, stream_id: int, seq: int) -> SequenceVerdict:
        """Classify one datagram; ``"accepted"`` and ``"restart"`` mean pass it on."""
        if self._stream is None:
            self._start(stream_id, seq)
            return "accepted"
        ahead = seq - self._newest
        if stream_id != self._stream or ahead > self.max_gap:
            return self._restart(stream_id, seq)
        if ahead > 0:
            if ahead > 1:
                self.counts["lost"] += ahead - 1
                self._missing.update(range(max(self._newest + 1, seq - self.window), seq))
                if len(self._missing) > 2 * self.window:
                    floor = seq - self.window
                    self._missing = {s for s in self._missing if s >= floor}
            self._newest = seq
            self._stale_run = 0
            return "accepted"
        if ahead >= -self.window:
            if seq in self._missing:
                self._missing.discard(seq)
                self.counts["lost"] -= 1
                self.counts["reordered"] += 1
                return "reordered"
            self.counts["duplicate"] += 1
            return "duplicate"
        self._stale_run = self._stale_run + 1 if seq == self._stale_next else 1
        self._stale_next = seq + 1
        if self._stale_run >= self.restart_after:
            return self._restart(stream_id, seq)
        self.counts["stale"] += 1
        return "stale"

    def _start(self, stream_id: int, seq: int) -> None:
        self._stream, self._newest = stream_id, seq
        self._missing.clear()
        self._stale_run = 0

    def _restart(self, stream_id: int, seq: int) -> SequenceVerdict:
        self._start(stream_id, seq)
        self.counts["restart"] += 1
        return "restart"


def _fuzz_parse(data: bytes) -> list[Sample]:
    datagram = decode_datagram(data)
    return datagram_samples(datagram, lambda source, confidence: Stamp(source, 0, 0, 0, 0, confidence))


#: Parses one datagram into IR samples; raises only :class:`telerig.errors.WireError`.
FUZZ_TARGET: Callable[[bytes], object] = _fuzz_parse
