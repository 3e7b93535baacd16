"""Which model a robot driver stands for, and the arm kinematics IK and the safety guards build on it."""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol, runtime_checkable

if TYPE_CHECKING:
    from telerig.robots.models.arm import ArmScene

__all__ = ["ModelledRobot", "arm_kinematics_of"]


@runtime_checkable
class ModelledRobot(Protocol):
    """A robot driver (simulated or real) that names its model: IK and the safety guards build on it."""

    @property
    def robot_model(self) -> str | None:
        """Name of the robot's arm model (a key of :data:`~telerig.robots.models.ARM_MODELS`); None: none."""
        ...

    @property
    def joint_names(self) -> tuple[str, ...]: ...


def arm_kinematics_of(robot: object) -> ArmScene | None:
    """The kinematic model (arm joints only) IK and the safety guard use for ``robot``; None if not an arm.

    A robot is an arm when it names an arm model (:class:`ModelledRobot`: a simulated arm, or a
    real one whose config names its ``model``) and commands that model's joints, in order
    (bimanual arms prefix them, e.g. ``left_shoulder_pan_joint``). Humanoid, mobile-manipulator and
    hand drivers build on the simulated arm but are not arms for this purpose.

    Raises:
        ConfigError: the robot names an arm model that does not exist.
        DependencyError: MuJoCo or robosuite (the model source) is not installed.
    """
    if not isinstance(robot, ModelledRobot) or robot.robot_model is None:
        return None
    from telerig.robots.models.arm import build_arm_kinematics  # MuJoCo is the sim extra

    kinematics = build_arm_kinematics(robot.robot_model)
    names, joints = robot.joint_names, kinematics.arm_joints
    if len(names) != len(joints):
        return None
    if any(n != j and not n.endswith("_" + j) for n, j in zip(names, joints, strict=True)):
        return None
    return kinematics
