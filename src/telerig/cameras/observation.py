"""Low-resolution raw frames of a camera for a policy, resized on a worker thread, published on the bus.

The dashboard's previews (320x240 JPEG at 2 Hz) are too slow and lossy for a policy acting at
10-30 Hz, so a camera whose rig entry sets ``observation:`` also publishes frames at the policy's
input size (e.g. 96x96) at a bounded rate on ``<camera>/observation``, raw RGB in the format of
:mod:`telerig.ir.observation`. The camera's capture thread only copies a due frame into a one-frame
slot (never blocks; a frame that finds the slot full is dropped and counted); the worker resizes it
with PyAV's area filter (libswscale) and publishes it at QoS 0.
"""

from __future__ import annotations

import logging
import threading

import numpy as np
import numpy.typing as npt

from telerig import priority
from telerig.bus.base import Bus
from telerig.bus.catalogue import OBSERVATION
from telerig.bus.topics import Topic
from telerig.ir.observation import encode_observation

__all__ = ["ObservationPublisher", "resize_area"]

_log = logging.getLogger(__name__)


def resize_area(image: npt.NDArray[np.uint8], width: int, height: int) -> npt.NDArray[np.uint8]:
    """An RGB uint8 image (H, W, 3) resized to exactly ``width`` x ``height`` [px] with area averaging."""
    if image.shape[0] == height and image.shape[1] == width:
        return np.ascontiguousarray(image)
    import av

    frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(image), format="rgb24")
    out = frame.reformat(width=width, height=height, format="rgb24", interpolation="AREA")
    return np.asarray(out.to_ndarray(), dtype=np.uint8)


class ObservationPublisher:
    """Publishes ``width`` x ``height`` RGB frames of one camera at most ``rate_hz`` times a second.

    Args:
        bus: Bus to publish on.
        rig: Rig name.
        camera: Camera id (the topic's node).
        width: Frame width [px].
        height: Frame height [px].
        rate_hz: Frames per second at most, on a grid in capture time [Hz].

    Counters: ``offered``, ``published``, ``rate_skipped``, ``dropped`` (worker busy), ``errors``.
    """

    def __init__(self, bus: Bus, rig: str, camera: str, *, width: int, height: int, rate_hz: float) -> None:
        if width < 1 or height < 1:
            raise ValueError(f"observation size must be at least 1x1 px, got {width}x{height}")
        if not rate_hz > 0:
            raise ValueError(f"observation rate_hz must be positive, got {rate_hz}")
        self.topic = str(Topic(rig, camera, OBSERVATION))
        self.width, self.height, self.rate_hz = width, height, rate_hz
        self._bus = bus
        self._period_ns = round(1e9 / rate_hz)
        self._next_ns: int | None = None
        self._cond = threading.Condition()
        self._slot: tuple[npt.NDArray[np.uint8], int, int] | None = None
        self._closed = False
        self._thread: threading.Thread | None = None
        self._seq = 0
        self.offered = self.published = self.rate_skipped = self.dropped = self.errors = 0

    def offer(self, image: npt.NDArray[np.uint8], capture_ns: int) -> bool:
        """Consider one RGB frame (H, W, 3) captured at ``capture_ns`` [ns]; never blocks.

        Returns whether it was taken (False: not due, worker busy, or closed).
        """
        with self._cond:
            self.offered += 1
            if self._closed:
                return False
            if self._next_ns is not None and capture_ns < self._next_ns:
                self.rate_skipped += 1
                return False
            due = capture_ns if self._next_ns is None else self._next_ns
            self._next_ns = max(due + self._period_ns, capture_ns)
            if self._slot is not None:
                self.dropped += 1
                return False
            self._seq += 1
            self._slot = (np.array(image, dtype=np.uint8, copy=True), capture_ns, self._seq)
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name=f"obs-{self.topic}", daemon=True)
                self._thread.start()
            self._cond.notify()
            return True

    def close(self) -> None:
        """Stop the worker (after the frame in progress). Idempotent."""
        with self._cond:
            self._closed = True
            self._cond.notify()
            thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join()

    def _run(self) -> None:
        priority.enter("work")  # below the control loop
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._slot is not None or self._closed)
                if self._slot is None:
                    return
                image, capture_ns, seq = self._slot
            try:
                small = resize_area(image, self.width, self.height)
                self._bus.publish(self.topic, encode_observation(small, capture_ns, seq), qos=0, retain=False)
                self.published += 1
            except Exception as exc:
                self.errors += 1
                if self.errors == 1:
                    _log.error("%s: observation failed (later failures only counted): %s", self.topic, exc)
            finally:
                with self._cond:
                    self._slot = None
