"""Frame delivery shared by every camera source: stamp, hand to ``on_frame``, count, keep file indices."""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np
import numpy.typing as npt

from telerig.ir.types import CameraFrame, Stamp

__all__ = ["FrameCallback", "FrameDelivery"]

_log = logging.getLogger(__name__)

#: Receives each frame: RGB uint8 image of shape (height, width, 3) and its metadata. Returns False
#: when the frame was not recorded (e.g. the encoder dropped it), so its index is given to the next one.
FrameCallback = Callable[[npt.NDArray[np.uint8], CameraFrame], bool | None]


class FrameDelivery:
    """Stamps each frame and calls ``on_frame`` without ever raising into the capture loop.

    ``frame_index`` counts only accepted frames (``on_frame`` did not return False), so it stays
    the frame's position in the video file; ``seq`` counts every frame. A raising callback is
    counted and logged once.
    """

    __slots__ = ("callback_errors", "frames", "index", "name", "on_frame", "seq")

    def __init__(self, name: str, on_frame: FrameCallback) -> None:
        self.name = name
        self.on_frame = on_frame
        self.index = 0
        self.seq = 0
        self.frames = 0
        self.callback_errors = 0

    def deliver(self, image: npt.NDArray[np.uint8], *, device_ns: int, capture_ns: int) -> bool:
        """Deliver an RGB frame (H, W, 3) captured at ``capture_ns`` [ns]; returns whether it was accepted."""
        height, width = image.shape[:2]
        stamp = Stamp(source_id=self.name, seq=self.seq, device_ns=device_ns, capture_ns=capture_ns)
        meta = CameraFrame(stamp, self.name, self.index, width, height)
        self.seq += 1
        self.frames += 1
        try:
            accepted = self.on_frame(image, meta)
        except Exception:
            self.callback_errors += 1
            if self.callback_errors == 1:
                _log.exception("%s: on_frame failed (later failures are only counted)", self.name)
            accepted = False
        if accepted is False:
            return False
        self.index += 1
        return True
