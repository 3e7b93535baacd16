"""Configs of the built-in robot drivers (registered by ``type``)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import Field, model_validator

from telerig.config.schema import Identifier, RobotConfig
from telerig.registry import ROBOTS

if TYPE_CHECKING:
    from telerig.robots.sim.arm import MujocoArm
    from telerig.robots.sim.bimanual import BimanualArm
    from telerig.robots.sim.gripper import MujocoGripper

__all__ = ["MujocoArmConfig", "MujocoBimanualArmConfig", "MujocoGripperConfig"]


@ROBOTS.register
class MujocoArmConfig(RobotConfig):
    """A simulated arm with a gripper on a table, MuJoCo, stepped headless in real time."""

    type: Literal["mujoco_arm"] = "mujoco_arm"
    #: Arm model (``telerig.robots.sim.models.ARM_MODELS``): UR5e + Robotiq 2F-85 (6 DoF) or Panda (7 DoF).
    model: Literal["ur5e_robotiq85", "panda"] = "ur5e_robotiq85"
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

        scene = build_arm_scene(self.model, timestep=1.0 / self.physics_rate_hz)
        return MujocoArm(scene, name=self.id)


def _check_rates(physics_rate_hz: float, control_rate_hz: float) -> None:
    ratio = physics_rate_hz / control_rate_hz
    if ratio < 1 or abs(ratio - round(ratio)) > 1e-9:
        raise ValueError(
            f"physics_rate_hz ({physics_rate_hz:g}) must be a whole multiple of control_rate_hz "
            f"({control_rate_hz:g}), e.g. 500 and 100"
        )


@ROBOTS.register
class MujocoGripperConfig(RobotConfig):
    """A simulated Robotiq 2F-85 alone on a fixed mount over a table (1 DoF), MuJoCo, real time."""

    type: Literal["mujoco_gripper"] = "mujoco_gripper"
    physics_rate_hz: Annotated[float, Field(ge=100, le=10_000)] = 500.0
    control_rate_hz: Annotated[float, Field(gt=0, le=1000)] = 100.0

    @model_validator(mode="after")
    def _rates(self) -> MujocoGripperConfig:
        _check_rates(self.physics_rate_hz, self.control_rate_hz)
        return self

    def build(self) -> MujocoGripper:
        from telerig.robots.sim.gripper import MujocoGripper, build_gripper_scene

        return MujocoGripper(build_gripper_scene(timestep=1.0 / self.physics_rate_hz), name=self.id)


@ROBOTS.register
class MujocoBimanualArmConfig(RobotConfig):
    """One arm of a simulated bimanual station; the two arm configs naming one ``station`` share its physics.

    A rig lists both arms, e.g. ``{id: left, type: mujoco_bimanual_arm, station: bench, side: left}``
    and the same with ``side: right``; their joints are named ``left_...`` and ``right_...``.
    """

    type: Literal["mujoco_bimanual_arm"] = "mujoco_bimanual_arm"
    station: Identifier
    side: Literal["left", "right"]
    model: Literal["ur5e_robotiq85", "panda"] = "ur5e_robotiq85"
    physics_rate_hz: Annotated[float, Field(ge=100, le=10_000)] = 500.0
    control_rate_hz: Annotated[float, Field(gt=0, le=1000)] = 100.0

    @model_validator(mode="after")
    def _rates(self) -> MujocoBimanualArmConfig:
        _check_rates(self.physics_rate_hz, self.control_rate_hz)
        return self

    def build(self) -> BimanualArm:
        from telerig.robots.sim.bimanual import BimanualStation

        station = BimanualStation.shared(self.station, self.model, timestep=1.0 / self.physics_rate_hz)
        return station.arm(self.side, name=self.id)
