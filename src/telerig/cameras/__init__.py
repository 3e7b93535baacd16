"""Cameras: MuJoCo, webcam, video-file and RealSense sources, the crash-safe encoder, JPEG previews."""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from telerig.cameras.capture import Camera, CaptureClock, CaptureStats, V4l2Camera, VideoFileCamera
    from telerig.cameras.encoder import Codec, EncodeResult, VideoEncoder
    from telerig.cameras.mujoco_camera import CameraStats, FrameCallback, LockProvider, MujocoCamera
    from telerig.cameras.preview import PreviewPublisher, PreviewStats
    from telerig.cameras.realsense import RealSenseCamera

__all__ = [
    "Camera",
    "CameraStats",
    "CaptureClock",
    "CaptureStats",
    "PreviewPublisher",
    "PreviewStats",
    "RealSenseCamera",
    "V4l2Camera",
    "VideoFileCamera",
    "Codec",
    "EncodeResult",
    "FrameCallback",
    "LockProvider",
    "MujocoCamera",
    "VideoEncoder",
]

# Imported on first use: the encoder needs PyAV (telerig[record]) and the camera MuJoCo
# (telerig[sim]); reading camera configs needs neither.
_HOMES = {
    "Camera": "capture",
    "CaptureClock": "capture",
    "CaptureStats": "capture",
    "V4l2Camera": "capture",
    "VideoFileCamera": "capture",
    "PreviewPublisher": "preview",
    "PreviewStats": "preview",
    "RealSenseCamera": "realsense",
    "Codec": "encoder",
    "EncodeResult": "encoder",
    "VideoEncoder": "encoder",
    "CameraStats": "mujoco_camera",
    "FrameCallback": "mujoco_camera",
    "LockProvider": "mujoco_camera",
    "MujocoCamera": "mujoco_camera",
}


def __getattr__(name: str) -> Any:
    if name not in _HOMES:
        raise AttributeError(f"module 'telerig.cameras' has no attribute {name!r}")
    return getattr(importlib.import_module(f"telerig.cameras.{_HOMES[name]}"), name)
