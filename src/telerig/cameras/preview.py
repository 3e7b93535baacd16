"""Low-rate JPEG previews of a camera for the dashboard, encoded on a worker thread, published on the bus."""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from fractions import Fraction
from types import TracebackType
from typing import Any

import numpy as np
import numpy.typing as npt

from telerig import priority
from telerig.bus.base import Bus
from telerig.bus.topics import Topic
from telerig.ir.types import now_ns

__all__ = [
    "PREVIEW_STREAM",
    "STAMP_PREFIX",
    "PreviewPublisher",
    "PreviewStats",
    "encode_jpeg",
    "preview_size",
    "stamp_jpeg",
]

_log = logging.getLogger("telerig.cameras.preview")

#: Stream name of previews: ``telerig/v1/<rig>/<camera>/preview``; payload: one JPEG image.
PREVIEW_STREAM = "preview"


@dataclass(frozen=True, slots=True)
class PreviewStats:
    """Counters of a :class:`PreviewPublisher`.

    Attributes:
        offered: Frames passed to :meth:`PreviewPublisher.offer`.
        published: JPEG previews published.
        rate_skipped: Frames not wanted because a preview was published less than a period ago.
        dropped: Frames wanted but dropped because the worker was still busy with the last one.
        errors: Frames whose encoding or publishing failed.
        mean_encode_ms: Mean time to downsample and encode one preview [ms].
        last_capture_ns: Capture time of the last published preview, common clock [ns]; 0 before.
    """

    offered: int
    published: int
    rate_skipped: int
    dropped: int
    errors: int
    mean_encode_ms: float
    last_capture_ns: int


#: The comment segment's text before the stamps (``telerig-stamps <capture_ns> <encoded_ns>``).
STAMP_PREFIX = b"telerig-stamps "


def stamp_jpeg(jpeg: bytes, capture_ns: int, encoded_ns: int) -> bytes:
    """``jpeg`` with a comment segment (``FF FE``) right after its start marker that carries the
    frame's capture time and the time its preview was encoded [ns, common clock]: the control
    center measures the video stages of the live view by them (``telerig.server.view_latency``).
    Decoders skip comments, so the image is unchanged; 46 bytes at most."""
    text = STAMP_PREFIX + b"%d %d" % (capture_ns, encoded_ns)
    return jpeg[:2] + b"\xff\xfe" + (len(text) + 2).to_bytes(2, "big") + text + jpeg[2:]


