"""Rosbridge v2 protocol subset (JSON over WebSocket) and the ROS messages a joint-space robot needs.

Operations: ``advertise``/``unadvertise``, ``publish``, ``subscribe``/``unsubscribe`` and the
server's ``status``. Messages: ``sensor_msgs/JointState`` (state), and as command either
``trajectory_msgs/JointTrajectory`` (ros2_control ``joint_trajectory_controller``) or
``std_msgs/Float64MultiArray`` (``forward_position_controller``). Type names use the short
``pkg/Type`` form, which rosbridge accepts on ROS 1 and ROS 2; ``pkg/msg/Type`` is read too.
Header stamps are written ROS 2 style (``sec``/``nanosec``); ROS 1 ``secs``/``nsecs`` are read too.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from telerig.errors import WireError
from telerig.ir.types import FloatArray

__all__ = [
    "BOOL",
    "FLOAT64_MULTI_ARRAY",
    "JOINT_STATE",
    "JOINT_TRAJECTORY",
    "CommandType",
    "JointStateMsg",
    "advertise",
    "canonical_type",
    "command_msg",
    "decode",
    "encode",
    "float64_multi_array",
    "joint_state",
    "joint_trajectory",
    "parse_command",
    "parse_joint_state",
    "publish",
    "status",
    "subscribe",
    "unadvertise",
    "unsubscribe",
]

JOINT_STATE = "sensor_msgs/JointState"
JOINT_TRAJECTORY = "trajectory_msgs/JointTrajectory"
FLOAT64_MULTI_ARRAY = "std_msgs/Float64MultiArray"
BOOL = "std_msgs/Bool"

#: Command message types a driver can publish.
CommandType = Literal["trajectory_msgs/JointTrajectory", "std_msgs/Float64MultiArray"]

Op = dict[str, Any]


def canonical_type(name: str) -> str:
    """``pkg/msg/Type`` -> ``pkg/Type`` (ROS 2 spelling to the form used here)."""
    parts = name.split("/")
    if len(parts) == 3 and parts[1] == "msg":
        return f"{parts[0]}/{parts[2]}"
    return name


# -- operations ----------------------------------------------------------------------------------


def advertise(topic: str, type: str, id: str) -> Op:
    """``advertise``: announce that this client publishes ``type`` on ``topic``."""
    return {"op": "advertise", "id": id, "topic": topic, "type": type}


def unadvertise(topic: str, id: str) -> Op:
    """``unadvertise``: stop publishing on ``topic``."""
    return {"op": "unadvertise", "id": id, "topic": topic}


def publish(topic: str, msg: Mapping[str, Any]) -> Op:
    """``publish``: one message on an advertised topic."""
    return {"op": "publish", "topic": topic, "msg": dict(msg)}


def subscribe(topic: str, type: str, id: str, *, throttle_rate_ms: int = 0, queue_length: int = 1) -> Op:
    """``subscribe``: ask for ``topic``; ``queue_length`` 1 keeps only the newest message when slow."""
    return {
        "op": "subscribe",
        "id": id,
        "topic": topic,
        "type": type,
        "throttle_rate": throttle_rate_ms,
        "queue_length": queue_length,
    }


def unsubscribe(topic: str, id: str) -> Op:
    """``unsubscribe``: cancel the subscription ``id`` to ``topic``."""
    return {"op": "unsubscribe", "id": id, "topic": topic}


def status(level: Literal["info", "warning", "error"], msg: str, id: str | None = None) -> Op:
    """``status``: what the server reports about a request (``id`` of that request when known)."""
    out: Op = {"op": "status", "level": level, "msg": msg}
    if id is not None:
        out["id"] = id
    return out


def encode(op: Mapping[str, Any]) -> str:
    """JSON text of one operation (NaN and infinity are refused: JSON has none).

    Raises:
        WireError: a value is not JSON-serialisable or not finite.
    """
    try:
        return json.dumps(op, allow_nan=False, separators=(",", ":"))
    except (TypeError, ValueError) as exc:
        raise WireError(f"cannot encode rosbridge message: {exc}") from None


def decode(text: str | bytes) -> Op:
    """Parse one operation: a JSON object with a string ``op``.

    Raises:
        WireError: not JSON, not an object, or no ``op``.
    """
    try:
        obj = json.loads(text)
    except (ValueError, UnicodeDecodeError) as exc:
        raise WireError(f"rosbridge message is not JSON: {exc}") from None
    if not isinstance(obj, dict):
        raise WireError(f"rosbridge message must be a JSON object, got {type(obj).__name__}")
    if not isinstance(obj.get("op"), str):
        raise WireError("rosbridge message has no string 'op'")
    return obj


# -- messages ------------------------------------------------------------------------------------


def _header(stamp_ns: int, frame_id: str = "") -> dict[str, Any]:
    return {
        "stamp": {"sec": stamp_ns // 1_000_000_000, "nanosec": stamp_ns % 1_000_000_000},
        "frame_id": frame_id,
    }


def _duration(seconds: float) -> dict[str, int]:
    ns = round(seconds * 1e9)
    return {"sec": ns // 1_000_000_000, "nanosec": ns % 1_000_000_000}


def _floats(values: Sequence[float] | FloatArray) -> list[float]:
    return [float(v) for v in values]


def joint_state(
    names: Sequence[str],
    positions: Sequence[float] | FloatArray,
    velocities: Sequence[float] | FloatArray = (),
    efforts: Sequence[float] | FloatArray = (),
    *,
    stamp_ns: int = 0,
) -> dict[str, Any]:
    """A ``sensor_msgs/JointState`` [rad], [rad/s], [N m]; ``stamp_ns`` in the publisher's clock."""
    return {
        "header": _header(stamp_ns),
        "name": list(names),
        "position": _floats(positions),
        "velocity": _floats(velocities),
        "effort": _floats(efforts),
    }


