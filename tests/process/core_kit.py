"""Inputs for the pipeline tests: small real videos and committed episodes (camera video, frame
stamps and joint states in a real MCAP log), generated in a few hundred milliseconds."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import av
import numpy as np

from telerig.ir import wire
from telerig.ir.mcap_log import McapLog
from telerig.ir.types import CameraFrame, JointState, Stamp
from telerig.store.episodes import EpisodeStore

T0_NS = 1_790_000_000_000_000_000
"""Common-clock start of the generated episodes [ns] (2026-09-21)."""
RIG = "kit"
JOINTS_TOPIC = f"telerig/v1/{RIG}/arm0/joint_state"
FRAMES_TOPIC = f"telerig/v1/{RIG}/front/frames"


def make_video(path: Path, *, seconds: float = 1.0, fps: int = 10, shade: int = 0) -> Path:
    """A small H.264 MP4 (160x120) whose frame ``i`` is filled with ``(shade + 9 i) % 256``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=fps, options={"preset": "ultrafast"})
        stream.width, stream.height, stream.pix_fmt = 160, 120, "yuv420p"
        image = np.zeros((120, 160, 3), dtype=np.uint8)
        for i in range(round(seconds * fps)):
            image[:] = (shade + 9 * i) % 256
            for packet in stream.encode(av.VideoFrame.from_ndarray(image, format="rgb24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    return path


def make_episode(root: Path, *, seconds: float = 2.0, fps: int = 10, task: str = "pick") -> str:
    """Commit a real episode in the store at ``root``: a ``front`` camera video, its frame stamps
    and a 50 Hz joint state of one 2-joint arm in ``episode.mcap``. Returns its id."""
    store = EpisodeStore(root)
    draft = store.begin(rig=RIG, task=task, operator="ann", start_ns=T0_NS)
    frames = round(seconds * fps)
    make_video(draft.camera_path("front"), seconds=seconds, fps=fps)
    with McapLog(draft.mcap_path, flush_interval_s=60.0) as log:
        for i in range(round(seconds * 50)):
            t = T0_NS + i * 20_000_000
            sample = JointState(
                Stamp("arm0", i, device_ns=t, capture_ns=t),
                ("j1", "j2"),
                np.array([0.01 * i, -0.01 * i]),
                np.zeros(2),
            )
            log.write(JOINTS_TOPIC, wire.encode(sample), log_time_ns=t, publish_time_ns=t)
        for i in range(frames):
            t = T0_NS + round(i * 1e9 / fps)
            frame = CameraFrame(Stamp("front", i, device_ns=t, capture_ns=t), "front", i, 160, 120)
            log.write(FRAMES_TOPIC, wire.encode(frame), log_time_ns=t, publish_time_ns=t)
    extra: dict[str, Any] = {
        "station": "station-7",
        "robots": ["arm0"],
        "cameras": {"front": {"file": "cameras/front.mp4", "frames": frames, "fps": float(fps)}},
    }
    manifest = draft.commit(extra, end_ns=T0_NS + round(seconds * 1e9))
    return manifest.id
