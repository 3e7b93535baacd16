"""Per-robot safety settings of a rig (workspace, self-collision, deadman) and the guard built from them."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field

from telerig.safety.guard import ConfigurationCheck, ConfigurationGuard

if TYPE_CHECKING:
    from telerig.robots.sim.scene import ArmScene

__all__ = [
    "BoxZoneConfig",
    "DeadmanConfig",
    "RobotSafetyConfig",
    "SphereZoneConfig",
    "WorkspaceConfig",
    "ZoneConfig",
    "arm_guard",
]

Vec3 = tuple[float, float, float]


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


class RobotSafetyConfig(_Model):
    """Safety settings of one robot, beyond the rig-wide limits and timeouts."""

    workspace: WorkspaceConfig | None = None
    self_collision: bool = False
    collision_margin_m: Annotated[float, Field(ge=0, le=0.1)] = 0.0
    deadman: DeadmanConfig | None = None


def arm_guard(
    scene: ArmScene, config: RobotSafetyConfig, *, acceleration_fraction: float = 1.0
) -> ConfigurationGuard | None:
    """The configuration guard of an arm (workspace and/or self-collision), or ``None`` if neither is on.

    Checks run on ``scene.model`` (use :func:`~telerig.robots.sim.scene.build_arm_kinematics`
    for speed; a full scene works too); positions are in the frame of ``scene.base_body``; pairs
    in contact at ``scene.home`` are allowed.

    Raises:
        ConfigError: a point or body does not exist, or a zone is invalid.
        DependencyError: MuJoCo (the sim extra) is missing.
    """
    from telerig.safety.collision import SelfCollision
    from telerig.safety.kinematics import KinematicsModel
    from telerig.safety.workspace import Box, Sphere, WorkspaceBounds, Zone

    if config.workspace is None and not config.self_collision:
        return None
    kin = KinematicsModel(scene.model, scene.arm_joints, base_body=scene.base_body)
    checks: list[ConfigurationCheck] = []
    ws = config.workspace
    if ws is not None:

        def zone(z: BoxZoneConfig | SphereZoneConfig) -> Zone:
            if isinstance(z, BoxZoneConfig):
                return Box(z.lower, z.upper, z.name)
            return Sphere(z.center, z.radius_m, z.name)

        box = None if ws.box is None else Box(ws.box.lower, ws.box.upper, ws.box.name)
        points = ws.points or [scene.ee_site]
        checks.append(
            WorkspaceBounds(
                kin, points, box=box, keep_out=[zone(z) for z in ws.keep_out], margin_m=ws.margin_m
            )
        )
    if config.self_collision:
        checks.append(SelfCollision(kin, allowed=[scene.home], margin_m=config.collision_margin_m))
    return ConfigurationGuard(checks, acceleration_fraction=acceleration_fraction)
