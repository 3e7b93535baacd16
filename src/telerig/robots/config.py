"""Configs of the built-in robot drivers (registered by ``type``)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import Field, model_validator

from telerig.config.schema import RobotConfig
from telerig.registry import ROBOTS

if TYPE_CHECKING:
    from telerig.robots.sim.arm import MujocoArm

__all__ = ["MujocoArmConfig"]


@ROBOTS.register
class MujocoArmConfig(RobotConfig):
    """A simulated arm with a gripper on a table, MuJoCo, stepped headless in real time."""

    type: Literal["mujoco_arm"] = "mujoco_arm"
    model: Literal["ur5e_robotiq85"] = "ur5e_robotiq85"
    physics_rate_hz: Annotated[float, Field(ge=100, le=10_000)] = 500.0
    control_rate_hz: Annotated[float, Field(gt=0, le=1000)] = 100.0

    @model_validator(mode="after")
    def _rates(self) -> MujocoArmConfig:
        ratio = self.physics_rate_hz / self.control_rate_hz
        if ratio < 1 or abs(ratio - round(ratio)) > 1e-9:
            raise ValueError(
                f"physics_rate_hz ({self.physics_rate_hz:g}) must be a whole multiple of control_rate_hz "
                f"({self.control_rate_hz:g}), e.g. 500 and 100"
            )
        return self

    def build(self) -> MujocoArm:
        from telerig.robots.sim.arm import MujocoArm
        from telerig.robots.sim.scene import build_arm_scene

        scene = build_arm_scene(timestep=1.0 / self.physics_rate_hz)
        return MujocoArm(scene, name=self.id)
