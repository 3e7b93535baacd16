"""Operator calibration core: neutral pose → axis-aligned operator-to-robot rotation, arm length, scale.

The operator holds both hands straight forward, parallel to the ground, for the calibration
window. From the hand poses (``ControllerState``, ``HandPose`` wrists, ``Pose`` of a hand
tracker, or the wrist joints of a ``BodySkeleton``) this module computes:

* the neutral hand poses (mean position and orientation per hand) and how still they were;
* the rotation operator frame → robot base frame: of the 24 rotations of the cube, the one that
  brings the neutral hand orientations closest to the robot's neutral end-effector orientation
  (``q_robot ≈ R q_hand``, the convention of :class:`telerig.config.schema.AlignmentConfig`);
* the arm length (shoulder → tracked hand point) and the human-to-robot scale
  ``robot_reach_m / arm_length_m``.

Shoulders come from a body skeleton when one is streamed, else from the head (HMD) pose with an
anthropometric model (see :class:`CalibrationSettings`): the HMD position is taken at the eyes;
the shoulder joint centres lie ``shoulder_drop_m`` below it, ``shoulder_back_m`` behind it and
``shoulder_half_width_m`` to each side. The defaults come from Drillis & Contini's segment ratios
for a 1.75 m adult (Winter, *Biomechanics and Motor Control of Human Movement*, fig. 4.1): eye
height 0.936 H and shoulder height 0.818 H (0.118 H = 0.21 m apart), shoulder width 0.259 H
(0.45 m between acromia, about 0.38 m between the joint centres); the joint centre sits about
0.09 m behind the eyes. "Forward" is the horizontal direction from the head to the hands' midpoint
(the hands are held straight forward), "up" is :attr:`CalibrationSettings.up`. For an operator far
from 1.75 m tall the arm length is off by a few centimetres; stream a skeleton or set
``arm_length_m`` when that matters.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from telerig.calibrate.profile import CalibrationProfile
from telerig.calibrate.rotations import cube_rotations, mean_quaternion
from telerig.devices.validate import SampleValidator
from telerig.errors import CalibrationError
from telerig.ir.frames import quat_angle, quat_multiply
from telerig.ir.types import (
    BodySkeleton,
    ControllerState,
    FloatArray,
    Handedness,
    HandPose,
    Pose,
    Sample,
)

__all__ = [
    "FORWARD_TOP_UP",
    "CalibrationError",
    "CalibrationSettings",
    "Role",
    "role_from_source",
    "run_calibration",
]

#: What a pose sample tracks during calibration.
Role = Literal["left", "right", "head"]

#: Tool orientation (w, x, y, z) pointing along base +x with its top (+x) up (tool z → base x,
#: tool x → base z, tool y → base -y): the controller convention's "hand straight forward".
FORWARD_TOP_UP: tuple[float, float, float, float] = (0.0, math.sqrt(0.5), 0.0, math.sqrt(0.5))

Quat = tuple[float, float, float, float]
Vec3 = tuple[float, float, float]


class CalibrationSettings(BaseModel):
    """Robot neutral pose, acceptance thresholds and the anthropometric shoulder model.

    Attributes:
        robot_neutral_orientation: End-effector orientation (w, x, y, z) in the robot base frame,
            tool convention +z approach / +x top, that the operator's hands-forward pose maps to.
        robot_neutral_orientation_left: The same for the left hand when it differs (e.g. hand
            trackers whose left wrist frame is mirrored); ``None`` uses the one above.
        robot_reach_m: Robot shoulder → end-effector distance at full reach [m] (UR5e: 0.85).
        hands: Hands that must be calibrated.
        up: Up direction in the operator frame (unit or not). Shape (3,).
        max_position_std_m: Largest hand position spread (sqrt of covariance trace) [m].
        max_orientation_std_deg: Largest RMS angle of a hand's orientation from its mean [deg].
        max_residual_deg: Largest angle left between a rotated neutral hand orientation and the
            robot neutral after the best cube rotation [deg] (the pose was not axis-aligned).
        max_height_difference_m: Largest height difference between the two hands [m].
        min_coverage: Share of ``duration_s`` the hand samples must cover, in (0, 1].
        min_samples: Fewest samples per hand.
        arm_length_m: Use this arm length [m] instead of measuring it.
        arm_length_range_m: Plausible measured arm lengths [m]; outside is rejected.
        shoulder_drop_m: Shoulder joint centres below the HMD (eyes) [m].
        shoulder_back_m: Shoulder joint centres behind the HMD [m].
        shoulder_half_width_m: Shoulder joint centre to the body midline [m].
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    robot_neutral_orientation: Quat = FORWARD_TOP_UP
    robot_neutral_orientation_left: Quat | None = None
    robot_reach_m: Annotated[float, Field(gt=0, le=10)] = 0.85
    hands: tuple[Handedness, ...] = ("left", "right")
    up: Vec3 = (0.0, 0.0, 1.0)
    max_position_std_m: Annotated[float, Field(gt=0)] = 0.03
    max_orientation_std_deg: Annotated[float, Field(gt=0)] = 10.0
    max_residual_deg: Annotated[float, Field(gt=0, le=180)] = 35.0
    max_height_difference_m: Annotated[float, Field(gt=0)] = 0.15
    min_coverage: Annotated[float, Field(gt=0, le=1)] = 0.8
    min_samples: Annotated[int, Field(ge=2)] = 10
    arm_length_m: Annotated[float, Field(gt=0, le=3)] | None = None
    arm_length_range_m: tuple[float, float] = (0.35, 1.1)
    shoulder_drop_m: Annotated[float, Field(ge=0, le=1)] = 0.21
    shoulder_back_m: Annotated[float, Field(ge=-0.5, le=0.5)] = 0.09
    shoulder_half_width_m: Annotated[float, Field(ge=0, le=0.5)] = 0.19

    @field_validator("robot_neutral_orientation", "robot_neutral_orientation_left")
    @classmethod
    def _unit(cls, q: Quat | None) -> Quat | None:
        if q is not None:
            norm = math.sqrt(sum(c * c for c in q))
            if abs(norm - 1.0) > 1e-3:
                raise ValueError(f"must be a unit quaternion (w, x, y, z); its norm is {norm:.4f}")
        return q

    @field_validator("hands")
    @classmethod
    def _hands(cls, hands: tuple[Handedness, ...]) -> tuple[Handedness, ...]:
        if not hands or len(set(hands)) != len(hands):
            raise ValueError("hands must name 'left' and/or 'right', each once")
        return hands

    @field_validator("up")
    @classmethod
    def _up(cls, up: Vec3) -> Vec3:
        n = math.sqrt(sum(c * c for c in up))
        if not (math.isfinite(n) and n > 1e-9):
            raise ValueError("up must be a finite non-zero vector (x, y, z)")
        return (up[0] / n, up[1] / n, up[2] / n)

    @model_validator(mode="after")
    def _range(self) -> CalibrationSettings:
        lo, hi = self.arm_length_range_m
        if not 0 < lo < hi:
            raise ValueError(f"arm_length_range_m must be (low, high) with 0 < low < high, got {lo}, {hi}")
        return self

    def robot_neutral(self, hand: Handedness) -> FloatArray:
        """Robot neutral end-effector orientation (w, x, y, z) for ``hand``. Shape (4,)."""
        q = self.robot_neutral_orientation
        if hand == "left" and self.robot_neutral_orientation_left is not None:
            q = self.robot_neutral_orientation_left
        return np.array(q, dtype=np.float64)


