"""Modbus robot drivers (Inspire hand over TCP, DH-Robotics grippers over RTU) and their fake peers."""

from telerig.robots.modbus._link import LinkStats
from telerig.robots.modbus.dh_gripper import DHGripper, DHStatus
from telerig.robots.modbus.fake import FakeDHGripper, FakeInspireHand
from telerig.robots.modbus.inspire import InspireHand, InspireHealth

__all__ = [
    "DHGripper",
    "DHStatus",
    "FakeDHGripper",
    "FakeInspireHand",
    "InspireHand",
    "InspireHealth",
    "LinkStats",
]
