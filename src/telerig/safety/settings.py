"""The configuration guard of an arm, built from its safety settings (:mod:`telerig.config.safety`)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from telerig.config.safety import (
    BoxZoneConfig,
    DeadmanConfig,
    RobotSafetyConfig,
    SphereZoneConfig,
    WorkspaceConfig,
    ZoneConfig,
)
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
