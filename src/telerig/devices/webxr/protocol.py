"""WebXR page wire format (binary, little-endian Float32) → IR samples in the operator frame.

Wire format, version 1. Every message the page sends is one binary WebSocket message starting
with a 4-byte header ``b"TX" | u8 version (1) | u8 kind``:

* kind 1, **frame** (page → server, one per XR frame or desktop tick)::

      offset  type     field
      0       4 bytes  header  b"TX\\x01\\x01"
      4       u32      seq           per-connection message counter, +1 per frame
      8       f64      client_ms     performance.timeOrigin + XRFrame time [ms since Unix epoch]
      16      u8       mode          0 desktop (virtual controllers), 1 immersive-vr, 2 immersive-ar
      17      u8       present       bit0 head, bit1 left controller, bit2 right controller,
                                     bit3 left hand, bit4 right hand (bits 5-7 must be 0)
      18      u16      reserved      0
      20      blocks, in bit order, only those flagged present:
              head         7 x f32   position x y z [m], orientation x y z w      (28 bytes)
              controller   7 x f32   grip pose as above
                           4 x f32   trigger, squeeze [0, 1], thumbstick x, y [-1, 1]
                                     (Gamepad API: y = -1 is pushed forward)
                           u32       buttons pressed, bit i = xr-standard gamepad.buttons[i]
                                     (0 trigger, 1 squeeze, 2 touchpad, 3 thumbstick,
                                     4 A / X, 5 B / Y)                             (48 bytes)
              hand         25 x 8 f32  per XRHand joint in order (wrist, thumb-metacarpal, ...,
                                     pinky-finger-tip): position x y z [m],
                                     orientation x y z w, radius [m] (0 = joint not tracked)
                                                                                   (800 bytes)

* kind 2, **pong** (page → server): ``u32 ping_id | f64 client_ms`` (16 bytes in all), the page's
  clock (performance.timeOrigin + performance.now()) when it received ping ``ping_id``.
* kind 3, **ping** (server → page): ``u32 ping_id`` (8 bytes in all).

Frames: poses arrive in the WebXR ``local-floor`` reference space (x right, y up, z backward,
metres, origin on the floor) and leave in the operator frame (x forward, y left, z up; see
:mod:`telerig.devices.scripted`): ``p_op = (-z, -x, y)``. Orientations:

* controller: the WebXR grip space (-z along the controller, +y up out of its top) becomes the
  scripted-controller convention (+z pointing axis, +x top);
* hand wrist: the WebXR wrist joint (-z toward the fingers, +y out of the back of the hand)
  becomes the same convention (+z toward the fingers, +x out of the back of the hand), so a
  flat hand pointing forward has the orientation of a controller pointing forward;
* head: the WebXR viewer (-z gaze, +y up) becomes a head frame with x gaze, y left, z up
  (identity when looking level along operator x).

Hands: the 25 WebXR joints map to the 21 MediaPipe keypoints by dropping the four finger
metacarpal joints (index, middle, ring, little); thumb-metacarpal is MediaPipe's thumb CMC.
"""

from __future__ import annotations

import math
import struct
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from telerig.devices.floats import f32_to_f64
from telerig.errors import WireError
from telerig.ir.types import ControllerState, FloatArray, Handedness, HandPose, Pose, Sample, Stamp

__all__ = [
    "BUTTON_NAMES",
    "FUZZ_TARGET",
    "HAND_JOINTS",
    "MAX_POSITION_M",
    "MEDIAPIPE_FROM_WEBXR",
    "ClockOffset",
    "ControllerReading",
    "HandReading",
    "Pong",
    "WebXRWireError",
    "XRFrame",
    "decode",
    "encode_ping",
    "frame_samples",
]

MAGIC = b"TX"
VERSION = 1
KIND_FRAME = 1
KIND_PONG = 2
KIND_PING = 3

#: Largest accepted |coordinate| of any position [m] (room scale with margin).
MAX_POSITION_M = 50.0
#: Largest accepted hand joint radius [m].
MAX_JOINT_RADIUS_M = 0.1
# Analog values may overshoot their range by float rounding; beyond this they are rejected.
_ANALOG_TOLERANCE = 1e-3
# A quaternion whose norm is further than this from 1 is rejected, not silently normalized.
_QUAT_NORM_TOLERANCE = 0.05
# Plausible client clock [ms since epoch]: 2001-09-09 .. 2286-11-20.
_CLIENT_MS_RANGE = (1e12, 1e13)

