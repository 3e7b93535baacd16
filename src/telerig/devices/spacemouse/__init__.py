"""3Dconnexion SpaceMouse over Linux hidraw: HID reports → operator-frame ``Twist`` and buttons."""

from telerig.devices.spacemouse.device import SpaceMouseDevice, find_spacemouse, list_hidraw
from telerig.devices.spacemouse.protocol import SpaceMouseNormalizer, parse_report

__all__ = ["SpaceMouseDevice", "SpaceMouseNormalizer", "find_spacemouse", "list_hidraw", "parse_report"]
