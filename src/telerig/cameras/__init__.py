"""Cameras: offscreen MuJoCo cameras and the crash-safe video encoder they feed."""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from telerig.cameras.encoder import Codec, EncodeResult, VideoEncoder
    from telerig.cameras.mujoco_camera import CameraStats, FrameCallback, LockProvider, MujocoCamera

__all__ = [
    "CameraStats",
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