#: XRHand joint names in wire order (WebXR Hand Input, 25 joints).
HAND_JOINTS: tuple[str, ...] = (
    "wrist",
    "thumb-metacarpal",
    "thumb-phalanx-proximal",
    "thumb-phalanx-distal",
    "thumb-tip",
    *(
        f"{finger}-{part}"
        for finger in ("index-finger", "middle-finger", "ring-finger", "pinky-finger")
        for part in ("metacarpal", "phalanx-proximal", "phalanx-intermediate", "phalanx-distal", "tip")
    ),
)
#: WebXR joint index of each MediaPipe keypoint (0 wrist, 1-4 thumb, 5-8 index, ..., 17-20 little).
MEDIAPIPE_FROM_WEBXR: tuple[int, ...] = (0, 1, 2, 3, 4, *(b + k for b in (6, 11, 16, 21) for k in range(4)))

#: Names of the xr-standard gamepad buttons by bit, per hand (bits 4 and 5 differ per hand).
BUTTON_NAMES: dict[Handedness, tuple[str, ...]] = {
    "right": ("trigger", "grip", "touchpad", "thumbstick", "a", "b"),
    "left": ("trigger", "grip", "touchpad", "thumbstick", "x", "y"),
}

_HEADER = struct.Struct("<2sBB")
_FRAME_HEAD = struct.Struct("<2sBBIdBBH")
_PONG = struct.Struct("<2sBBId")
_PING = struct.Struct("<2sBBI")
_POSE = struct.Struct("<7f")
_CONTROLLER = struct.Struct("<11fI")
_HAND_FLOATS = len(HAND_JOINTS) * 8
_BLOCK_SIZES = (_POSE.size, _CONTROLLER.size, _CONTROLLER.size, _HAND_FLOATS * 4, _HAND_FLOATS * 4)
_MODES: tuple[str, ...] = ("desktop", "immersive-vr", "immersive-ar")

Quat = tuple[float, float, float, float]

# Operator <- WebXR reference space: p_op = M p_xr with M = [[0,0,-1],[-1,0,0],[0,1,0]].
_MP_INDEX = np.array(MEDIAPIPE_FROM_WEBXR)
_M = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
_MT = np.ascontiguousarray(_M.T)
# The same rotation as a quaternion (w, x, y, z), and its inverse.
_Q_M: Quat = (0.5, 0.5, -0.5, -0.5)
_Q_M_INV: Quat = (0.5, -0.5, 0.5, 0.5)
# WebXR grip/joint frame <- telerig controller frame: x_c = y_g, y_c = x_g, z_c = -z_g.
_Q_G: Quat = (0.0, math.sqrt(0.5), math.sqrt(0.5), 0.0)


class WebXRWireError(WireError):
    """A malformed WebXR page message; ``reason`` is a short key for drop counters."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


@dataclass(frozen=True, slots=True)
class ControllerReading:
    """One controller in a frame, operator frame.

    Attributes:
        hand: Which hand holds it.
        position: Grip position [m]. Shape (3,).
        orientation: (w, x, y, z), controller convention of :mod:`telerig.devices.scripted`.
        trigger: Trigger in [0, 1].
        grip: Squeeze in [0, 1].
        joystick: Thumbstick (x right, y forward) in [-1, 1]. Shape (2,).
        buttons: Names of the buttons held down (see :data:`BUTTON_NAMES`).
    """

    hand: Handedness
    position: FloatArray
    orientation: FloatArray
    trigger: float
    grip: float
    joystick: FloatArray
    buttons: frozenset[str]


@dataclass(frozen=True, slots=True)
class HandReading:
    """One tracked hand in a frame, operator frame.

    Attributes:
        hand: Which hand.
        wrist_position: Wrist position [m]. Shape (3,).
        wrist_orientation: (w, x, y, z); +z toward the fingers, +x out of the back of the hand.
        keypoints: 21 MediaPipe-order keypoints [m]; untracked ones sit at the wrist. Shape (21, 3).
        keypoint_confidence: 1 for tracked keypoints, 0 otherwise. Shape (21,).
        radii: WebXR joint radii [m], 0 where untracked. Shape (25,).
        confidence: Fraction of the 21 keypoints that are tracked, in [0, 1].
    """

    hand: Handedness
    wrist_position: FloatArray
    wrist_orientation: FloatArray
    keypoints: FloatArray
    keypoint_confidence: FloatArray
    radii: FloatArray
    confidence: float


@dataclass(frozen=True, slots=True)
class XRFrame:
    """One decoded frame message, validated and converted to the operator frame.

    Attributes:
        seq: Per-connection message counter from the page.
        client_ns: Page clock at the XR frame [ns since Unix epoch] (not yet offset-corrected).
        mode: ``"desktop"``, ``"immersive-vr"`` or ``"immersive-ar"``.
        head: Head (position [m] (3,), orientation (w, x, y, z) (4,)) or ``None``.
        controllers: Controllers present, left before right.
        hands: Tracked hands present, left before right.
    """

    seq: int
    client_ns: int
    mode: str
    head: tuple[FloatArray, FloatArray] | None
    controllers: tuple[ControllerReading, ...]
    hands: tuple[HandReading, ...]


@dataclass(frozen=True, slots=True)
class Pong:
    """The page's answer to a server ping: its clock [ns since epoch] when the ping arrived."""

    ping_id: int
    client_ns: int