def role_from_source(source_id: str) -> Role | None:
    """Guess what a ``Pose`` stream tracks from its source id: ``head``/``hmd`` → head, then
    ``left`` / ``right``; ``None`` when the id says neither (e.g. ``"quest/head"`` → ``"head"``)."""
    s = source_id.lower()
    if "head" in s or "hmd" in s:
        return "head"
    if "left" in s:
        return "left"
    if "right" in s:
        return "right"
    return None


# Skeleton joint names, normalized (lower case, letters and digits only), best first: the upper
# arm joint is the glenohumeral joint (BVH "LeftArm", NatNet "LUArm"); "shoulder" is the clavicle
# in BVH / NatNet but the glenohumeral joint in MediaPipe / COCO.
_SHOULDER_NAMES: dict[Handedness, tuple[str, ...]] = {
    "left": ("leftarm", "leftupperarm", "luarm", "lupperarm", "leftshoulder", "lshoulder", "shoulderleft"),
    "right": (
        "rightarm",
        "rightupperarm",
        "ruarm",
        "rupperarm",
        "rightshoulder",
        "rshoulder",
        "shoulderright",
    ),
}
_WRIST_NAMES: dict[Handedness, tuple[str, ...]] = {
    "left": ("leftwrist", "lwrist", "wristleft", "lefthand", "lhand", "handleft"),
    "right": ("rightwrist", "rwrist", "wristright", "righthand", "rhand", "handright"),
}


