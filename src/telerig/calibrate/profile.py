"""Per-operator calibration profiles: the JSON model, where profiles live, and their alignment."""

from __future__ import annotations

import math
import os
import tempfile
from datetime import UTC, datetime
from pathlib import Path
from typing import Annotated, Literal

from pydantic import AwareDatetime, BaseModel, ConfigDict, Field, ValidationError, field_validator

from telerig.config.schema import AlignmentConfig
from telerig.errors import ConfigError
from telerig.ir.types import Handedness

__all__ = [
    "DEFAULT_DATA_ROOT",
    "PROFILE_VERSION",
    "CalibrationProfile",
    "alignment_for",
    "load_profile",
    "profile_path",
    "save_profile",
]

#: Version of the profile file format this code writes and reads.
PROFILE_VERSION: Literal[1] = 1
#: Where profiles go when no data root is given (the rig's default ``recording.data_root``).
DEFAULT_DATA_ROOT = Path("telerig-data")

OperatorName = Annotated[str, Field(pattern=r"^[A-Za-z0-9_.\-]+$", min_length=1, max_length=64)]
Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]


class CalibrationProfile(BaseModel):
    """One operator's calibration, stored as ``<data_root>/operators/<operator>.json``.

    Positions are in the operator frame the calibration samples were in (``frame_id``; telerig's
    operator frame is x forward, y left, z up, metres).

    Attributes:
        version: File format version (:data:`PROFILE_VERSION`).
        operator: Operator name (letters, digits, ``_ . -``).
        created: When the calibration was taken (timezone-aware, UTC).
        frame_id: Frame of the measured positions and orientations.
        rotation: Operator frame → robot base frame (w, x, y, z); one of the 24 cube rotations.
        scale: Human-to-robot motion scale = ``robot_reach_m / arm_length_m``.
        arm_length_m: Shoulder → tracked hand point distance [m] (controller grip or wrist).
        arm_length_source: ``"head"`` (shoulders estimated from the head pose), ``"skeleton"``
            (shoulder joints of a body skeleton) or ``"given"`` (set by the user).
        robot_reach_m: Robot shoulder → end-effector distance at full reach used for ``scale`` [m].
        neutral_positions: Mean hand position over the window, per hand [m].
        neutral_orientations: Mean hand orientation (w, x, y, z) over the window, per hand.
        shoulders: Shoulder positions used for the arm length, per hand [m]; empty when given.
        residual_deg: Largest angle between a rotated neutral hand orientation and the robot's
            neutral end-effector orientation [deg] (how far from axis-aligned the pose was).
        position_std_m: Hand position spread over the window (sqrt of the covariance trace) [m].
        duration_s: Time the window covered [s].
        samples: Hand samples used.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    version: Literal[1] = PROFILE_VERSION
    operator: OperatorName
    created: AwareDatetime = Field(default_factory=lambda: datetime.now(UTC))
    frame_id: str
    rotation: Quat
    scale: Annotated[float, Field(gt=0, le=100)]
    arm_length_m: Annotated[float, Field(gt=0, le=3)]
    arm_length_source: Literal["head", "skeleton", "given"]
    robot_reach_m: Annotated[float, Field(gt=0, le=10)]
    neutral_positions: dict[Handedness, Vec3]
    neutral_orientations: dict[Handedness, Quat]
    shoulders: dict[Handedness, Vec3] = Field(default_factory=dict)
    residual_deg: Annotated[float, Field(ge=0, le=180)]
    position_std_m: dict[Handedness, float]
    duration_s: Annotated[float, Field(ge=0)]
    samples: Annotated[int, Field(ge=0)]

    @field_validator("rotation")
    @classmethod
    def _unit(cls, q: Quat) -> Quat:
        norm = math.sqrt(sum(c * c for c in q))
        if abs(norm - 1.0) > 1e-6:
            raise ValueError(f"rotation must be a unit quaternion (w, x, y, z); its norm is {norm:.6f}")
        return q


def profile_path(operator: str, *, data_root: Path | str = DEFAULT_DATA_ROOT) -> Path:
    """``<data_root>/operators/<operator>.json``; the name must be a plain identifier."""
    _check_name(operator)
    return Path(data_root) / "operators" / f"{operator}.json"


def save_profile(profile: CalibrationProfile, *, data_root: Path | str = DEFAULT_DATA_ROOT) -> Path:
    """Write ``profile`` atomically (temp file + rename) to its path; returns the path."""
    path = profile_path(profile.operator, data_root=data_root)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{profile.operator}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(profile.model_dump_json(indent=2))
            f.write("\n")
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def load_profile(operator: str, *, data_root: Path | str = DEFAULT_DATA_ROOT) -> CalibrationProfile:
    """Read the profile of ``operator``; ``ConfigError`` saying what to do if it is missing or invalid."""
    path = profile_path(operator, data_root=data_root)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        known = sorted(p.stem for p in path.parent.glob("*.json")) if path.parent.is_dir() else []
        raise ConfigError(
            f"no calibration profile for operator {operator!r} at {path}; run "
            f"`telerig calibrate --operator {operator}`. Available: {', '.join(known) or 'none'}"
        ) from None
    try:
        profile = CalibrationProfile.model_validate_json(text)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"]) or "file"
        raise ConfigError(
            f"calibration profile {path} is invalid ({where}: {first['msg']}); recalibrate with "
            f"`telerig calibrate --operator {operator}`"
        ) from None
    if profile.operator != operator:
        raise ConfigError(f"calibration profile {path} belongs to {profile.operator!r}, not {operator!r}")
    return profile


def alignment_for(
    profile: CalibrationProfile, *, hand: Handedness = "right", base: AlignmentConfig | None = None
) -> AlignmentConfig:
    """The :class:`AlignmentConfig` of one arm from a profile.

    ``rotation`` and ``scale`` come from the profile and ``operator_origin`` is the neutral
    position of ``hand``, so the operator's neutral hand maps onto ``robot_origin`` (kept from
    ``base``: set it to the robot's neutral end-effector position).
    """
    if hand not in profile.neutral_positions:
        raise ConfigError(
            f"profile of {profile.operator!r} has no {hand} hand; calibrated hands: "
            f"{', '.join(sorted(profile.neutral_positions)) or 'none'}"
        )
    fields = (base if base is not None else AlignmentConfig()).model_dump()
    fields.update(
        rotation=profile.rotation,
        operator_origin=profile.neutral_positions[hand],
        scale=profile.scale,
    )
    return AlignmentConfig.model_validate(fields)


def _check_name(operator: str) -> None:
    if not (
        isinstance(operator, str)
        and 0 < len(operator) <= 64
        and all(c.isascii() and (c.isalnum() or c in "_.-") for c in operator)
        and operator not in (".", "..")
    ):
        raise ConfigError(
            f"operator name {operator!r} must be 1-64 letters, digits, '_', '.' or '-' (it names a file)"
        )
