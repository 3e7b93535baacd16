"""Configs of the built-in cameras (registered by ``type``)."""

from __future__ import annotations

from typing import Literal

from telerig.config.schema import CameraConfig, Identifier
from telerig.registry import CAMERAS

__all__ = ["MujocoCameraConfig"]


@CAMERAS.register
class MujocoCameraConfig(CameraConfig):
    """A camera of a simulated robot's scene, rendered offscreen."""

    type: Literal["mujoco"] = "mujoco"
    robot: Identifier
    camera: str = "scene"