def _joint_index(names: tuple[str, ...], candidates: tuple[str, ...]) -> int | None:
    normalized = [re.sub(r"[^a-z0-9]", "", n.lower()) for n in names]
    for c in candidates:
        if c in normalized:
            return normalized.index(c)
    return None


@dataclass(slots=True)
class _Series:
    """Positions (n, 3) and orientations (n, 4) of one tracked thing, with capture times [ns]."""

    ns: list[int] = field(default_factory=list)
    positions: list[FloatArray] = field(default_factory=list)
    orientations: list[FloatArray] = field(default_factory=list)

    def add(self, ns: int, position: FloatArray, orientation: FloatArray | None = None) -> None:
        self.ns.append(ns)
        self.positions.append(position)
        if orientation is not None:
            self.orientations.append(orientation)

    def window(self, start_ns: int) -> _Series:
        keep = [i for i, t in enumerate(self.ns) if t >= start_ns]
        out = _Series([self.ns[i] for i in keep], [self.positions[i] for i in keep])
        if self.orientations:
            out.orientations = [self.orientations[i] for i in keep]
        return out


@dataclass(slots=True)
class _Collected:
    hands: dict[Handedness, _Series] = field(default_factory=dict)
    skeleton_hands: dict[Handedness, _Series] = field(default_factory=dict)
    head: _Series = field(default_factory=_Series)
    shoulders: dict[Handedness, _Series] = field(default_factory=dict)
    frames: set[str] = field(default_factory=set)
    dropped: int = 0


def _collect(
    samples: Iterable[Sample], roles: Mapping[str, Role] | None, validator: SampleValidator
) -> _Collected:
    out = _Collected()
    for sample in samples:
        if validator.validate(sample) is not None:
            out.dropped += 1
            continue
        ns = sample.stamp.capture_ns
        match sample:
            case ControllerState():
                out.hands.setdefault(sample.hand, _Series()).add(ns, sample.position, sample.orientation)
            case HandPose():
                out.hands.setdefault(sample.handedness, _Series()).add(
                    ns, sample.wrist_position, sample.wrist_orientation
                )
            case Pose():
                sid = sample.stamp.source_id
                role = roles.get(sid) if roles is not None else None
                role = role if role is not None else role_from_source(sid)
                if role is None:
                    continue
                if role == "head":
                    out.head.add(ns, sample.position)
                else:
                    out.hands.setdefault(role, _Series()).add(ns, sample.position, sample.orientation)
            case BodySkeleton():
                for hand, shoulder_names in _SHOULDER_NAMES.items():
                    i = _joint_index(sample.joint_names, shoulder_names)
                    if i is not None:
                        out.shoulders.setdefault(hand, _Series()).add(ns, sample.positions[i])
                    j = _joint_index(sample.joint_names, _WRIST_NAMES[hand])
                    if j is not None:
                        out.skeleton_hands.setdefault(hand, _Series()).add(
                            ns, sample.positions[j], sample.orientations[j]
                        )
            case _:
                continue
        out.frames.add(getattr(sample, "frame_id", ""))
    for hand, series in out.skeleton_hands.items():
        out.hands.setdefault(hand, series)  # skeleton wrists only stand in for missing hand streams
    return out


@dataclass(frozen=True, slots=True)
class _Neutral:
    position: FloatArray
    orientation: FloatArray
    position_std_m: float
    orientation_std_deg: float
    samples: int
    span_s: float


def _neutral(series: _Series) -> _Neutral:
    p = np.array(series.positions)
    q = np.array(series.orientations)
    mean_q = mean_quaternion(q)
    dots = np.clip(np.abs(q @ mean_q), 0.0, 1.0)
    angle_rms = math.degrees(float(np.sqrt(np.mean((2.0 * np.arccos(dots)) ** 2))))
    return _Neutral(
        position=p.mean(axis=0),
        orientation=mean_q,
        position_std_m=math.sqrt(float(np.trace(np.atleast_2d(np.cov(p.T, bias=True))))),
        orientation_std_deg=angle_rms,
        samples=len(series.ns),
        span_s=(max(series.ns) - min(series.ns)) / 1e9,
    )