def joint_trajectory(
    names: Sequence[str], positions: Sequence[float] | FloatArray, time_from_start_s: float
) -> dict[str, Any]:
    """A one-point ``trajectory_msgs/JointTrajectory`` to ``positions`` [rad] after ``time_from_start_s`` [s].

    The header stamp is zero, which the controller reads as "start now".
    """
    return {
        "header": _header(0),
        "joint_names": list(names),
        "points": [
            {
                "positions": _floats(positions),
                "velocities": [],
                "accelerations": [],
                "effort": [],
                "time_from_start": _duration(time_from_start_s),
            }
        ],
    }


def float64_multi_array(values: Sequence[float] | FloatArray) -> dict[str, Any]:
    """A ``std_msgs/Float64MultiArray`` (what ``forward_position_controller`` takes, in its joint order)."""
    return {"layout": {"dim": [], "data_offset": 0}, "data": _floats(values)}


def command_msg(
    type: CommandType, names: Sequence[str], positions: Sequence[float] | FloatArray, time_from_start_s: float
) -> dict[str, Any]:
    """The command message of ``type`` for joint ``positions`` [rad] in ``names`` order."""
    if canonical_type(type) == JOINT_TRAJECTORY:
        return joint_trajectory(names, positions, time_from_start_s)
    if canonical_type(type) == FLOAT64_MULTI_ARRAY:
        return float64_multi_array(positions)
    raise WireError(f"unsupported command type {type!r}; use {JOINT_TRAJECTORY} or {FLOAT64_MULTI_ARRAY}")


@dataclass(frozen=True, slots=True)
class JointStateMsg:
    """A decoded ``sensor_msgs/JointState``.

    Attributes:
        names: Joint names. Length n.
        positions: [rad] or [m]. Shape (n,).
        velocities: [rad/s]; empty when not published, NaN for a joint that does not measure it
            (JSON null). Shape (n,) or (0,).
        efforts: [N m]; empty when not published, NaN for a joint that does not measure it (JSON
            null). Shape (n,) or (0,).
        stamp_ns: Header stamp in the publisher's clock [ns]; 0 when unset.
    """

    names: tuple[str, ...]
    positions: FloatArray
    velocities: FloatArray
    efforts: FloatArray
    stamp_ns: int


