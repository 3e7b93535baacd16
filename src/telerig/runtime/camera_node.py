"""Camera node: renders a simulated camera, encodes it to the episode's MP4, publishes frame stamps."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import numpy.typing as npt

from telerig.bus.base import Bus
from telerig.bus.topics import Topic
from telerig.cameras.encoder import EncodeResult, VideoEncoder
from telerig.cameras.mujoco_camera import MujocoCamera
from telerig.config.schema import CameraConfig
from telerig.ir import wire
from telerig.ir.types import CameraFrame
from telerig.robots.sim.arm import MujocoArm
from telerig.runtime import streams

__all__ = ["CameraNode"]


class CameraNode:
    """One camera for one episode: pixels go to a local MP4, only frame stamps go on the bus.

    A frame the encoder cannot take (queue full) is not published either, so the
    published ``frame_index`` is always the frame's position in the video file.
    """

    def __init__(
        self, rig: str, config: CameraConfig, camera: str, robot: MujocoArm, bus: Bus, path: Path
    ) -> None:
        self._bus = bus
        self._topic = str(Topic(rig, config.id, streams.CAMERA_FRAMES))
        self._encoder = VideoEncoder(path, width=config.width, height=config.height, fps=config.fps)
        self._camera = MujocoCamera(
            config.id,
            camera,
            robot.locked,
            on_frame=self._on_frame,
            width=config.width,
            height=config.height,
            fps=config.fps,
            geom_groups=robot.scene.visual_groups,
        )
        self._result: EncodeResult | None = None

    def start(self) -> None:
        self._camera.start()

    def finish(self) -> EncodeResult:
        """Stop capturing and close the video. Idempotent."""
        if self._result is None:
            self._camera.stop()
            self._result = self._encoder.finish()
        return self._result

    def _on_frame(self, image: npt.NDArray[np.uint8], meta: CameraFrame) -> bool:
        if not self._encoder.submit(image, meta.stamp.capture_ns):
            return False
        self._bus.publish(self._topic, wire.encode(meta))
        return True
