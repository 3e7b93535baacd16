"""Gamepads over Linux evdev: input_event records → left/right ``ControllerState`` and a ``Twist``."""

from telerig.devices.gamepad.device import GamepadDevice, find_gamepad, list_event_devices
from telerig.devices.gamepad.protocol import GamepadNormalizer, parse_events

__all__ = ["GamepadDevice", "GamepadNormalizer", "find_gamepad", "list_event_devices", "parse_events"]
