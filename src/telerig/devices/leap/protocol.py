"""Leap Motion legacy WebSocket JSON protocol (``ws://127.0.0.1:6437/v6.json``), pure parsing.

The tracker service first sends ``{"serviceVersion": "2.3.1+33747", "version": 6}``, then one JSON
frame per tracking frame: ``id``, ``timestamp`` [us, service clock], ``hands`` (each ``id``,
``type`` "left"/"right", ``palmPosition`` [mm], ``palmNormal``, ``direction``, ``confidence``,
``wrist`` [mm], ...) and ``pointables`` (each ``handId``, ``type`` 0..4 thumb..pinky,
``carpPosition``, ``mcpPosition``, ``pipPosition``, ``dipPosition``, ``btipPosition`` /
``tipPosition`` [mm], ...), plus ``{"event": {...}}`` device events. Clients may send
``{"enableGestures": false}``, ``{"background": true}``, ``{"focused": true}``.

Leap frame: right-handed, origin at the device, +x to the user's right, +y up, +z toward the user,
millimetres. :class:`Mounting` maps it into the operator frame (x forward, y left, z up, metres);
:data:`DESK_MOUNT` assumes the device lies on the desk in front of the operator, facing up, its
+z toward the operator: operator = (-z, -x, +y) / 1000 + ``position_m``.

Keypoints (MediaPipe order): 0 = ``wrist`` (or the mean carpal position when absent); thumb:
1 = ``mcpPosition`` (Leap models the thumb with a zero-length metacarpal, so its MCP is the
anatomical CMC), 2 = ``pipPosition``, 3 = ``dipPosition``, 4 = ``btipPosition``; other fingers:
MCP, PIP, DIP, ``btipPosition``. Hand frame of ``wrist_orientation``: x = ``direction`` (toward the
fingers), z = -``palmNormal`` (out of the back of the hand), y = z x x, as the glove's hand frame.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from telerig.errors import ConfigError, WireError
from telerig.ir.types import HAND_KEYPOINTS, FloatArray, Handedness, HandPose, Stamp

__all__ = [
    "DESK_MOUNT",
    "FUZZ_TARGET",
    "MAX_COORD_MM",
    "LeapEvent",
    "LeapFrame",
    "LeapHand",
    "Mounting",
    "ServiceVersion",
    "hand_pose",
    "parse_message",
]

#: Largest accepted coordinate magnitude [mm] (the Leap sees about 60 cm).
MAX_COORD_MM = 2000.0
_MAX_HANDS = 8
_MAX_POINTABLES = 64
_MAX_TIMESTAMP_US = 2**62 // 1000


@dataclass(frozen=True, slots=True)
class ServiceVersion:
    """The service's first message: its version string and the protocol version it speaks."""

    service_version: str
    version: int


@dataclass(frozen=True, slots=True)
class LeapEvent:
    """A service event such as ``deviceEvent`` (``{"event": {"type": ..., "state": {...}}}``)."""

    type: str


@dataclass(frozen=True, slots=True)
class LeapHand:
    """One tracked hand in the Leap frame.

    Attributes:
        id: Hand id (stable while tracked).
        handedness: ``"left"`` or ``"right"``.
        confidence: Tracking confidence in [0, 1] (1 when the protocol version has none).
        palm_position_mm: Palm centre [mm]. Shape (3,).
        rotation: Hand frame axes (x direction, y, z = -palmNormal) as columns. Shape (3, 3).
        keypoints_mm: 21 MediaPipe-order keypoints [mm]. Shape (21, 3).
    """

    id: int
    handedness: Handedness
    confidence: float
    palm_position_mm: FloatArray
    rotation: FloatArray
    keypoints_mm: FloatArray


@dataclass(frozen=True, slots=True)
class LeapFrame:
    """One tracking frame.

    Attributes:
        id: Frame id (increasing).
        timestamp_us: Service timestamp [us].
        hands: Complete hands (all five fingers with joint positions).
        incomplete_hands: Hands left out because a finger or joint was missing.
    """

    id: int
    timestamp_us: int
    hands: tuple[LeapHand, ...]
    incomplete_hands: int = 0


