"""Dobot CR-series arms over the controller's TCP/IP protocol (V3/V4), with a fake controller for dry runs."""

from telerig.robots.dobot.driver import CR5_LIMITS, DobotRobot
from telerig.robots.dobot.fake import FakeDobot
from telerig.robots.dobot.protocol import FeedbackPacket, Reply, RobotMode

__all__ = ["CR5_LIMITS", "DobotRobot", "FakeDobot", "FeedbackPacket", "Reply", "RobotMode"]
