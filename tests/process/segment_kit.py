"""Real H.264 videos for the segmentation and clip tests: a blob that moves in given spans."""

from __future__ import annotations

from collections.abc import Sequence
from fractions import Fraction
from pathlib import Path
from typing import Any

import av
import numpy as np


def blob_video(
    path: Path,
    *,
    seconds: float,
    moving: Sequence[tuple[float, float]],
    fps: int = 30,
    gop: int = 30,
    b_frames: int = 0,
    size: tuple[int, int] = (160, 120),
    noise: int = 3,
    blob_px: int = 20,
) -> Path:
    """A ``size`` grey video with a ``blob_px`` square that sweeps left-right during each ``moving``
    span [s] at 120 px/s per 160 px of width and rests otherwise; sensor-like noise of +-``noise``
    levels. A keyframe every ``gop`` frames.
    """
    width, height = size
    rng = np.random.default_rng(0)
    x = 10.0
    direction = 1.0
    with av.open(str(path), mode="w", format="mp4") as out:
        stream: Any = out.add_stream(
            "libx264",
            rate=fps,
            options={
                "g": str(gop),
                "keyint_min": str(gop),
                "sc_threshold": "0",
                "bf": str(b_frames),
                "preset": "ultrafast",
            },
        )
        stream.width, stream.height, stream.pix_fmt = width, height, "yuv420p"
        stream.time_base = Fraction(1, fps)
        for i in range(round(seconds * fps)):
            t = i / fps
            if any(a <= t < b for a, b in moving):
                x += direction * 120.0 * width / 160 / fps
                if x > width - blob_px - 10 or x < 10:
                    direction = -direction
            image = np.full((height, width, 3), 90, dtype=np.int16)
            image += rng.integers(-noise, noise + 1, size=(height, width, 1), dtype=np.int16)
            xi, yi = int(x), (height - blob_px) // 2
            image[yi : yi + blob_px, xi : xi + blob_px] = (230, 200, 40)
            frame = av.VideoFrame.from_ndarray(np.clip(image, 0, 255).astype(np.uint8), format="rgb24")
            frame.pts = i
            for packet in stream.encode(frame):
                out.mux(packet)
        for packet in stream.encode(None):
            out.mux(packet)
    return path