def _reject_constant(name: str) -> float:
    raise WireError(f"JSON must not contain {name}; numbers must be finite")


def _json_loads(data: str | bytes) -> Any:
    return json.loads(data, parse_constant=_reject_constant)


try:  # orjson parses the ~700 numbers of a frame ~5x faster; it also rejects NaN and Infinity
    import orjson

    _loads: Callable[[str | bytes], Any] = orjson.loads
except ImportError:  # pragma: no cover - depends on the environment
    _loads = _json_loads


def _int(obj: dict[str, Any], key: str, lo: int, hi: int) -> int:
    value = obj.get(key)
    if type(value) is not int or not lo <= value <= hi:
        raise WireError(f"field {key!r} must be an integer in [{lo}, {hi}], got {value!r:.40}")
    return value


def _vec(obj: dict[str, Any], key: str, limit: float = MAX_COORD_MM) -> list[float]:
    value = obj.get(key)
    if type(value) is not list or len(value) != 3:
        raise WireError(f"field {key!r} must be a list of 3 numbers, got {value!r:.60}")
    out: list[float] = []
    for v in value:
        if type(v) is not float and type(v) is not int:
            raise WireError(f"field {key!r} must hold numbers, got {v!r:.40}")
        f = float(v)
        if not -limit <= f <= limit:
            raise WireError(f"field {key!r} coordinates must be finite within +-{limit}, got {f}")
        out.append(f)
    return out


def _unit(v: list[float], key: str) -> list[float]:
    n = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    if not 0.5 <= n <= 1.5:
        raise WireError(f"field {key!r} must be a unit vector, got norm {n:.3g}")
    return [v[0] / n, v[1] / n, v[2] / n]


def _hand(raw: Any, fingers: dict[int, list[Any]]) -> LeapHand | None:
    if type(raw) is not dict:
        raise WireError("each entry of 'hands' must be an object")
    hid = _int(raw, "id", -(2**31), 2**31 - 1)
    kind = raw.get("type")
    if kind not in ("left", "right"):
        raise WireError(f"hand field 'type' must be 'left' or 'right', got {kind!r:.40}")
    conf_raw = raw.get("confidence", 1.0)
    if type(conf_raw) not in (float, int) or not 0.0 <= conf_raw <= 1.0:
        raise WireError(f"hand field 'confidence' must be a number in [0, 1], got {conf_raw!r:.40}")
    palm = _vec(raw, "palmPosition")
    x = _unit(_vec(raw, "direction", 10.0), "direction")
    n = _unit(_vec(raw, "palmNormal", 10.0), "palmNormal")
    dot = x[0] * n[0] + x[1] * n[1] + x[2] * n[2]
    if abs(dot) > 0.5:
        raise WireError(f"hand 'direction' and 'palmNormal' must be near-orthogonal, got cos {dot:.3f}")
    # z = -normal, made orthogonal to x; y = z x x.
    z = [-n[0] + dot * x[0], -n[1] + dot * x[1], -n[2] + dot * x[2]]
    zn = math.sqrt(z[0] * z[0] + z[1] * z[1] + z[2] * z[2])
    z = [z[0] / zn, z[1] / zn, z[2] / zn]
    y = [z[1] * x[2] - z[2] * x[1], z[2] * x[0] - z[0] * x[2], z[0] * x[1] - z[1] * x[0]]
    found = fingers.get(hid)
    if found is None or any(c is None or c is _DUPLICATE for c in found):
        return None
    # Pointable vectors are checked in bulk: one array conversion and one range test.
    raw_points: list[Any] = [raw.get("wrist", _NO_WRIST)]
    for chain in found:
        raw_points.extend(chain[1:5])
    raw_points.extend(chain[0] for chain in found[1:])
    try:
        pts = np.array(raw_points, dtype=np.float64)
    except (ValueError, TypeError):
        raise WireError("joint positions must be lists of 3 numbers [mm]") from None
    if pts.shape != (25, 3):
        raise WireError("joint positions must be lists of 3 numbers [mm]")
    if not bool(np.all(np.abs(pts) <= MAX_COORD_MM)):  # False for NaN as well
        raise WireError(f"joint positions must be finite within +-{MAX_COORD_MM} mm")
    kp = pts[:21]
    if raw_points[0] is _NO_WRIST:
        kp[0] = pts[21:].mean(axis=0)
    rot = np.array([x, y, z]).T
    return LeapHand(hid, kind, float(conf_raw), np.array(palm), rot, kp)


