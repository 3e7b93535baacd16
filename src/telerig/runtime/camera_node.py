"""Camera node: renders a simulated camera, encodes each episode's MP4, publishes frame stamps."""

from __future__ import annotations

import dataclasses
import threading
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
    """A camera that runs for the whole session and records into one MP4 per episode.

    The renderer is created once in :meth:`start` (creating a GL context holds
    the GIL for ~150 ms, which must not happen while a robot is being
    controlled). Pixels stay local; only frame stamps go on the bus, and only
    for frames the encoder took, so a published ``frame_index`` is always the
    frame's position in that episode's video file.
    """

    def __init__(self, rig: str, config: CameraConfig, camera: str, robot: MujocoArm, bus: Bus) -> None:
        self.config = config
        self._bus = bus
        self._topic = str(Topic(rig, config.id, streams.CAMERA_FRAMES))
        self._lock = threading.Lock()
        self._encoder: VideoEncoder | None = None
        self._index = 0
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

    def start(self) -> None:
        """Create the renderer and start capturing (frames are dropped until :meth:`begin`)."""
        self._camera.start()

    def stop(self) -> None:
        """Finish any open video and stop capturing. Idempotent."""
        self.end()
        self._camera.stop()

    def begin(self, path: Path) -> None:
        """Start recording into a new MP4 at ``path``."""
        encoder = VideoEncoder(path, width=self.config.width, height=self.config.height, fps=self.config.fps)
        with self._lock:
            if self._encoder is not None:
                raise RuntimeError(f"camera {self.config.id!r} is already recording; end() first")
            self._encoder, self._index = encoder, 0

    def end(self) -> EncodeResult | None:
        """Close the current MP4 and return its result; ``None`` when not recording."""
        with self._lock:
            encoder, self._encoder = self._encoder, None
        return encoder.finish() if encoder is not None else None

    def _on_frame(self, image: npt.NDArray[np.uint8], meta: CameraFrame) -> bool:
        with self._lock:
            encoder = self._encoder
            if encoder is None or not encoder.submit(image, meta.stamp.capture_ns):
                return False
            meta = dataclasses.replace(meta, frame_index=self._index)
            self._index += 1
        self._bus.publish(self._topic, wire.encode(meta))
        return True
