"""Configs of the built-in cameras (registered by ``type``)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import Field

from telerig.config.schema import CameraConfig, Identifier
from telerig.registry import CAMERAS

if TYPE_CHECKING:
    from telerig.cameras.capture import Camera
    from telerig.cameras.mujoco_camera import FrameCallback, MujocoCamera

__all__ = [
    "MujocoCameraConfig",
    "RealSenseCameraConfig",
    "V4l2CameraConfig",
    "VideoFileCameraConfig",
]


@CAMERAS.register
class MujocoCameraConfig(CameraConfig):
    """A camera of a simulated robot's scene, rendered offscreen from the physics of ``robot``."""

    type: Literal["mujoco"] = "mujoco"
    robot: Identifier
    camera: str = "scene"

    def build(self, on_frame: FrameCallback, *, robots: Mapping[str, object] | None = None) -> MujocoCamera:
        """The scene camera of ``robots[self.robot]``, which must be a simulated robot.

        ``robots``: the robots built in this process, by rig id (any object: the camera layer does
        not import the robots; a robot is simulated when it has a rendered scene and ``locked``).

        Raises:
            ConfigError: the robot is not among ``robots``, or is not simulated.
        """
        from telerig.cameras.mujoco_camera import MujocoCamera, RenderedScene, SimulatedRobot
        from telerig.errors import ConfigError

        robot = (robots or {}).get(self.robot)
        if robot is None:
            raise ConfigError(
                f"camera {self.id!r}: robot {self.robot!r} is not built in this process; run the camera "
                "where its robot runs"
            )
        if not (isinstance(robot, SimulatedRobot) and isinstance(robot.scene, RenderedScene)):
            raise ConfigError(
                f"camera {self.id!r}: robot {self.robot!r} is not simulated; use a real camera type"
            )
        return MujocoCamera(
            self.id,
            self.camera,
            robot.locked,
            on_frame=on_frame,
            width=self.width,
            height=self.height,
            fps=self.fps,
            geom_groups=robot.scene.visual_groups,
        )


@CAMERAS.register
class V4l2CameraConfig(CameraConfig):
    """A USB/UVC webcam through Video4Linux2 (PyAV), with kernel capture timestamps."""

    type: Literal["v4l2"] = "v4l2"
    device: str = "/dev/video0"
    input_format: str | None = "mjpeg"

    def build(self, on_frame: FrameCallback, *, robots: Mapping[str, object] | None = None) -> Camera:
        from telerig.cameras.capture import V4l2Camera

        return V4l2Camera(
            self.id,
            on_frame=on_frame,
            device=self.device,
            width=self.width,
            height=self.height,
            fps=self.fps,
            input_format=self.input_format,
        )


@CAMERAS.register
class VideoFileCameraConfig(CameraConfig):
    """A video file replayed as a camera at its own timing (any format PyAV reads)."""

    type: Literal["video_file"] = "video_file"
    path: Path
    loop: bool = False
    speed: Annotated[float, Field(gt=0, le=100)] = 1.0

    def build(self, on_frame: FrameCallback, *, robots: Mapping[str, object] | None = None) -> Camera:
        from telerig.cameras.capture import VideoFileCamera

        return VideoFileCamera(
            self.id,
            self.path,
            on_frame=on_frame,
            loop=self.loop,
            width=self.width,
            height=self.height,
            speed=self.speed,
        )


@CAMERAS.register
class RealSenseCameraConfig(CameraConfig):
    """An Intel RealSense colour stream (``pip install telerig[realsense]``)."""

    type: Literal["realsense"] = "realsense"
    serial: str | None = None

    def build(self, on_frame: FrameCallback, *, robots: Mapping[str, object] | None = None) -> Camera:
        from telerig.cameras.realsense import RealSenseCamera

        return RealSenseCamera(
            self.id, on_frame=on_frame, serial=self.serial, width=self.width, height=self.height, fps=self.fps
        )
