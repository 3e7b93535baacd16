"""Intermediate representation: the typed samples devices emit and robots consume.

Every sample is a frozen, slotted dataclass carrying a :class:`Stamp`. Arrays are
float64 NumPy arrays marked read-only on construction, so a sample can be shared
between threads without copies. Units are SI (metres, radians, seconds, newtons);
quaternions are ``(w, x, y, z)``, unit norm, Hamilton convention; every spatial
quantity names the frame it is expressed in.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import numpy.typing as npt

__all__ = [
    "HAND_KEYPOINTS",
    "BaseVelocity",
    "BodySkeleton",
    "CameraFrame",
    "ControlKind",
    "ControlMode",
    "ControlSource",
    "ControllerState",
    "FloatArray",
    "GripperCommand",
    "HandPose",
    "Handedness",
    "JointCommand",
    "JointState",
    "MAX_ERROR_M",
    "Pose",
    "RetargetResidual",
    "Sample",
    "Stamp",
    "Twist",
    "Wrench",
    "now_ns",
]

FloatArray = npt.NDArray[np.float64]
Handedness = Literal["left", "right"]
#: Who drives a robot with a handover in one tick: a ``policy`` or an ``operator`` source, that source
#: while its device is ``paused`` (the robot holds), ``home`` (driving to its home configuration),
#: or ``none`` (no source engaged).
ControlKind = Literal["policy", "operator", "paused", "home", "none"]
#: A handover's mode: ``auto`` (priority and engagement decide), or the kind that is made to drive.
ControlMode = Literal["auto", "operator", "policy"]
#: A residual distance beyond this is corrupt, not a miss [m] (:meth:`RetargetResidual.worst_error_m`).
MAX_ERROR_M = 1e9
_CONTROL_KINDS = frozenset(("policy", "operator", "paused", "home", "none"))
_CONTROL_MODES = frozenset(("auto", "operator", "policy"))

#: Number of hand keypoints in :class:`HandPose` (MediaPipe / OpenXR-style 21-point hand).
HAND_KEYPOINTS = 21


def now_ns() -> int:
    """Current time in the rig's common clock, integer nanoseconds since the Unix epoch.

    Stations on other hosts correct their readings with the offset estimated by
    clock sync, so this is the one clock capture and arrival times are in.
    """
    return time.time_ns()


def _array(value: object, shape: tuple[int, ...], name: str) -> FloatArray:
    arr = np.array(value, dtype=np.float64)
    if arr.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {arr.shape}")
    arr.flags.writeable = False
    return arr


def _vector(value: object, name: str) -> FloatArray:
    arr = np.array(value, dtype=np.float64)
    if arr.ndim != 1:
        raise ValueError(f"{name} must be one-dimensional, got shape {arr.shape}")
    arr.flags.writeable = False
    return arr


@dataclass(frozen=True, slots=True)
class Stamp:
    """When and where a sample came from.

    Attributes:
        source_id: Id of the device or node that produced the sample, e.g. ``"vr0/right"``.
        seq: Per-source sequence number, increasing by one per sample.
        device_ns: Timestamp in the device's own clock [ns] (raw, not comparable across devices).
        capture_ns: Capture time in the rig's common clock [ns]; what alignment uses.
        arrival_ns: Time the sample reached telerig in the common clock [ns]; 0 until it arrives.
        confidence: Producer's confidence in the sample, in [0, 1].
    """

    source_id: str
    seq: int
    device_ns: int
    capture_ns: int
    arrival_ns: int = 0
    confidence: float = 1.0

    def arrived(self, arrival_ns: int | None = None) -> Stamp:
        """Return a copy with ``arrival_ns`` set (now, if not given)."""
        return dataclasses.replace(self, arrival_ns=now_ns() if arrival_ns is None else arrival_ns)

    @classmethod
    def now(cls, source_id: str, seq: int, *, confidence: float = 1.0) -> Stamp:
        """Stamp a sample captured now by a source whose device clock is the common clock."""
        t = now_ns()
        return cls(source_id=source_id, seq=seq, device_ns=t, capture_ns=t, confidence=confidence)


@dataclass(frozen=True, slots=True)
class Pose:
    """A rigid-body pose sample.

    Attributes:
        position: Translation [m]. Shape (3,).
        orientation: Unit quaternion (w, x, y, z). Shape (4,).
        frame_id: Frame the pose is expressed in, e.g. ``"operator"`` or ``"ur5e/base"``.
    """

    stamp: Stamp
    position: FloatArray
    orientation: FloatArray
    frame_id: str

    def __post_init__(self) -> None:
        object.__setattr__(self, "position", _array(self.position, (3,), "position"))
        object.__setattr__(self, "orientation", _array(self.orientation, (4,), "orientation"))


@dataclass(frozen=True, slots=True)
class HandPose:
    """A tracked hand: wrist pose plus 21 keypoints.

    Attributes:
        handedness: ``"left"`` or ``"right"``.
        wrist_position: Wrist translation [m] in ``frame_id``. Shape (3,).
        wrist_orientation: Wrist orientation (w, x, y, z) in ``frame_id``. Shape (4,).
        keypoints: Keypoint positions [m] in ``frame_id``, MediaPipe order
            (0 wrist, 1-4 thumb, 5-8 index, 9-12 middle, 13-16 ring, 17-20 little). Shape (21, 3).
        keypoint_confidence: Per-keypoint confidence in [0, 1]. Shape (21,).
    """

    stamp: Stamp
    handedness: Handedness
    wrist_position: FloatArray
    wrist_orientation: FloatArray
    keypoints: FloatArray
    keypoint_confidence: FloatArray
    frame_id: str

    def __post_init__(self) -> None:
        object.__setattr__(self, "wrist_position", _array(self.wrist_position, (3,), "wrist_position"))
        object.__setattr__(
            self, "wrist_orientation", _array(self.wrist_orientation, (4,), "wrist_orientation")
        )
        object.__setattr__(self, "keypoints", _array(self.keypoints, (HAND_KEYPOINTS, 3), "keypoints"))
        object.__setattr__(
            self,
            "keypoint_confidence",
            _array(self.keypoint_confidence, (HAND_KEYPOINTS,), "keypoint_confidence"),
        )


@dataclass(frozen=True, slots=True)
class BodySkeleton:
    """A tracked body as named joints.

    Attributes:
        joint_names: Joint names, e.g. ``("pelvis", "spine", ...)``. Length N.
        positions: Joint positions [m] in ``frame_id``. Shape (N, 3).
        orientations: Joint orientations (w, x, y, z) in ``frame_id``. Shape (N, 4).
    """

    stamp: Stamp
    joint_names: tuple[str, ...]
    positions: FloatArray
    orientations: FloatArray
    frame_id: str

    def __post_init__(self) -> None:
        n = len(self.joint_names)
        object.__setattr__(self, "joint_names", tuple(self.joint_names))
        object.__setattr__(self, "positions", _array(self.positions, (n, 3), "positions"))
        object.__setattr__(self, "orientations", _array(self.orientations, (n, 4), "orientations"))


@dataclass(frozen=True, slots=True)
class ControllerState:
    """A handheld controller: its pose plus buttons and analog inputs.

    Attributes:
        hand: Which hand holds it.
        position: Controller grip position [m] in ``frame_id``. Shape (3,).
        orientation: Controller orientation (w, x, y, z) in ``frame_id``. Shape (4,).
        buttons: Names of the buttons held down in this sample, e.g. ``{"a", "b"}``.
        trigger: Index trigger in [0, 1] (1 = fully pressed).
        grip: Grip/squeeze in [0, 1].
        joystick: Thumbstick (x right, y forward) in [-1, 1]. Shape (2,).
    """

    stamp: Stamp
    hand: Handedness
    position: FloatArray
    orientation: FloatArray
    frame_id: str
    buttons: frozenset[str] = frozenset()
    trigger: float = 0.0
    grip: float = 0.0
    joystick: FloatArray = field(default_factory=lambda: np.zeros(2))

    def __post_init__(self) -> None:
        object.__setattr__(self, "position", _array(self.position, (3,), "position"))
        object.__setattr__(self, "orientation", _array(self.orientation, (4,), "orientation"))
        object.__setattr__(self, "joystick", _array(self.joystick, (2,), "joystick"))
        object.__setattr__(self, "buttons", frozenset(self.buttons))

    @property
    def pose(self) -> Pose:
        """The controller pose as a :class:`Pose` sample with the same stamp."""
        return Pose(self.stamp, self.position, self.orientation, self.frame_id)


@dataclass(frozen=True, slots=True)
class Twist:
    """A spatial velocity.

    Attributes:
        linear: Linear velocity [m/s] in ``frame_id``. Shape (3,).
        angular: Angular velocity [rad/s] in ``frame_id``. Shape (3,).
    """

    stamp: Stamp
    linear: FloatArray
    angular: FloatArray
    frame_id: str

    def __post_init__(self) -> None:
        object.__setattr__(self, "linear", _array(self.linear, (3,), "linear"))
        object.__setattr__(self, "angular", _array(self.angular, (3,), "angular"))


@dataclass(frozen=True, slots=True)
class JointCommand:
    """Joint position targets for a robot part.

    Attributes:
        names: Joint names, in the order of the arrays. Length n.
        positions: Target joint positions [rad] or [m] for prismatic joints. Shape (n,).
        velocities: Optional feed-forward joint velocities [rad/s]; empty when absent. Shape (n,) or (0,).
    """

    stamp: Stamp
    names: tuple[str, ...]
    positions: FloatArray
    velocities: FloatArray = field(default_factory=lambda: np.zeros(0))

    def __post_init__(self) -> None:
        object.__setattr__(self, "names", tuple(self.names))
        object.__setattr__(self, "positions", _array(self.positions, (len(self.names),), "positions"))
        vel = _vector(self.velocities, "velocities")
        if vel.size not in (0, len(self.names)):
            raise ValueError(f"velocities must have shape ({len(self.names)},) or (0,), got {vel.shape}")
        object.__setattr__(self, "velocities", vel)


@dataclass(frozen=True, slots=True)
class GripperCommand:
    """Parallel gripper or hand open/close command.

    Attributes:
        opening: Normalized opening in [0, 1]: 0 fully closed, 1 fully open.
        max_force: Grip force limit [N]; 0 means the gripper's default.
    """

    stamp: Stamp
    opening: float
    max_force: float = 0.0


@dataclass(frozen=True, slots=True)
class BaseVelocity:
    """Planar velocity command for a mobile base, in the base frame.

    Attributes:
        vx: Forward velocity [m/s].
        vy: Leftward velocity [m/s] (0 for differential drive).
        wz: Yaw rate [rad/s], counter-clockwise positive.
    """

    stamp: Stamp
    vx: float
    vy: float
    wz: float


@dataclass(frozen=True, slots=True)
class JointState:
    """Measured robot joint state.

    Attributes:
        names: Joint names. Length n.
        positions: Joint positions [rad] or [m]. Shape (n,).
        velocities: Joint velocities [rad/s] or [m/s]. Shape (n,).
        efforts: Joint torques [N m] or forces [N]; empty when the robot does not report them.
    """

    stamp: Stamp
    names: tuple[str, ...]
    positions: FloatArray
    velocities: FloatArray
    efforts: FloatArray = field(default_factory=lambda: np.zeros(0))

    def __post_init__(self) -> None:
        n = len(self.names)
        object.__setattr__(self, "names", tuple(self.names))
        object.__setattr__(self, "positions", _array(self.positions, (n,), "positions"))
        object.__setattr__(self, "velocities", _array(self.velocities, (n,), "velocities"))
        eff = _vector(self.efforts, "efforts")
        if eff.size not in (0, n):
            raise ValueError(f"efforts must have shape ({n},) or (0,), got {eff.shape}")
        object.__setattr__(self, "efforts", eff)


@dataclass(frozen=True, slots=True)
class Wrench:
    """A measured force and torque: a wrist force/torque sensor, or a contact force.

    Attributes:
        force: Force [N] acting on the robot, in ``frame_id``. Shape (3,).
        torque: Torque [N m] about the origin of ``frame_id``, in ``frame_id``. Shape (3,).
        frame_id: Frame of the measurement, e.g. ``"arm0/ft_sensor"`` (a wrist sensor's frame).
    """

    stamp: Stamp
    force: FloatArray
    torque: FloatArray
    frame_id: str

    def __post_init__(self) -> None:
        object.__setattr__(self, "force", _array(self.force, (3,), "force"))
        object.__setattr__(self, "torque", _array(self.torque, (3,), "torque"))


@dataclass(frozen=True, slots=True)
class CameraFrame:
    """Metadata of one captured camera frame (the pixels stay in the camera's video file).

    Attributes:
        camera_id: Camera name from the rig file.
        frame_index: Index of the frame in the camera's video file, from 0.
        width: Image width [px].
        height: Image height [px].
    """

    stamp: Stamp
    camera_id: str
    frame_index: int
    width: int
    height: int


@dataclass(frozen=True, slots=True)
class ControlSource:
    """Who drove a robot in one control tick, for robots several sources can drive (a policy and an
    operator who takes over); published every tick and recorded, so each tick of an episode says
    whether a person or a policy was in control.

    Attributes:
        source: Device id of the driving source, ``"home"`` while homing; None exactly when
            ``kind`` is ``"none"`` (never the empty string: on the wire that means None).
        kind: What drove (:data:`ControlKind`).
        mode: The handover's mode in that tick (:data:`ControlMode`).

    Raises:
        ValueError: ``kind`` or ``mode`` is not one of its values, or ``source`` and ``kind``
            disagree about whether anyone drove.
    """

    stamp: Stamp
    source: str | None
    kind: ControlKind
    mode: ControlMode

    def __post_init__(self) -> None:
        # Membership tests only: this runs every control tick on the control thread.
        if self.kind not in _CONTROL_KINDS:
            raise ValueError(f"kind must be one of {sorted(_CONTROL_KINDS)}, got {self.kind!r}")
        if self.mode not in _CONTROL_MODES:
            raise ValueError(f"mode must be one of {sorted(_CONTROL_MODES)}, got {self.mode!r}")
        if (self.source is None) != (self.kind == "none") or self.source == "":
            raise ValueError(
                f"source {self.source!r} with kind {self.kind!r}: a source is named exactly when "
                "kind is not 'none', and is not empty"
            )


@dataclass(frozen=True, slots=True)
class RetargetResidual:
    """How well a robot's retargeter reached its target in one solve (the IK residual), one per
    solved input sample; recorded, and drawn by the scene (a flagged target turns red).

    The metrics are named because every retargeter records its own set (the keys of its
    :meth:`~telerig.retarget.binding.Residual.metrics`): the arm IK ``position_error_m``,
    ``orientation_error_rad``; the humanoid IK ``right_wrist_error_m``, ``left_wrist_error_m``,
    ``right_elbow_error_m``, ``left_elbow_error_m``, ``ik_time_s``; the hand ``vector_error_m``,
    ``vector_error_max_m``, ``vectors_valid``, ``solve_s``; the whole-body controller its task
    errors (``ee_linear`` .. ``hand_orientation``), ``mode``, action (``a_vx`` .. ``a_mode``) and
    ``solve_s``.
    The unit is the name's suffix (``_m``, ``_rad``, ``_s``) or the producer's documentation.

    Attributes:
        flagged: True when the target was not reached within the retargeter's threshold.
        names: Metric names, unique and not empty. Length n.
        values: One float per name; NaN where a metric was not measured. Length n. A tuple, not
            an array: a handful of scalars built every control tick, where an array would cost
            more than the encode.

    Raises:
        ValueError: a name is empty or repeated, or the values do not match the names.
        TypeError: a value is not a number.
    """

    stamp: Stamp
    flagged: bool
    names: tuple[str, ...]
    values: tuple[float, ...]

    def __post_init__(self) -> None:
        names = tuple(self.names)
        values = tuple(map(float, self.values))
        object.__setattr__(self, "flagged", bool(self.flagged))  # a NumPy comparison's bool_
        object.__setattr__(self, "names", names)
        object.__setattr__(self, "values", values)
        if len(values) != len(names):
            raise ValueError(f"{len(values)} values for {len(names)} metric names")
        if len(set(names)) != len(names) or "" in names:
            raise ValueError(f"metric names must be unique and not empty, got {names!r}")

    def metrics(self) -> dict[str, float]:
        """The metrics by name (a new dict)."""
        return dict(zip(self.names, self.values, strict=True))

    def get(self, name: str, default: float = float("nan")) -> float:
        """The value of metric ``name``, or ``default`` when this residual does not record it."""
        try:
            return self.values[self.names.index(name)]
        except ValueError:
            return default

    def worst_error_m(self) -> float | None:
        """The largest ``*_error_m`` metric [m]: how far the worst of the solve's targets was missed.
        ``None`` where no such metric is measured; NaN, inf, negative values and values over
        :data:`MAX_ERROR_M` are corrupt and left out."""
        errors = [
            v
            for k, v in zip(self.names, self.values, strict=True)
            if k.endswith("_error_m") and 0.0 <= v <= MAX_ERROR_M
        ]
        return max(errors) if errors else None


#: Any IR sample.
Sample = (
    Pose
    | HandPose
    | BodySkeleton
    | ControllerState
    | Twist
    | JointCommand
    | GripperCommand
    | BaseVelocity
    | JointState
    | CameraFrame
    | Wrench
    | ControlSource
    | RetargetResidual
)