def _qmul(a: Quat, b: Quat) -> Quat:
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


def _unit(x: float, y: float, z: float, w: float, what: str) -> Quat:
    """WebXR (x, y, z, w) → validated unit (w, x, y, z)."""
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if not abs(n - 1.0) <= _QUAT_NORM_TOLERANCE:
        raise WebXRWireError(
            "orientation", f"{what} orientation must be a unit quaternion (norm 1 +- 0.05), got norm {n:.4g}"
        )
    return (w / n, x / n, y / n, z / n)


def _canonical(q: Quat) -> FloatArray:
    w, x, y, z = q
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if w < 0.0:
        n = -n
    return np.array((w / n, x / n, y / n, z / n))


def _position(x: float, y: float, z: float, what: str) -> FloatArray:
    if not (abs(x) <= MAX_POSITION_M and abs(y) <= MAX_POSITION_M and abs(z) <= MAX_POSITION_M):
        # Also catches NaN: every comparison with NaN is false.
        raise WebXRWireError(
            "position", f"{what} position must be finite within +-{MAX_POSITION_M} m, got ({x}, {y}, {z})"
        )
    return np.array((-z, -x, y))


def _analog(value: float, lo: float, what: str) -> float:
    if not (lo - _ANALOG_TOLERANCE <= value <= 1.0 + _ANALOG_TOLERANCE):
        raise WebXRWireError("analog", f"{what} must be in [{lo:g}, 1], got {value}")
    return min(1.0, max(lo, value))


def _decode_controller(data: bytes, offset: int, hand: Handedness) -> ControllerReading:
    px, py, pz, qx, qy, qz, qw, trig, squeeze, ax, ay, bits = _CONTROLLER.unpack_from(data, offset)
    position = _position(px, py, pz, f"{hand} controller")
    q_xr = _unit(qx, qy, qz, qw, f"{hand} controller")
    names = BUTTON_NAMES[hand]
    buttons = frozenset((names[i] if i < len(names) else f"button{i}") for i in range(32) if bits >> i & 1)
    return ControllerReading(
        hand=hand,
        position=position,
        orientation=_canonical(_qmul(_qmul(_Q_M, q_xr), _Q_G)),
        trigger=_analog(trig, 0.0, f"{hand} trigger"),
        grip=_analog(squeeze, 0.0, f"{hand} squeeze"),
        # Gamepad API y is -1 when pushed forward; the IR wants +1 forward.
        joystick=np.array(
            (_analog(ax, -1.0, f"{hand} thumbstick x"), -_analog(ay, -1.0, f"{hand} thumbstick y"))
        ),
        buttons=buttons,
    )


def _decode_hand(data: bytes, offset: int, hand: Handedness) -> HandReading:
    joints = np.frombuffer(data, dtype="<f4", count=_HAND_FLOATS, offset=offset).reshape(25, 8)
    xyz = joints[:, :3]
    # max() propagates NaN, and every comparison with NaN is false: one check covers non-finite too.
    extent = float(np.abs(xyz).max())
    if not extent <= MAX_POSITION_M:
        raise WebXRWireError(
            "position",
            f"{hand} hand joint positions must be finite within +-{MAX_POSITION_M} m, got {extent}",
        )
    radii = f32_to_f64(joints[:, 7])
    r_min, r_max = float(radii.min()), float(radii.max())
    if not (r_min >= 0.0 and r_max <= MAX_JOINT_RADIUS_M):
        raise WebXRWireError(
            "range", f"{hand} hand joint radii must be in [0, {MAX_JOINT_RADIUS_M}] m, got [{r_min}, {r_max}]"
        )
    if radii[0] <= 0.0:
        raise WebXRWireError("untracked", f"{hand} hand is flagged present but its wrist is not tracked")
    qx, qy, qz, qw = (float(v) for v in joints[0, 3:7])
    q_xr = _unit(qx, qy, qz, qw, f"{hand} wrist")
    positions = xyz @ _MT
    tracked = radii > 0.0
    if r_min <= 0.0:
        positions[~tracked] = positions[0]
    confidence = tracked[_MP_INDEX].astype(np.float64)
    return HandReading(
        hand=hand,
        wrist_position=positions[0].copy(),
        wrist_orientation=_canonical(_qmul(_qmul(_Q_M, q_xr), _Q_G)),
        keypoints=positions[_MP_INDEX],
        keypoint_confidence=confidence,
        radii=radii,
        confidence=float(confidence.sum()) / len(MEDIAPIPE_FROM_WEBXR),
    )