def _best_rotation(
    neutral: Mapping[Handedness, _Neutral], settings: CalibrationSettings
) -> tuple[FloatArray, float]:
    """The cube rotation minimizing the summed angle between ``R q_hand`` and the robot neutral;
    returns it (w, x, y, z) and the largest remaining angle [deg]."""
    best_q = np.array([1.0, 0.0, 0.0, 0.0])
    best_cost = math.inf
    best_worst = math.inf
    for _, q_c in cube_rotations():
        angles = [
            quat_angle(quat_multiply(q_c, n.orientation), settings.robot_neutral(hand))
            for hand, n in neutral.items()
        ]
        cost = sum(angles)
        if cost < best_cost - 1e-9:
            best_q, best_cost, best_worst = q_c, cost, max(angles)
    return np.array(best_q), math.degrees(best_worst)


def _shoulders_from_head(
    head: FloatArray, hands: Mapping[Handedness, FloatArray], settings: CalibrationSettings
) -> dict[Handedness, FloatArray]:
    up = np.array(settings.up)
    ahead = np.mean(list(hands.values()), axis=0) - head
    forward = ahead - float(ahead @ up) * up
    norm = float(np.linalg.norm(forward))
    if norm < 0.05:
        raise CalibrationError(
            "the hands are not in front of the head; hold both arms straight forward and recalibrate"
        )
    forward /= norm
    left = np.cross(up, forward)
    centre = head - settings.shoulder_back_m * forward - settings.shoulder_drop_m * up
    w = settings.shoulder_half_width_m
    return {"left": centre + w * left, "right": centre - w * left}


