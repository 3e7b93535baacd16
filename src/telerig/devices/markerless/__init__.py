"""Markerless tracking: webcam or video file → MediaPipe (in its own venv) → HandPose / BodySkeleton."""

from telerig.devices.markerless.device import MarkerlessDevice
from telerig.devices.markerless.fake import FakeTracker, typical_payload
from telerig.devices.markerless.protocol import FUZZ_TARGET, POSE_JOINTS, decode

__all__ = ["FUZZ_TARGET", "POSE_JOINTS", "FakeTracker", "MarkerlessDevice", "decode", "typical_payload"]
