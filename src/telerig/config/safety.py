"""Safety settings of a rig file: per-robot workspace, self-collision and deadman, and the fault policy.

These are data only; :mod:`telerig.safety` builds the chain, guards and supervisor from them
(:func:`telerig.safety.arm_guard`, :class:`telerig.safety.SafetySupervisor`), so loading a rig
file needs neither the safety package nor the bus.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field

__all__ = [
    "POLICIES",
    "BaseSafetyConfig",
    "BoxZoneConfig",
    "DeadmanConfig",
    "FaultPolicy",
    "GripperSafetyConfig",
    "RobotSafetyConfig",
    "SphereZoneConfig",
    "WorkspaceConfig",
    "ZoneConfig",
]

Vec3 = tuple[float, float, float]

#: ``halt_all``: a fault on one robot e-stops every robot of the rig; ``pause_affected``: only the
#: faulty robot stops, the others keep running (seed: "halt all tasks or only pause the affected device").
FaultPolicy = Literal["halt_all", "pause_affected"]
POLICIES: tuple[FaultPolicy, ...] = ("halt_all", "pause_affected")


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class BoxZoneConfig(_Model):
    """An axis-aligned box in the robot base frame [m]."""

    shape: Literal["box"] = "box"
    name: str = "box"
    lower: Vec3
    upper: Vec3


class SphereZoneConfig(_Model):
    """A sphere in the robot base frame [m]."""

    shape: Literal["sphere"] = "sphere"
    name: str = "sphere"
    center: Vec3
    radius_m: Annotated[float, Field(gt=0)]


ZoneConfig = Annotated[BoxZoneConfig | SphereZoneConfig, Field(discriminator="shape")]


class WorkspaceConfig(_Model):
    """Where the robot's listed points may go (robot base frame)."""

    #: Sites or bodies to keep in bounds; empty means the robot's end-effector site.
    points: list[str] = Field(default_factory=list)
    box: BoxZoneConfig | None = None
    keep_out: list[ZoneConfig] = Field(default_factory=list)
    margin_m: Annotated[float, Field(ge=0, le=1)] = 0.0


class DeadmanConfig(_Model):
    """The enable button: commands pass only while it is held on the given device stream."""

    #: Device stream ``<device>/<part>`` whose samples carry the button, e.g. ``vr0/right_controller``.
    stream: Annotated[str, Field(pattern=r"^[A-Za-z0-9_.\-]+/[A-Za-z0-9_.\-]+$")]
    #: Button name in ``ControllerState.buttons``, or ``"trigger"`` / ``"grip"`` for the analog inputs.
    button: str = "grip"
    #: Analog inputs count as held at or above this value.
    threshold: Annotated[float, Field(gt=0, le=1)] = 0.5
    signal_timeout_ms: Annotated[float, Field(gt=0, le=10_000)] = 200.0


class GripperSafetyConfig(_Model):
    """Limits of a robot's gripper commands (the opening is always kept in [0, 1])."""

    #: Grip force cap [N]; ``None`` leaves each command's force to the gripper's own rating.
    max_force_n: Annotated[float, Field(gt=0, le=10_000)] | None = None


class BaseSafetyConfig(_Model):
    """Limits of a wheeled base's velocity commands, in the base frame.

    The defaults allow a TIAGo-class base its rated speed (1 m/s) and a firm but smooth start
    (0 to 0.3 m/s in 0.15 s); a stop always passes at once.
    """

    #: Planar speed limit |(vx, vy)| [m/s].
    max_linear_m_s: Annotated[float, Field(gt=0, le=5)] = 1.0
    #: Yaw rate limit |wz| [rad/s].
    max_angular_rad_s: Annotated[float, Field(gt=0, le=10)] = 2.0
    #: Planar acceleration limit [m/s^2].
    max_linear_accel_m_s2: Annotated[float, Field(gt=0, le=50)] = 2.0
    #: Yaw acceleration limit [rad/s^2].
    max_angular_accel_rad_s2: Annotated[float, Field(gt=0, le=100)] = 4.0


class RobotSafetyConfig(_Model):
    """Safety settings of one robot, beyond the rig-wide limits and timeouts."""

    workspace: WorkspaceConfig | None = None
    self_collision: bool = False
    collision_margin_m: Annotated[float, Field(ge=0, le=0.1)] = 0.0
    deadman: DeadmanConfig | None = None
    gripper: GripperSafetyConfig = GripperSafetyConfig()
    base: BaseSafetyConfig = BaseSafetyConfig()