def _array(msg: Mapping[str, Any], key: str, names: Sequence[str], *, optional: bool) -> FloatArray:
    """``msg[key]`` as floats. rosbridge writes NaN as JSON null: in an optional field (velocity,
    effort, which ROS 2's joint_state_broadcaster fills with NaN for a joint without that interface)
    null reads as NaN; in a required one it is refused, naming the joint."""
    n = len(names)
    raw = msg.get(key, [])
    if raw is None:
        raw = []
    if not isinstance(raw, list):
        raise WireError(f"JointState.{key} must be a list of numbers, got {type(raw).__name__}")
    values: list[float] = []
    for i, v in enumerate(raw):
        if v is None and optional:
            values.append(math.nan)
        elif isinstance(v, int | float) and not isinstance(v, bool):
            values.append(v)
        else:
            joint = f" ({names[i]!r})" if i < n else ""
            what = "null" if v is None else f"not a number ({v!r:.40})"
            raise WireError(f"JointState.{key}[{i}]{joint} is {what}")
    arr = np.array(values, dtype=np.float64)
    if arr.size not in ((0, n) if optional else (n,)):
        raise WireError(f"JointState.{key} has {arr.size} values for {n} names")
    if not optional and not np.all(np.isfinite(arr)):
        raise WireError(f"JointState.{key} has non-finite values")
    if optional and np.any(np.isinf(arr)):
        raise WireError(f"JointState.{key} has infinite values")
    return arr


def _stamp_ns(header: Any) -> int:
    if not isinstance(header, dict):
        return 0
    stamp = header.get("stamp")
    if not isinstance(stamp, dict):
        return 0
    sec = stamp.get("sec", stamp.get("secs", 0))
    nsec = stamp.get("nanosec", stamp.get("nsecs", 0))
    if not (isinstance(sec, int) and isinstance(nsec, int)) or sec < 0 or not 0 <= nsec < 1_000_000_000:
        raise WireError(f"JointState.header.stamp is invalid: {stamp!r}")
    return sec * 1_000_000_000 + nsec


def parse_joint_state(msg: Any) -> JointStateMsg:
    """Decode a ``sensor_msgs/JointState`` message body.

    Raises:
        WireError: missing or mistyped fields, array lengths that do not match ``name``, a null
            or non-finite position, an infinite velocity or effort, or an invalid stamp.
    """
    if not isinstance(msg, dict):
        raise WireError("JointState must be a JSON object")
    names = msg.get("name")
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise WireError("JointState.name must be a list of strings")
    return JointStateMsg(
        names=tuple(names),
        positions=_array(msg, "position", names, optional=False),
        velocities=_array(msg, "velocity", names, optional=True),
        efforts=_array(msg, "effort", names, optional=True),
        stamp_ns=_stamp_ns(msg.get("header")),
    )


def parse_command(type: str, msg: Any, names: Sequence[str]) -> FloatArray:
    """Target positions [rad] in ``names`` order from a command message of ``type`` (what a controller reads).

    A ``JointTrajectory`` gives its last point and must name every joint in ``names``; a
    ``Float64MultiArray`` must hold one value per joint.

    Raises:
        WireError: the message does not fit ``type`` or ``names``.
    """
    if not isinstance(msg, dict):
        raise WireError(f"{type} must be a JSON object")
    kind = canonical_type(type)
    if kind == FLOAT64_MULTI_ARRAY:
        data = msg.get("data")
        if not isinstance(data, list) or len(data) != len(names):
            raise WireError(f"Float64MultiArray.data must hold {len(names)} numbers")
        values = data
    elif kind == JOINT_TRAJECTORY:
        joints, points = msg.get("joint_names"), msg.get("points")
        if not isinstance(joints, list) or not isinstance(points, list) or not points:
            raise WireError("JointTrajectory needs joint_names and at least one point")
        last = points[-1]
        pos = last.get("positions") if isinstance(last, dict) else None
        if not isinstance(pos, list) or len(pos) != len(joints):
            raise WireError("JointTrajectory point positions must match joint_names")
        by_name = dict(zip(joints, pos, strict=True))
        missing = [j for j in names if j not in by_name]
        if missing:
            raise WireError(f"JointTrajectory lacks joints {missing}")
        values = [by_name[j] for j in names]
    else:
        raise WireError(f"unsupported command type {type!r}")
    try:
        arr = np.array(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise WireError(f"{type} values are not numbers") from None
    if not np.all(np.isfinite(arr)) or not all(isinstance(v, int | float) for v in values):
        raise WireError(f"{type} values must be finite numbers")
    return arr
