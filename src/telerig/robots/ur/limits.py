"""Joint names and datasheet limits of the Universal Robots e-Series arms."""

from __future__ import annotations

import math

import numpy as np

from telerig.robots.base import JointLimits

__all__ = ["UR_JOINT_NAMES", "UR_MODELS", "ur_limits"]

#: UR joint names, base to tool (the names of the URDF/MJCF models too).
UR_JOINT_NAMES: tuple[str, ...] = (
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
)

_DEG = math.pi / 180.0
#: Joint speed limits per model [deg/s], from the e-Series datasheets (base to tool).
_SPEED_DEG: dict[str, tuple[float, ...]] = {
    "ur3e": (180, 180, 180, 360, 360, 360),
    "ur5e": (180, 180, 180, 180, 180, 180),
    "ur10e": (120, 120, 180, 180, 180, 180),
    "ur16e": (120, 120, 180, 180, 180, 180),
}
#: Models :func:`ur_limits` knows.
UR_MODELS: tuple[str, ...] = tuple(_SPEED_DEG)
#: Universal Robots publishes no per-joint acceleration limit; this conservative teleoperation value
#: [rad/s^2] matches the simulated UR5e (well above the URScript ``movej`` default of 1.4).
_ACCELERATION = 8.0


def ur_limits(model: str = "ur5e") -> JointLimits:
    """Limits of a UR e-Series arm: +-360 deg on every joint [rad], datasheet speeds [rad/s].

    Raises:
        ValueError: unknown ``model``; the message lists :data:`UR_MODELS`.
    """
    try:
        speed = np.array(_SPEED_DEG[model], dtype=np.float64) * _DEG
    except KeyError:
        raise ValueError(f"unknown UR model {model!r}. Valid: {', '.join(UR_MODELS)}") from None
    n = len(UR_JOINT_NAMES)
    return JointLimits(
        names=UR_JOINT_NAMES,
        lower=np.full(n, -2 * math.pi),
        upper=np.full(n, 2 * math.pi),
        velocity=speed,
        acceleration=np.full(n, _ACCELERATION),
    )
