"""Keyboard in the terminal (cbreak tty, no global hook): held keys → ``Twist``, keys → buttons."""

from telerig.devices.keyboard.device import KeyboardDevice
from telerig.devices.keyboard.protocol import KeyboardNormalizer, KeyDecoder, decode_keys

__all__ = ["KeyDecoder", "KeyboardDevice", "KeyboardNormalizer", "decode_keys"]
