"""Data gloves (Manus-class) over the telerig glove bridge stream: HandPose samples and gestures."""

from telerig.devices.glove.device import GloveDevice
from telerig.devices.glove.gesture import Gesture, GestureThresholds, GestureTracker, classify
from telerig.devices.glove.kinematics import HandModel, glove_hand_pose
from telerig.devices.glove.protocol import GloveFrame, GloveStreamDecoder, decode_frame, encode_frame

__all__ = [
    "Gesture",
    "GestureThresholds",
    "GestureTracker",
    "GloveDevice",
    "GloveFrame",
    "GloveStreamDecoder",
    "HandModel",
    "classify",
    "decode_frame",
    "encode_frame",
    "glove_hand_pose",
]