def _client_ns(client_ms: float) -> int:
    lo, hi = _CLIENT_MS_RANGE
    if not lo <= client_ms <= hi:
        raise WebXRWireError(
            "timestamp",
            f"client_ms must be performance.timeOrigin + time in ms since the Unix epoch, got {client_ms}",
        )
    return round(client_ms * 1e6)


def decode(data: bytes) -> XRFrame | Pong:
    """Decode one page message (see the module docstring) into an :class:`XRFrame` or :class:`Pong`.

    Raises:
        WebXRWireError: (a :class:`~telerig.errors.WireError`) if the message is truncated, has
            the wrong magic, version or kind, or carries a non-finite or out-of-range value.
    """
    if len(data) < _HEADER.size:
        raise WebXRWireError("size", f"message must be at least {_HEADER.size} bytes, got {len(data)}")
    magic, version, kind = _HEADER.unpack_from(data)
    if magic != MAGIC:
        raise WebXRWireError("magic", f"message must start with {MAGIC!r}, got {bytes(magic)!r}")
    if version != VERSION:
        raise WebXRWireError(
            "version", f"wire version must be {VERSION}, got {version}; reload the page from this server"
        )
    if kind == KIND_PONG:
        if len(data) != _PONG.size:
            raise WebXRWireError("size", f"pong must be {_PONG.size} bytes, got {len(data)}")
        _, _, _, ping_id, client_ms = _PONG.unpack(data)
        return Pong(ping_id, _client_ns(client_ms))
    if kind != KIND_FRAME:
        raise WebXRWireError(
            "kind", f"message kind must be {KIND_FRAME} (frame) or {KIND_PONG} (pong), got {kind}"
        )
    if len(data) < _FRAME_HEAD.size:
        raise WebXRWireError("size", f"frame must be at least {_FRAME_HEAD.size} bytes, got {len(data)}")
    _, _, _, seq, client_ms, mode, present, _ = _FRAME_HEAD.unpack_from(data)
    if mode >= len(_MODES):
        raise WebXRWireError(
            "mode", f"mode must be 0 (desktop), 1 (immersive-vr) or 2 (immersive-ar), got {mode}"
        )
    if present >> 5:
        raise WebXRWireError("flags", f"present flags must use bits 0-4 only, got {present:#04x}")
    expected = _FRAME_HEAD.size + sum(size for bit, size in enumerate(_BLOCK_SIZES) if present >> bit & 1)
    if len(data) != expected:
        raise WebXRWireError(
            "size", f"frame with present flags {present:#04x} must be {expected} bytes, got {len(data)}"
        )
    client_ns = _client_ns(client_ms)
    offset = _FRAME_HEAD.size
    head: tuple[FloatArray, FloatArray] | None = None
    if present & 1:
        px, py, pz, qx, qy, qz, qw = _POSE.unpack_from(data, offset)
        q_xr = _unit(qx, qy, qz, qw, "head")
        head = (_position(px, py, pz, "head"), _canonical(_qmul(_qmul(_Q_M, q_xr), _Q_M_INV)))
        offset += _POSE.size
    controllers: list[ControllerReading] = []
    for bit, hand in ((1, "left"), (2, "right")):
        if present >> bit & 1:
            controllers.append(_decode_controller(data, offset, hand))  # type: ignore[arg-type]
            offset += _CONTROLLER.size
    hands: list[HandReading] = []
    for bit, hand in ((3, "left"), (4, "right")):
        if present >> bit & 1:
            hands.append(_decode_hand(data, offset, hand))  # type: ignore[arg-type]
            offset += _HAND_FLOATS * 4
    return XRFrame(seq, client_ns, _MODES[mode], head, tuple(controllers), tuple(hands))


def encode_ping(ping_id: int) -> bytes:
    """The server → page ping message for ``ping_id`` (u32)."""
    return _PING.pack(MAGIC, VERSION, KIND_PING, ping_id & 0xFFFFFFFF)


