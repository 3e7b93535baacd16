"""The dataset schema: joint order, limits, parts and cameras that every export writes and references.

Seed 004: a joint-order mismatch between datasets is the most common silent error. Every export
therefore writes one JSON file (:data:`SCHEMA_FILE`) naming each entry of the state and action
vectors (the robot's joint names, in the robot model's order), its limits and the robot part it
belongs to; an append to an existing dataset is refused unless its schema is the same.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import numpy.typing as npt
from pydantic import JsonValue

from telerig.errors import ExportError

__all__ = ["SCHEMA_FILE", "SCHEMA_VERSION", "CameraSpec", "DatasetSchema", "JointSpec", "Vector"]

#: File name of the schema JSON inside every export.
SCHEMA_FILE = "robot_schema.json"
#: Layout version of :meth:`DatasetSchema.to_json`.
SCHEMA_VERSION = 1

#: Which vector of a frame: the measured robot state or the commanded action.
Vector = Literal["state", "action"]

Float32Array = npt.NDArray[np.float32]


@dataclass(frozen=True, slots=True)
class JointSpec:
    """One entry of a state or action vector.

    Attributes:
        name: Entry name: the joint name (``shoulder_pan_joint``), ``gripper`` for a gripper's
            normalized opening, ``base_vx`` / ``base_vy`` / ``base_wz`` for a mobile base's velocity;
            prefixed ``<robot>.`` in rigs with several robots.
        robot: Robot id in the rig (``arm0``).
        part: Robot part: ``joints`` (the driver's commanded joints), ``gripper`` or ``base``.
        lower: Lower limit [rad], [m], [0..1] opening or [m/s]; ``-inf`` when unknown.
        upper: Upper limit, same unit; ``inf`` when unknown.
        velocity: Speed limit [rad/s] or [m/s]; ``inf`` when unknown.
    """

    name: str
    robot: str
    part: str
    lower: float = -math.inf
    upper: float = math.inf
    velocity: float = math.inf

    def to_json(self) -> dict[str, JsonValue]:
        return {
            "name": self.name,
            "robot": self.robot,
            "part": self.part,
            "lower": _finite_or_none(self.lower),
            "upper": _finite_or_none(self.upper),
            "velocity": _finite_or_none(self.velocity),
        }

    @classmethod
    def from_json(cls, data: dict[str, JsonValue]) -> JointSpec:
        return cls(
            name=str(data["name"]),
            robot=str(data["robot"]),
            part=str(data["part"]),
            lower=_float(data.get("lower"), -math.inf),
            upper=_float(data.get("upper"), math.inf),
            velocity=_float(data.get("velocity"), math.inf),
        )


@dataclass(frozen=True, slots=True)
class CameraSpec:
    """One camera of the dataset: frames are RGB ``uint8`` of shape (height, width, channels).

    Attributes:
        key: Camera id in the rig (``scene``), the dataset's video key.
        height: Frame height [px].
        width: Frame width [px].
        fps: The camera's configured rate [Hz].
        codec: Codec of the recorded video (``h264``).
        channels: Colour channels, always 3 (RGB).
    """

    key: str
    height: int
    width: int
    fps: int
    codec: str
    channels: int = 3

    @property
    def shape(self) -> tuple[int, int, int]:
        """(height, width, channels)."""
        return (self.height, self.width, self.channels)

    def to_json(self) -> dict[str, JsonValue]:
        return {
            "key": self.key,
            "height": self.height,
            "width": self.width,
            "channels": self.channels,
            "fps": self.fps,
            "codec": self.codec,
        }

    @classmethod
    def from_json(cls, data: dict[str, JsonValue]) -> CameraSpec:
        return cls(
            key=str(data["key"]),
            height=_int(data["height"]),
            width=_int(data["width"]),
            fps=_int(data["fps"]),
            codec=str(data["codec"]),
            channels=_int(data.get("channels", 3)),
        )


@dataclass(frozen=True, slots=True)
class DatasetSchema:
    """What every frame of a dataset holds, in order; identical for every episode of a dataset.

    Attributes:
        rig: Rig name.
        fingerprint: Rig fingerprint digest: episodes of another rig never mix into the dataset.
        fps: Dataset frame rate [Hz].
        robots: Robot id → robot model name (the driver type when it has no model).
        state: Entries of ``observation.state``, in order.
        action: Entries of ``action``, in order.
        cameras: Cameras, sorted by key.
        normalized: Whether state and action values are mapped to [-1, 1] from the limits (entries
            without finite limits are left as they are).
    """

    rig: str
    fingerprint: str
    fps: int
    robots: dict[str, str]
    state: tuple[JointSpec, ...]
    action: tuple[JointSpec, ...]
    cameras: tuple[CameraSpec, ...] = ()
    normalized: bool = False
    _bounds: dict[str, tuple[Float32Array, Float32Array, npt.NDArray[np.bool_]]] = field(
        default_factory=dict, init=False, repr=False, compare=False
    )

    def __post_init__(self) -> None:
        if self.fps <= 0:
            raise ExportError(f"dataset fps must be > 0 Hz, got {self.fps}; pass --fps")
        for which, specs in (("state", self.state), ("action", self.action)):
            names = [s.name for s in specs]
            dup = sorted({n for n in names if names.count(n) > 1})
            if dup:
                raise ExportError(
                    f"{which} entry names repeat ({', '.join(dup)}); a robot lists a joint twice"
                )
            lower = np.array([s.lower for s in specs], dtype=np.float32)
            upper = np.array([s.upper for s in specs], dtype=np.float32)
            bounded = np.isfinite(lower) & np.isfinite(upper) & (upper > lower)
            self._bounds[which] = (lower, upper, bounded)

    def names(self, which: Vector) -> tuple[str, ...]:
        """Entry names of the state or action vector, in order."""
        return tuple(s.name for s in self._specs(which))

    @property
    def state_names(self) -> tuple[str, ...]:
        return self.names("state")

    @property
    def action_names(self) -> tuple[str, ...]:
        return self.names("action")

    def parts(self, which: Vector) -> dict[str, tuple[int, int]]:
        """Named parts of a vector: ``<robot>.<part>`` → [start, stop) indices, in vector order."""
        out: dict[str, tuple[int, int]] = {}
        for i, spec in enumerate(self._specs(which)):
            key = f"{spec.robot}.{spec.part}"
            start, _ = out.get(key, (i, i))
            out[key] = (start, i + 1)
        return out

    def camera(self, key: str) -> CameraSpec:
        for cam in self.cameras:
            if cam.key == key:
                return cam
        available = ", ".join(c.key for c in self.cameras) or "none"
        raise ExportError(f"camera {key!r} is not in the dataset. Available: {available}")

    def normalize(self, values: npt.ArrayLike, which: Vector) -> Float32Array:
        """Map values to [-1, 1] from the limits (entries without finite limits unchanged).

        Args:
            values: Shape (..., n) with n the vector's length.
        """
        lower, upper, bounded = self._bounds[which]
        arr = np.array(values, dtype=np.float32)
        scaled = 2.0 * (arr - lower) / np.where(bounded, upper - lower, 1.0) - 1.0
        return np.where(bounded, scaled, arr).astype(np.float32)

    def denormalize(self, values: npt.ArrayLike, which: Vector) -> Float32Array:
        """Inverse of :meth:`normalize`. Shape (..., n)."""
        lower, upper, bounded = self._bounds[which]
        arr = np.array(values, dtype=np.float32)
        restored = (arr + 1.0) * 0.5 * np.where(bounded, upper - lower, 1.0) + lower
        return np.where(bounded, restored, arr).astype(np.float32)

    def check_compatible(self, other: DatasetSchema) -> None:
        """Refuse to mix datasets: raise naming the first difference and the fix.

        Raises:
            ExportError: One line: what differs, and to export into another directory.
        """
        mine, theirs = self.to_json(), other.to_json()
        for key in ("fingerprint", "rig", "fps", "robots", "state", "action", "cameras", "normalized"):
            if mine[key] != theirs[key]:
                raise ExportError(
                    f"the dataset's {key} is {_short(mine[key])}, the episodes' is {_short(theirs[key])}: "
                    "episodes of a different rig or export setting never mix into one dataset; "
                    "export them into another --out directory"
                )

    def to_json(self) -> dict[str, JsonValue]:
        """The JSON written as :data:`SCHEMA_FILE` (limits ``null`` where unknown)."""
        return {
            "version": SCHEMA_VERSION,
            "rig": self.rig,
            "fingerprint": self.fingerprint,
            "fps": self.fps,
            "robots": dict(self.robots),
            "state": [s.to_json() for s in self.state],
            "action": [s.to_json() for s in self.action],
            "cameras": [c.to_json() for c in self.cameras],
            "normalized": self.normalized,
        }

    def dumps(self) -> str:
        """:meth:`to_json` as indented text."""
        return json.dumps(self.to_json(), indent=2) + "\n"

    @classmethod
    def from_json(cls, data: JsonValue) -> DatasetSchema:
        """Parse :meth:`to_json` output.

        Raises:
            ExportError: The data is not a schema of a version this telerig reads.
        """
        try:
            if not isinstance(data, dict):
                raise TypeError("not a JSON object")
            if data.get("version") != SCHEMA_VERSION:
                raise ValueError(f"version {data.get('version')!r}, this telerig reads {SCHEMA_VERSION}")
            robots = data["robots"]
            if not isinstance(robots, dict):
                raise TypeError("robots is not an object")
            return cls(
                rig=str(data["rig"]),
                fingerprint=str(data["fingerprint"]),
                fps=_int(data["fps"]),
                robots={str(k): str(v) for k, v in robots.items()},
                state=tuple(JointSpec.from_json(_obj(s)) for s in _list(data["state"])),
                action=tuple(JointSpec.from_json(_obj(s)) for s in _list(data["action"])),
                cameras=tuple(CameraSpec.from_json(_obj(c)) for c in _list(data.get("cameras", []))),
                normalized=bool(data.get("normalized", False)),
            )
        except ExportError:
            raise
        except (KeyError, TypeError, ValueError) as exc:
            raise ExportError(f"{SCHEMA_FILE}: {exc}; was it written by telerig export?") from None

    @classmethod
    def loads(cls, text: str | bytes) -> DatasetSchema:
        """Parse :meth:`dumps` output (one-line :class:`ExportError` on bad JSON)."""
        try:
            data = json.loads(text)
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise ExportError(
                f"{SCHEMA_FILE} is not JSON ({exc}); was it written by telerig export?"
            ) from None
        return cls.from_json(data)

    def _specs(self, which: Vector) -> tuple[JointSpec, ...]:
        if which == "state":
            return self.state
        if which == "action":
            return self.action
        raise ValueError(f"vector must be 'state' or 'action', got {which!r}")


def _finite_or_none(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def _float(value: JsonValue, default: float) -> float:
    if value is None:
        return default
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise TypeError(f"expected a number, got {value!r}")
    return float(value)


def _int(value: JsonValue) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise TypeError(f"expected an integer, got {value!r}")
    return value


def _obj(value: JsonValue) -> dict[str, JsonValue]:
    if not isinstance(value, dict):
        raise TypeError(f"expected an object, got {type(value).__name__}")
    return value


def _list(value: JsonValue) -> list[JsonValue]:
    if not isinstance(value, list):
        raise TypeError(f"expected a list, got {type(value).__name__}")
    return value


def _short(value: JsonValue) -> str:
    text = json.dumps(value)
    return text if len(text) <= 80 else text[:77] + "..."
