"""CameraNode: each episode's video, with what the camera lost or delivered late while it recorded."""

from __future__ import annotations

import pickle
from dataclasses import replace
from pathlib import Path

import numpy as np

from telerig.bus.memory import InMemoryBus
from telerig.cameras.capture import CaptureStats
from telerig.cameras.config import VideoFileCameraConfig
from telerig.cameras.mujoco_camera import FrameCallback
from telerig.ir.types import CameraFrame, Stamp
from telerig.runtime.camera_node import CameraEpisode, CameraNode

W, H = 32, 24


class _CountingCamera:
    """A camera whose frames and counters the test sets (the node's side of the Camera protocol)."""

    name = "cam"

    def __init__(self, on_frame: FrameCallback) -> None:
        self.on_frame = on_frame
        self.counters = CaptureStats(frames=0, late=0, skipped=0, callback_errors=0, mean_decode_ms=0.0)
        self._seq = 0

    def start(self) -> None:
        pass

    def stop(self) -> None:
        pass

    @property
    def stats(self) -> CaptureStats:
        return self.counters

    def deliver(self, n: int) -> None:
        for _ in range(n):
            t = 1_700_000_000_000_000_000 + self._seq * 33_000_000
            meta = CameraFrame(Stamp(self.name, self._seq, t, t), self.name, self._seq, W, H)
            self.on_frame(np.zeros((H, W, 3), np.uint8), meta)
            self._seq += 1
            self.counters = replace(self.counters, frames=self.counters.frames + 1)

    def lose(self, *, skipped: int = 0, late: int = 0, callback_errors: int = 0) -> None:
        c = self.counters
        self.counters = replace(
            c,
            skipped=c.skipped + skipped,
            late=c.late + late,
            callback_errors=c.callback_errors + callback_errors,
        )


def _node(tmp_path: Path) -> tuple[CameraNode, _CountingCamera]:
    config = VideoFileCameraConfig(id="cam", path=tmp_path / "unused.mp4", width=W, height=H, fps=30.0)
    cameras: list[_CountingCamera] = []

    def make_camera(on_frame: FrameCallback) -> _CountingCamera:
        cameras.append(_CountingCamera(on_frame))
        return cameras[0]

    node = CameraNode(
        "rig",
        config.model_copy(update={"preview": config.preview.model_copy(update={"enabled": False})}),
        make_camera,
        InMemoryBus(),
    )
    return node, cameras[0]


def test_an_episode_counts_only_what_the_camera_lost_while_it_recorded(tmp_path: Path) -> None:
    node, camera = _node(tmp_path)
    node.start()
    camera.deliver(3)
    camera.lose(skipped=4, late=2, callback_errors=1)  # before the episode: not its own
    node.begin(tmp_path / "e1.mp4")
    camera.deliver(5)
    camera.lose(skipped=3, late=6)
    camera.deliver(2)
    first = node.end()
    camera.lose(skipped=10)  # between episodes
    node.begin(tmp_path / "e2.mp4")
    camera.deliver(4)
    camera.lose(callback_errors=2)
    second = node.end()
    node.stop()
    assert isinstance(first, CameraEpisode)
    assert isinstance(second, CameraEpisode)
    assert (first.video.frames, first.skipped, first.late, first.callback_errors) == (7, 3, 6, 0)
    assert (second.video.frames, second.skipped, second.late, second.callback_errors) == (4, 0, 0, 2)
    assert node.end() is None  # not recording


def test_an_episode_crosses_the_robot_process_boundary_whole(tmp_path: Path) -> None:
    node, camera = _node(tmp_path)
    node.start()
    node.begin(tmp_path / "e.mp4")
    camera.deliver(2)
    camera.lose(skipped=1)
    episode = node.end()
    node.stop()
    assert episode is not None
    assert pickle.loads(pickle.dumps(episode)) == episode