def frame_samples(
    frame: XRFrame,
    device_id: str,
    capture_ns: int,
    next_seq: Callable[[str], int],
    *,
    frame_id: str = "operator",
) -> list[Sample]:
    """IR samples of one frame: head :class:`Pose`, :class:`ControllerState` s, :class:`HandPose` s.

    Source ids: ``"<id>/head"``, ``"<id>/left"`` / ``"<id>/right"`` (controllers),
    ``"<id>/left_hand"`` / ``"<id>/right_hand"``. ``device_ns`` is the page clock
    (``frame.client_ns``), ``capture_ns`` the same instant in the common clock; ``next_seq(source_id)``
    returns the per-source sequence number. Hand confidence is the tracked fraction of keypoints.
    """
    out: list[Sample] = []
    device_ns = frame.client_ns
    if frame.head is not None:
        sid = f"{device_id}/head"
        out.append(
            Pose(Stamp(sid, next_seq(sid), device_ns, capture_ns), frame.head[0], frame.head[1], frame_id)
        )
    for c in frame.controllers:
        sid = f"{device_id}/{c.hand}"
        out.append(
            ControllerState(
                stamp=Stamp(sid, next_seq(sid), device_ns, capture_ns),
                hand=c.hand,
                position=c.position,
                orientation=c.orientation,
                frame_id=frame_id,
                buttons=c.buttons,
                trigger=c.trigger,
                grip=c.grip,
                joystick=c.joystick,
            )
        )
    for h in frame.hands:
        sid = f"{device_id}/{h.hand}_hand"
        out.append(
            HandPose(
                stamp=Stamp(sid, next_seq(sid), device_ns, capture_ns, confidence=h.confidence),
                handedness=h.hand,
                wrist_position=h.wrist_position,
                wrist_orientation=h.wrist_orientation,
                keypoints=h.keypoints,
                keypoint_confidence=h.keypoint_confidence,
                frame_id=frame_id,
            )
        )
    return out


class ClockOffset:
    """Estimates ``offset_ns = common clock - page clock`` for one connection (pure; feed it times).

    Primary: ping/pong. The server stamps a ping when sent (t0) and its pong when received (t1);
    the page reports its clock tc on receipt, so ``offset ~= (t0 + t1) / 2 - tc`` with an error of
    at most half the round trip. The estimate comes from the pong with the smallest round trip
    among the last ``window`` pongs (follows clock drift, ignores queueing spikes).

    Fallback before the first pong: the smallest ``receive - client`` seen over frames, which
    overestimates the offset by the one-way latency (a sample is never stamped later than it
    arrived).
    """

    def __init__(self, window: int = 16) -> None:
        """Args:
        window: Number of recent pongs the minimum-round-trip choice is made over (>= 1).
        """
        self._pongs: deque[tuple[int, int]] = deque(maxlen=max(1, window))  # (rtt, offset)
        self._frame_min: int | None = None
        self._offset: int | None = None

    @property
    def offset_ns(self) -> int | None:
        """Current estimate [ns], or ``None`` before any observation."""
        return self._offset

    @property
    def round_trip_ns(self) -> int | None:
        """Round trip [ns] of the pong the estimate comes from, or ``None`` without pongs."""
        return min(self._pongs)[0] if self._pongs else None

    def observe_frame(self, client_ns: int, receive_ns: int) -> None:
        """A frame stamped ``client_ns`` (page clock) arrived at ``receive_ns`` (common clock)."""
        d = receive_ns - client_ns
        if self._frame_min is None or d < self._frame_min:
            self._frame_min = d
        if not self._pongs:
            self._offset = self._frame_min

    def observe_pong(self, sent_ns: int, client_ns: int, receive_ns: int) -> None:
        """Ping sent at ``sent_ns``, answered with page time ``client_ns``, pong back at ``receive_ns``."""
        rtt = receive_ns - sent_ns
        if rtt < 0:
            return
        self._pongs.append((rtt, (sent_ns + receive_ns) // 2 - client_ns))
        self._offset = min(self._pongs)[1]

    def capture_ns(self, client_ns: int, receive_ns: int) -> int:
        """Map page time to the common clock, never later than ``receive_ns``."""
        offset = self._offset
        if offset is None:
            return receive_ns
        return min(client_ns + offset, receive_ns)


def _fuzz(data: bytes) -> object:
    msg = decode(data)
    if isinstance(msg, Pong):
        return msg
    counter = iter(range(1 << 30))
    return frame_samples(msg, "fuzz", msg.client_ns, lambda _sid: next(counter))


#: Parses one message into IR samples; only :class:`~telerig.errors.WireError` escapes.
FUZZ_TARGET: Callable[[bytes], object] = _fuzz
