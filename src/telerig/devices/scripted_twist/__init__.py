"""A scripted SpaceMouse stand-in: a looping twist script with button presses (dry runs, tests)."""

from telerig.devices.scripted_twist.device import ScriptedTwistDevice, TwistSegment

__all__ = ["ScriptedTwistDevice", "TwistSegment"]
