"""Leap Motion class hand tracker over the service's legacy WebSocket JSON protocol: HandPose samples."""

from telerig.devices.leap.protocol import (
    DESK_MOUNT,
    LeapEvent,
    LeapFrame,
    LeapHand,
    Mounting,
    ServiceVersion,
    hand_pose,
    parse_message,
)

__all__ = [
    "DESK_MOUNT",
    "LeapEvent",
    "LeapFrame",
    "LeapHand",
    "Mounting",
    "ServiceVersion",
    "hand_pose",
    "parse_message",
]