def preview_size(width: int, height: int, max_width: int, max_height: int) -> tuple[int, int]:
    """Largest even size within ``max_width`` x ``max_height`` [px] keeping the aspect; never upscaled."""
    scale = min(max_width / width, max_height / height, 1.0)
    return max(2, round(width * scale) // 2 * 2), max(2, round(height * scale) // 2 * 2)


class _JpegEncoder:
    """PyAV's MJPEG encoder at one output size; not thread-safe."""

    def __init__(self, width: int, height: int, quality: int) -> None:
        import av

        context: Any = av.CodecContext.create("mjpeg", "w")
        context.width = width
        context.height = height
        context.pix_fmt = "yuvj420p"  # full-range YUV, as JPEG viewers expect
        context.time_base = Fraction(1, 1000)
        # qscale bounds: 2 (best) .. 31 (smallest); fixing both gives constant quality.
        context.options = {"qmin": str(quality), "qmax": str(quality)}
        context.open()
        self._av = av
        self._context = context
        self._pts = 0
        self.width = width
        self.height = height

    def encode(self, image: npt.NDArray[np.uint8]) -> bytes:
        frame = self._av.VideoFrame.from_ndarray(image, format="rgb24").reformat(
            width=self.width, height=self.height, format="yuvj420p", interpolation="AREA"
        )
        frame.pts = self._pts  # the encoder refuses repeated pts
        self._pts += 1
        return b"".join(bytes(packet) for packet in self._context.encode(frame))


def encode_jpeg(image: npt.NDArray[np.uint8], *, width: int, height: int, quality: int = 8) -> bytes:
    """Downsample an RGB image, uint8 of shape (H, W, 3), to ``width`` x ``height`` [px] and encode a JPEG.

    ``quality`` is the MJPEG qscale, 2 (best) to 31 (smallest).
    """
    return _JpegEncoder(width, height, quality).encode(np.ascontiguousarray(image))


class PreviewPublisher:
    """Publishes low-rate downsampled JPEGs of a camera on ``telerig/v1/<rig>/<camera>/preview``.

    :meth:`offer` is called with every frame (from the camera's ``on_frame``) and never blocks:
    frames are taken on an absolute grid of ``1 / rate_hz`` in capture time, copied, and handed
    to a worker thread through a one-frame slot; a wanted frame that finds the slot still full
    (the worker is behind) is dropped and counted. The worker downsamples (aspect kept, within
    ``max_width`` x ``max_height``) and JPEG-encodes with PyAV's MJPEG encoder (~2 ms at
    320x240), then publishes the bytes at QoS 0, not retained: a preview is disposable, and the
    recorder does not record this stream.

    Args:
        bus: Bus to publish on.
        rig: Rig name.
        camera: Camera id (the topic's node).
        max_width: Largest preview width [px].
        max_height: Largest preview height [px].
        rate_hz: Previews per second (> 0).
        quality: MJPEG qscale, 2 (best) to 31 (smallest).

    The worker starts with the first wanted frame; :meth:`close` (idempotent) stops it.
    """

    def __init__(
        self,
        bus: Bus,
        rig: str,
        camera: str,
        *,
        max_width: int = 320,
        max_height: int = 240,
        rate_hz: float = 2.0,
        quality: int = 8,
    ) -> None:
        if max_width < 2 or max_height < 2:
            raise ValueError(f"preview size must be at least 2x2 px, got {max_width}x{max_height}")
        if not rate_hz > 0:
            raise ValueError(f"rate_hz must be positive, got {rate_hz}")
        if not 2 <= quality <= 31:
            raise ValueError(f"quality must be an MJPEG qscale in 2..31, got {quality}")
        self.topic = str(Topic(rig, camera, PREVIEW_STREAM))
        self.max_width = max_width
        self.max_height = max_height
        self.rate_hz = rate_hz
        self.quality = quality
        self._bus = bus
        self._period_ns = round(1e9 / rate_hz)
        self._next_ns: int | None = None
        self._cond = threading.Condition()
        self._slot: tuple[npt.NDArray[np.uint8], int] | None = None
        self._closed = False
        self._thread: threading.Thread | None = None
        self._offered = 0
        self._published = 0
        self._rate_skipped = 0
        self._dropped = 0
        self._errors = 0
        self._encode_ns = 0
        self._last_capture_ns = 0

    @property
    def stats(self) -> PreviewStats:
        """Counters since construction."""
        mean = self._encode_ns / self._published / 1e6 if self._published else 0.0
        return PreviewStats(
            self._offered,
            self._published,
            self._rate_skipped,
            self._dropped,
            self._errors,
            mean,
            self._last_capture_ns,
        )

    def offer(self, image: npt.NDArray[np.uint8], capture_ns: int) -> bool:
        """Consider one frame for a preview; never blocks.

        Args:
            image: RGB image, uint8, shape (H, W, 3). Copied when taken.
            capture_ns: Its capture time, common clock [ns]; paces the previews.

        Returns:
            Whether the frame was taken for a preview (False: not due yet, busy, or closed).
        """
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise ValueError(
                f"preview image must be uint8 of shape (H, W, 3), got {image.dtype} {image.shape}"
            )
        with self._cond:
            self._offered += 1
            if self._closed:
                return False
            if self._next_ns is not None and capture_ns < self._next_ns:
                self._rate_skipped += 1
                return False
            # Next due on the grid; after a long pause restart the grid rather than catch up.
            due = capture_ns if self._next_ns is None else self._next_ns
            self._next_ns = max(due + self._period_ns, capture_ns)
            if self._slot is not None:
                self._dropped += 1
                return False
            self._slot = (np.array(image, dtype=np.uint8, copy=True), capture_ns)
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name=f"preview-{self.topic}", daemon=True)
                self._thread.start()
            self._cond.notify()
            return True

    def close(self) -> None:
        """Publish the preview in progress, if any, and stop the worker. Idempotent."""
        with self._cond:
            self._closed = True
            self._cond.notify()
            thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join()

    def __enter__(self) -> PreviewPublisher:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def _run(self) -> None:
        priority.enter("work")  # below the control loop
        encoders: dict[tuple[int, int], _JpegEncoder] = {}
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._slot is not None or self._closed)
                if self._slot is None:
                    return
                image, capture_ns = self._slot
            try:
                t0 = time.perf_counter_ns()
                size = preview_size(image.shape[1], image.shape[0], self.max_width, self.max_height)
                encoder = encoders.get(size)
                if encoder is None:
                    encoder = encoders[size] = _JpegEncoder(*size, self.quality)
                jpeg = stamp_jpeg(encoder.encode(image), capture_ns, now_ns())
                elapsed = time.perf_counter_ns() - t0
                self._bus.publish(self.topic, jpeg, qos=0, retain=False)
                self._encode_ns += elapsed
                self._published += 1
                self._last_capture_ns = capture_ns
            except Exception as exc:
                self._errors += 1
                if self._errors == 1:
                    _log.error("%s: preview failed (later failures are only counted): %s", self.topic, exc)
            finally:
                # Freed only now, so a frame offered while this one is encoded counts as dropped.
                with self._cond:
                    self._slot = None