def _pointables(raw: Any) -> dict[int, list[Any]]:
    """handId -> five (thumb..pinky) raw [carp, mcp, pip, dip, tip] joint lists (checked later)."""
    if type(raw) is not list or len(raw) > _MAX_POINTABLES:
        raise WireError(f"field 'pointables' must be a list of at most {_MAX_POINTABLES} objects")
    out: dict[int, list[Any]] = {}
    for p in raw:
        if type(p) is not dict:
            raise WireError("each entry of 'pointables' must be an object")
        if p.get("tool") is True:
            continue
        hid = _int(p, "handId", -(2**31), 2**31 - 1)
        kind = _int(p, "type", 0, 4)
        mcp = p.get("mcpPosition")
        if mcp is None:
            continue  # protocol versions before 6 carry no joint positions
        tip = p.get("btipPosition", p.get("tipPosition"))
        chain = [p.get("carpPosition", mcp), mcp, p.get("pipPosition"), p.get("dipPosition"), tip]
        slots = out.get(hid)
        if slots is None:
            slots = out[hid] = [None] * 5
        # A duplicated finger type makes the hand ambiguous: mark it incomplete.
        slots[kind] = chain if slots[kind] is None else _DUPLICATE
    return out


_NO_WRIST = [0.0, 0.0, 0.0]
_DUPLICATE: list[Any] = []  # sentinel: a finger type seen twice


def parse_message(data: str | bytes) -> ServiceVersion | LeapEvent | LeapFrame:
    """Parse one WebSocket message from the Leap service.

    Raises:
        WireError: Malformed JSON, non-finite numbers, missing or out-of-range fields.
    """
    try:
        msg = _loads(data)
    except WireError:
        raise
    except (ValueError, RecursionError) as exc:
        raise WireError(f"message must be JSON text: {str(exc)[:80]}") from None
    if type(msg) is not dict:
        raise WireError(f"message must be a JSON object, got {type(msg).__name__}")
    if "event" in msg:
        event = msg["event"]
        kind = event.get("type") if type(event) is dict else None
        if type(kind) is not str:
            raise WireError("field 'event' must be an object with a string 'type'")
        return LeapEvent(kind[:64])
    if "hands" not in msg and "version" in msg:
        version = _int(msg, "version", 1, 99)
        service = msg.get("serviceVersion", "")
        if type(service) is not str:
            raise WireError("field 'serviceVersion' must be a string")
        return ServiceVersion(service[:64], version)
    fid = _int(msg, "id", 0, 2**63 - 1)
    ts = _int(msg, "timestamp", 0, _MAX_TIMESTAMP_US)
    hands_raw = msg.get("hands")
    if type(hands_raw) is not list or len(hands_raw) > _MAX_HANDS:
        raise WireError(f"field 'hands' must be a list of at most {_MAX_HANDS} objects")
    fingers = _pointables(msg.get("pointables", [])) if hands_raw else {}
    hands: list[LeapHand] = []
    incomplete = 0
    for raw in hands_raw:
        hand = _hand(raw, fingers)
        if hand is None:
            incomplete += 1
        else:
            hands.append(hand)
    return LeapFrame(fid, ts, tuple(hands), incomplete)


