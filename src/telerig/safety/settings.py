"""The configuration guard of an arm, from its model and safety settings (:mod:`telerig.config.safety`)."""

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
from telerig.errors import ConfigError
from telerig.robots.models import arm_kinematics_of
from telerig.safety.guard import ConfigurationCheck, ConfigurationGuard

if TYPE_CHECKING:
    from telerig.robots.models.arm import ArmScene

__all__ = [
    "BoxZoneConfig",
    "DeadmanConfig",
    "RobotSafetyConfig",
    "SphereZoneConfig",
    "WorkspaceConfig",
    "ZoneConfig",
    "arm_guard",
    "robot_guard",
]


def arm_guard(
    scene: ArmScene, config: RobotSafetyConfig, *, acceleration_fraction: float = 1.0
) -> ConfigurationGuard | None:
    """The configuration guard of an arm (workspace and/or self-collision), or ``None`` if neither is on.

    Checks run on ``scene.model`` (use :func:`~telerig.robots.models.arm.build_arm_kinematics`
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


def robot_guard(
    robot: object, config: RobotSafetyConfig, *, where: str, acceleration_fraction: float = 1.0
) -> ConfigurationGuard | None:
    """The configuration guard of a robot driver, simulated or real, from the arm model it names.

    The model is the robot's :attr:`~telerig.robots.models.ModelledRobot.robot_model` (a
    ``mujoco_arm``'s scene, a ``ur_rtde`` robot's ``model``); its kinematic model
    (:func:`~telerig.robots.models.arm.build_arm_kinematics`) carries the checks.

    Args:
        robot: The robot driver.
        config: The robot's safety settings.
        where: Where the settings are, for the error (e.g. ``safety.robots.arm0``).
        acceleration_fraction: Share of the rated accelerations used for braking, in (0, 1].

    Returns:
        The guard, or ``None`` when neither workspace nor self-collision is on.

    Raises:
        ConfigError: they are on but the robot names no arm model (one line saying what to set).
    """
    if config.workspace is None and not config.self_collision:
        return None
    kinematics = arm_kinematics_of(robot)
    if kinematics is None:
        raise ConfigError(
            f"{where}: workspace and self_collision need the robot's arm model; "
            f"{type(robot).__name__} names none (set it in the robot's config, e.g. `model: ur5e_robotiq85` "
            "on a ur_rtde robot, use a mujoco_arm, or remove them)"
        )
    return arm_guard(kinematics, config, acceleration_fraction=acceleration_fraction)
