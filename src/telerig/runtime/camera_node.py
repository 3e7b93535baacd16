"""Camera node: runs one camera, encodes each episode's MP4, publishes frame stamps and previews."""

from __future__ import annotations

import dataclasses
import threading
from collections.abc import Callable
from pathlib import Path

import numpy as np
import numpy.typing as npt

from telerig.bus.base import Bus
from telerig.bus.topics import Topic
from telerig.cameras.capture import Camera
from telerig.cameras.encoder import EncodeResult, VideoEncoder
from telerig.cameras.mujoco_camera import FrameCallback
from telerig.cameras.observation import ObservationPublisher
from telerig.cameras.preview import PreviewPublisher
from telerig.config.schema import CameraConfig
from telerig.ir import wire
from telerig.ir.types import CameraFrame
from telerig.runtime import streams

__all__ = ["CameraEpisode", "CameraNode"]

#: Builds the camera of a node, given the callback it must deliver frames to.
CameraFactory = Callable[[FrameCallback], Camera]


@dataclasses.dataclass(frozen=True, slots=True)
class CameraEpisode:
    """What one camera recorded in an episode: its video, and what the camera itself lost or
    delivered late while it recorded (its ``stats`` at :meth:`CameraNode.end` less those at
    :meth:`CameraNode.begin`), which says why a camera stream has gaps.

    Attributes:
        video: What the encoder wrote (frames, frames its full queue refused, capture times).
        skipped: Frames lost before the encoder: deadlines a simulated camera woke too late for or
            snapshots its renderer fell behind on, frames a device dropped, a replay's late frames.
        late: Frames the camera captured or delivered late (see each camera's ``stats``).
        callback_errors: Frames whose delivery raised.
    """

    video: EncodeResult
    skipped: int
    late: int
    callback_errors: int


class CameraNode:
    """A camera that runs for the whole session and records into one MP4 per episode.

    The camera is started once in :meth:`start` (a simulated camera creates its GL
    context then, which must not happen while a robot is being controlled).
    Pixels stay local; only frame stamps go on the bus, and only for frames the
    encoder took, so a published ``frame_index`` is always the frame's position in
    that episode's video file. Low-rate JPEG previews go on the ``preview`` stream; when the rig sets
    the camera's ``observation``, small raw frames for a policy go on ``observation``.
    """

    def __init__(self, rig: str, config: CameraConfig, make_camera: CameraFactory, bus: Bus) -> None:
        self.config = config
        self._bus = bus
        self._topic = str(Topic(rig, config.id, streams.CAMERA_FRAMES))
        self._lock = threading.Lock()
        self._encoder: VideoEncoder | None = None
        self._index = 0
        self._counts_at_begin = (0, 0, 0)
        p = config.preview
        self._preview = (
            PreviewPublisher(
                bus, rig, config.id, max_width=p.max_width, max_height=p.max_height, rate_hz=p.rate_hz
            )
            if p.enabled
            else None
        )
        o = config.observation
        self.observation = (
            None
            if o is None
            else ObservationPublisher(bus, rig, config.id, width=o.width, height=o.height, rate_hz=o.rate_hz)
        )
        self._camera = make_camera(self._on_frame)

    @property
    def camera(self) -> Camera:
        return self._camera

    def start(self) -> None:
        """Start capturing (frames are only previewed until :meth:`begin`)."""
        self._camera.start()

    def stop(self) -> None:
        """Finish any open video, stop capturing and previews. Idempotent."""
        self.end()
        self._camera.stop()
        if self._preview is not None:
            self._preview.close()
        if self.observation is not None:
            self.observation.close()

    def begin(self, path: Path) -> None:
        """Start recording into a new MP4 at ``path``."""
        cfg = self.config
        encoder = VideoEncoder(path, width=cfg.width, height=cfg.height, fps=cfg.fps, codec=cfg.codec)
        with self._lock:
            if self._encoder is not None:
                raise RuntimeError(f"camera {self.config.id!r} is already recording; end() first")
            self._encoder, self._index = encoder, 0
            self._counts_at_begin = self._counts()

    def end(self) -> CameraEpisode | None:
        """Close the current MP4; the episode's video and camera counters, ``None`` when not recording."""
        with self._lock:
            encoder, self._encoder = self._encoder, None
            counts = self._counts()
        if encoder is None:
            return None
        skipped, late, errors = (now - then for now, then in zip(counts, self._counts_at_begin, strict=True))
        return CameraEpisode(encoder.finish(), skipped, late, errors)

    def _counts(self) -> tuple[int, int, int]:
        stats = self._camera.stats
        return stats.skipped, stats.late, stats.callback_errors

    def _on_frame(self, image: npt.NDArray[np.uint8], meta: CameraFrame) -> bool:
        if self._preview is not None:
            self._preview.offer(image, meta.stamp.capture_ns)
        if self.observation is not None:
            self.observation.offer(image, meta.stamp.capture_ns)
        with self._lock:
            encoder = self._encoder
            if encoder is None or not encoder.submit(image, meta.stamp.capture_ns):
                return False
            meta = dataclasses.replace(meta, frame_index=self._index)
            self._index += 1
        self._bus.publish(self._topic, wire.encode(meta))
        return True