def _quat_from_matrix(r: FloatArray) -> FloatArray:
    """(w, x, y, z) of a rotation matrix, w >= 0 (Shepperd's method)."""
    m00, m01, m02 = float(r[0, 0]), float(r[0, 1]), float(r[0, 2])
    m10, m11, m12 = float(r[1, 0]), float(r[1, 1]), float(r[1, 2])
    m20, m21, m22 = float(r[2, 0]), float(r[2, 1]), float(r[2, 2])
    tr = m00 + m11 + m22
    if tr > 0.0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = (0.25 * s, (m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s)
    elif m00 > m11 and m00 > m22:
        s = 2.0 * math.sqrt(1.0 + m00 - m11 - m22)
        q = ((m21 - m12) / s, 0.25 * s, (m01 + m10) / s, (m02 + m20) / s)
    elif m11 > m22:
        s = 2.0 * math.sqrt(1.0 + m11 - m00 - m22)
        q = ((m02 - m20) / s, (m01 + m10) / s, 0.25 * s, (m12 + m21) / s)
    else:
        s = 2.0 * math.sqrt(1.0 + m22 - m00 - m11)
        q = ((m10 - m01) / s, (m02 + m20) / s, (m12 + m21) / s, 0.25 * s)
    out = np.array(q)
    out /= np.linalg.norm(out)
    if out[0] < 0.0:
        out = -out
    return out


def _matrix_from_quat(q: FloatArray) -> FloatArray:
    w, x, y, z = (float(v) for v in q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


class Mounting:
    """Where the Leap device sits in the operator frame: Leap frame (mm) -> operator frame (m).

    Args:
        orientation: Unit quaternion (w, x, y, z) rotating Leap-frame vectors into the operator
            frame. Shape (4,).
        position_m: Position of the Leap origin in the operator frame [m]. Shape (3,).
    """

    def __init__(self, orientation: Sequence[float], position_m: Sequence[float]) -> None:
        q = np.array(orientation, dtype=np.float64)
        p = np.array(position_m, dtype=np.float64)
        if q.shape != (4,) or not np.all(np.isfinite(q)) or abs(float(np.linalg.norm(q)) - 1.0) > 1e-3:
            raise ConfigError(
                f"mount orientation must be a unit quaternion (w, x, y, z), got {orientation!r}"
            )
        if p.shape != (3,) or not np.all(np.isfinite(p)) or float(np.abs(p).max()) > 100.0:
            raise ConfigError(
                f"mount position must be 3 finite coordinates [m] within 100 m, got {position_m!r}"
            )
        self.orientation: FloatArray = q / np.linalg.norm(q)
        self.position_m: FloatArray = p
        self.rotation: FloatArray = _matrix_from_quat(self.orientation)
        self._scaled_t = (self.rotation * 1e-3).T  # row vectors (mm) @ this -> metres
        for arr in (self.orientation, self.position_m, self.rotation, self._scaled_t):
            arr.flags.writeable = False

    def points(self, points_mm: FloatArray) -> FloatArray:
        """Leap-frame points [mm] -> operator-frame points [m]. Shape (n, 3) -> (n, 3)."""
        out: FloatArray = points_mm @ self._scaled_t + self.position_m
        return out

    def __repr__(self) -> str:
        return f"Mounting(orientation={self.orientation.tolist()}, position_m={self.position_m.tolist()})"


#: Device on the desk in front of the operator (desk top 0.75 m high, 0.40 m ahead), +z toward them.
DESK_MOUNT = Mounting((0.5, 0.5, -0.5, -0.5), (0.40, 0.0, 0.75))


def hand_pose(
    hand: LeapHand, stamp: Stamp, mounting: Mounting = DESK_MOUNT, frame_id: str = "operator"
) -> HandPose:
    """Normalize one Leap hand into a :class:`HandPose` in the operator frame (metres).

    Wrist position = keypoint 0; wrist orientation = the hand frame (x toward the fingers, z out
    of the back of the hand) rotated by the mounting; keypoint confidence = hand confidence.
    """
    kp = mounting.points(hand.keypoints_mm)
    rot = mounting.rotation @ hand.rotation
    return HandPose(
        stamp=stamp,
        handedness=hand.handedness,
        wrist_position=kp[0],
        wrist_orientation=_quat_from_matrix(rot),
        keypoints=kp,
        keypoint_confidence=np.full(HAND_KEYPOINTS, hand.confidence),
        frame_id=frame_id,
    )


def _fuzz(data: bytes) -> object:
    msg = parse_message(data)
    if isinstance(msg, LeapFrame):
        return [hand_pose(h, Stamp("fuzz", 0, 0, 0)) for h in msg.hands]
    return msg


#: Parses one message and normalizes its hands (desk mount); raises only WireError.
FUZZ_TARGET: Callable[[bytes], object] = _fuzz