def run_calibration(
    samples: Iterable[Sample],
    *,
    duration_s: float = 30.0,
    operator: str = "operator",
    settings: CalibrationSettings | None = None,
    roles: Mapping[str, Role] | None = None,
    validator: SampleValidator | None = None,
    created: datetime | None = None,
) -> CalibrationProfile:
    """Compute an operator's calibration from the samples of a hands-forward hold.

    Only the last ``duration_s`` of hand samples (by ``stamp.capture_ns``) is used; samples that
    fail ``validator`` (default: :meth:`SampleValidator.default`) are ignored.

    Args:
        samples: Device samples of the hold, any order of streams, each stream in time order.
        duration_s: Calibration window [s] (> 0).
        operator: Operator name for the profile.
        settings: Robot neutral, thresholds, shoulder model; defaults when None.
        roles: ``source_id`` → what a ``Pose`` stream tracks; :func:`role_from_source` otherwise.
        validator: Sample validation; a fresh default one when None.
        created: Time stamp of the profile (UTC now when None).

    Raises:
        CalibrationError: One line saying why the hold cannot be used (too short, hands moving,
            not level, not axis-aligned, no way to measure the arm, implausible arm length).
    """
    if not (math.isfinite(duration_s) and duration_s > 0):
        raise CalibrationError(f"duration_s must be > 0 s, got {duration_s}")
    cfg = settings if settings is not None else CalibrationSettings()
    data = _collect(samples, roles, validator if validator is not None else SampleValidator.default())

    missing = [h for h in cfg.hands if not data.hands.get(h, _Series()).ns]
    if missing:
        seen = ", ".join(sorted(data.hands)) or "none"
        raise CalibrationError(
            f"no valid {' or '.join(missing)} hand samples (hands seen: {seen}; {data.dropped} samples "
            "failed validation); track both hands, or set `hands` to the ones you use"
        )
    frames = sorted(data.frames)
    if len(frames) > 1:
        raise CalibrationError(
            f"samples are in different frames ({', '.join(frames)}); calibrate in one frame"
        )
    end_ns = max(max(data.hands[h].ns) for h in cfg.hands)
    start_ns = end_ns - int(duration_s * 1e9)

    neutral: dict[Handedness, _Neutral] = {}
    for hand in cfg.hands:
        series = data.hands[hand].window(start_ns)
        if len(series.ns) < cfg.min_samples:
            raise CalibrationError(
                f"only {len(series.ns)} valid {hand} hand samples in the window (need {cfg.min_samples}); "
                "check the tracking and recalibrate"
            )
        n = _neutral(series)
        if n.span_s < cfg.min_coverage * duration_s:
            raise CalibrationError(
                f"the {hand} hand was tracked for {n.span_s:.1f} s of the {duration_s:.1f} s window; "
                "keep both hands in view for the whole calibration"
            )
        if n.position_std_m > cfg.max_position_std_m:
            raise CalibrationError(
                f"the {hand} hand moved during calibration (position spread {100 * n.position_std_m:.1f} cm "
                f"> {100 * cfg.max_position_std_m:.1f} cm); hold both hands still, straight forward"
            )
        if n.orientation_std_deg > cfg.max_orientation_std_deg:
            raise CalibrationError(
                f"the {hand} hand turned during calibration (orientation spread {n.orientation_std_deg:.1f}° "
                f"> {cfg.max_orientation_std_deg:.1f}°); hold both hands still, straight forward"
            )
        neutral[hand] = n

    up = np.array(cfg.up)
    if len(neutral) == 2:
        dz = abs(float((neutral["left"].position - neutral["right"].position) @ up))
        if dz > cfg.max_height_difference_m:
            raise CalibrationError(
                f"the hands are {100 * dz:.0f} cm apart in height (> "
                f"{100 * cfg.max_height_difference_m:.0f} cm); hold both hands level, parallel to the ground"
            )

    rotation, residual_deg = _best_rotation(neutral, cfg)
    if residual_deg > cfg.max_residual_deg:
        raise CalibrationError(
            f"the hands are {residual_deg:.0f}° away from any axis-aligned neutral pose "
            f"(> {cfg.max_residual_deg:.0f}°); point both hands straight forward, level, and recalibrate"
        )

    hand_points = {h: n.position for h, n in neutral.items()}
    shoulders: dict[Handedness, FloatArray] = {}
    source: Literal["head", "skeleton", "given"]
    if cfg.arm_length_m is not None:
        arm_length, source = cfg.arm_length_m, "given"
    else:
        sk = {h: data.shoulders[h].window(start_ns) for h in cfg.hands if h in data.shoulders}
        head = data.head.window(start_ns)
        if len(sk) == len(cfg.hands) and all(s.ns for s in sk.values()):
            shoulders = {h: np.mean(s.positions, axis=0) for h, s in sk.items()}
            source = "skeleton"
        elif head.ns:
            shoulders = _shoulders_from_head(np.mean(head.positions, axis=0), hand_points, cfg)
            source = "head"
        else:
            raise CalibrationError(
                "no head pose or body skeleton in the window, so the arm length cannot be measured; "
                "stream the headset pose (a Pose whose source id names 'head') or set arm_length_m"
            )
        arm_length = float(np.mean([np.linalg.norm(hand_points[h] - shoulders[h]) for h in cfg.hands]))
        lo, hi = cfg.arm_length_range_m
        if not lo <= arm_length <= hi:
            raise CalibrationError(
                f"measured arm length {arm_length:.2f} m is not plausible ({lo:.2f}-{hi:.2f} m); check that "
                "the head/skeleton and hands are tracked in the same frame, or set arm_length_m"
            )

    return CalibrationProfile(
        operator=operator,
        created=created if created is not None else datetime.now(UTC),
        frame_id=frames[0] if frames else "",
        rotation=_quat_tuple(rotation),
        scale=cfg.robot_reach_m / arm_length,
        arm_length_m=arm_length,
        arm_length_source=source,
        robot_reach_m=cfg.robot_reach_m,
        neutral_positions={h: _vec_tuple(n.position) for h, n in neutral.items()},
        neutral_orientations={h: _quat_tuple(n.orientation) for h, n in neutral.items()},
        shoulders={h: _vec_tuple(shoulders[h]) for h in cfg.hands if h in shoulders},
        residual_deg=residual_deg,
        position_std_m={h: n.position_std_m for h, n in neutral.items()},
        duration_s=(end_ns - min(min(data.hands[h].window(start_ns).ns) for h in cfg.hands)) / 1e9,
        samples=sum(n.samples for n in neutral.values()),
    )


def _vec_tuple(v: FloatArray) -> Vec3:
    x, y, z = (float(c) for c in v)
    return (x, y, z)


def _quat_tuple(q: FloatArray) -> Quat:
    w, x, y, z = (float(c) for c in np.asarray(q) / np.linalg.norm(q))
    return (w, x, y, z)
