"""Simulated robots in MuJoCo."""

from telerig.robots.sim.arm import MujocoArm, SimStats
from telerig.robots.sim.scene import ArmScene, build_arm_kinematics, build_arm_scene

__all__ = ["ArmScene", "MujocoArm", "SimStats", "build_arm_kinematics", "build_arm_scene"]
