"""Simulated robots in MuJoCo (their models: :mod:`telerig.robots.models`)."""

from telerig.robots.sim.arm import MujocoArm, SimStats
from telerig.robots.sim.scene import build_arm_scene

__all__ = ["MujocoArm", "SimStats", "build_arm_scene"]
