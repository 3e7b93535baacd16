"""Robots: the driver interface and its joint limits (simulated drivers live in ``telerig.robots.sim``)."""

from telerig.robots.base import JointLimits, RobotDriver

__all__ = ["JointLimits", "RobotDriver"]
