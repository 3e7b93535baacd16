"""Universal Robots over RTDE and URScript: the driver, its wire format and a fake controller."""

from __future__ import annotations

from telerig.robots.ur.driver import ClockMapper, URRobot, URStats, URStatus
from telerig.robots.ur.fake import FakeURController
from telerig.robots.ur.limits import UR_JOINT_NAMES, UR_MODELS, ur_limits
from telerig.robots.ur.robotiq import ROBOTIQ_PORT, RobotiqSocket
from telerig.robots.ur.script import ServoProgram, stop_program

__all__ = [
    "ROBOTIQ_PORT",
    "UR_JOINT_NAMES",
    "UR_MODELS",
    "ClockMapper",
    "FakeURController",
    "RobotiqSocket",
    "ServoProgram",
    "URRobot",
    "URStats",
    "URStatus",
    "stop_program",
    "ur_limits",
]
