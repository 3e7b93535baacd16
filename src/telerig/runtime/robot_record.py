"""What an episode's manifest records about a robot (``EpisodeExtra.robot_joints``), read off its
driver where the driver runs: in the station's process or in a robot host's."""

from __future__ import annotations

import math
from typing import Protocol, runtime_checkable

from telerig.config.schema import RobotConfig
from telerig.robots.base import RobotDriver, StandingRobot
from telerig.store.manifest_extra import RobotJointsRecord

__all__ = ["robot_joints_record"]


@runtime_checkable
class _Modelled(Protocol):
    """A robot config that names its model (e.g. ``ur5e_robotiq85``; ``None`` on a real arm without)."""

    model: str | None


def robot_joints_record(config: RobotConfig, driver: RobotDriver) -> RobotJointsRecord:
    """The driver's joint order and limits, gripper and standing height, with the config's type and model."""
    limits = driver.limits
    return RobotJointsRecord(
        type=config.type,
        model=config.model if isinstance(config, _Modelled) else None,
        joints=list(limits.names),
        lower=_bounds(limits.lower.tolist()),
        upper=_bounds(limits.upper.tolist()),
        velocity=limits.velocity.tolist(),
        acceleration=limits.acceleration.tolist(),
        gripper=driver.has_gripper,
        standing_height_m=driver.standing_height_m if isinstance(driver, StandingRobot) else None,
    )


def _bounds(values: list[float]) -> list[float | None]:
    """Position limits with ``None`` for an unbounded joint (JSON has no infinity)."""
    return [v if math.isfinite(v) else None for v in values]
