"""Capture cameras besides MuJoCo: USB/UVC webcams through PyAV's v4l2 input, and video-file replay.

Both hand ``(RGB uint8 image of shape (H, W, 3), CameraFrame)`` to an ``on_frame`` callback of the
same shape as :class:`telerig.cameras.mujoco_camera.MujocoCamera`'s, from their own thread, and
share the small :class:`Camera` protocol (``start`` / ``stop`` / ``stats``).

Depth cameras (Intel RealSense) live in :mod:`telerig.cameras.realsense`, behind the optional
``pyrealsense2`` dependency (``pip install pyrealsense2``): colour frames go through the same
``on_frame`` callback, depth frames through ``on_depth``.
"""

from __future__ import annotations

import glob
import logging
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any, Literal, Protocol, runtime_checkable

import numpy as np
import numpy.typing as npt

from telerig.cameras.delivery import FrameCallback, FrameDelivery
from telerig.errors import DeviceError
from telerig.ir.clock import ClockOffsetEstimator
from telerig.ir.types import now_ns

if TYPE_CHECKING:
    from telerig.cameras.mujoco_camera import MujocoCamera

__all__ = [
    "Camera",
    "CameraCounters",
    "CaptureClock",
    "CaptureStats",
    "FrameCallback",
    "V4l2Camera",
    "VideoFileCamera",
    "list_video_devices",
    "v4l2_options",
]

_log = logging.getLogger("telerig.cameras.capture")


#: A kernel timestamp further than this from a clock's current reading is not in that clock [ns].
_CLOCK_MATCH_NS = 10_000_000_000
#: How long :meth:`stop` waits for the capture thread (a v4l2 read returns within a frame) [s].
_STOP_TIMEOUT_S = 5.0
_NS = 1_000_000_000


class CameraCounters(Protocol):
    """The counters every camera's ``stats`` has (read-only)."""

    @property
    def frames(self) -> int:
        """Frames handed to ``on_frame``."""
        ...

    @property
    def skipped(self) -> int:
        """Frames lost before ``on_frame`` (not delivered by the device, or dropped to keep up)."""
        ...

    @property
    def late(self) -> int:
        """Frames captured or delivered late (each camera says by how much)."""
        ...

    @property
    def callback_errors(self) -> int:
        """``on_frame`` calls that raised."""
        ...


@runtime_checkable
class Camera(Protocol):
    """A frame source: :meth:`start` begins calling ``on_frame`` from its own thread, :meth:`stop` ends it."""

    name: str

    def start(self) -> None:
        """Open the source and start capturing; raises a one-line error when it cannot. Idempotent."""
        ...

    def stop(self) -> None:
        """Stop capturing and release the source. Idempotent."""
        ...

    @property
    def stats(self) -> CameraCounters:
        """Counters since :meth:`start`."""
        ...


@dataclass(frozen=True, slots=True)
class CaptureStats:
    """Counters of a capture camera since :meth:`V4l2Camera.start` / :meth:`VideoFileCamera.start`.

    Attributes:
        frames: Frames handed to ``on_frame``.
        late: Frames that reached ``on_frame`` more than one frame period after capture.
        skipped: Frames lost before ``on_frame``: gaps in the device's timestamps (the driver
            dropped them) or, for file replay, frames dropped to keep to the schedule.
        callback_errors: ``on_frame`` calls that raised.
        mean_decode_ms: Mean time to decode a frame and convert it to RGB [ms].
    """

    frames: int
    late: int
    skipped: int
    callback_errors: int
    mean_decode_ms: float


class CaptureClock:
    """Maps a device's frame timestamps onto the common clock (:func:`telerig.ir.types.now_ns`).

    V4L2 stamps each buffer in the kernel when the frame is captured, usually in
    ``CLOCK_MONOTONIC`` (UVC, ``V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC``), on some drivers in
    ``CLOCK_REALTIME``. The clock is recognised from the first frame: a monotonic stamp is
    moved by ``now_ns() - time.monotonic_ns()`` read at the frame's arrival (exact up to the
    two clock reads, ~100 ns); a realtime stamp is kept; any other clock (a device's own
    counter) goes through a :class:`~telerig.ir.clock.ClockOffsetEstimator` fed with the
    arrival times. A mapped time is never later than the frame's arrival.

    Units: every time is integer nanoseconds.
    """

    def __init__(self, window_ns: int = 2 * _NS) -> None:
        self.mode: Literal["monotonic", "realtime", "estimated"] | None = None
        self._estimator = ClockOffsetEstimator(window_ns, reset_ns=_NS)

    def map(self, device_ns: int, arrival_ns: int, monotonic_ns: int) -> int:
        """Capture time in the common clock [ns] of a frame stamped ``device_ns`` by the device.

        Args:
            device_ns: The frame's timestamp in the device's clock [ns].
            arrival_ns: ``now_ns()`` when the frame reached this process [ns].
            monotonic_ns: ``time.monotonic_ns()`` read right beside ``arrival_ns`` [ns].
        """
        if self.mode is None:
            if abs(monotonic_ns - device_ns) < _CLOCK_MATCH_NS:
                self.mode = "monotonic"
            elif abs(arrival_ns - device_ns) < _CLOCK_MATCH_NS:
                self.mode = "realtime"
            else:
                self.mode = "estimated"
        if self.mode == "monotonic":
            capture = device_ns + (arrival_ns - monotonic_ns)
        elif self.mode == "realtime":
            capture = device_ns
        else:
            capture = device_ns + self._estimator.update(device_ns, arrival_ns)
        return min(capture, arrival_ns)


def _clock_pair() -> tuple[int, int]:
    """``(now_ns(), time.monotonic_ns())`` read as close together as possible."""
    best: tuple[int, int, int] | None = None
    for _ in range(3):
        m0 = time.monotonic_ns()
        wall = now_ns()
        m1 = time.monotonic_ns()
        if best is None or m1 - m0 < best[0]:
            best = (m1 - m0, wall, (m0 + m1) // 2)
    assert best is not None
    return best[1], best[2]


def list_video_devices() -> list[str]:
    """The V4L2 device nodes present, e.g. ``["/dev/video0", "/dev/video1"]``, sorted by number."""

    def number(path: str) -> int:
        digits = path.removeprefix("/dev/video")
        return int(digits) if digits.isdigit() else 1 << 30

    return sorted(glob.glob("/dev/video*"), key=number)


def v4l2_options(width: int, height: int, fps: float, input_format: str | None = "mjpeg") -> dict[str, str]:
    """FFmpeg ``v4l2`` demuxer options for a capture mode.

    Args:
        width: Image width [px].
        height: Image height [px].
        fps: Frame rate [Hz].
        input_format: Pixel format asked of the device (``"mjpeg"``, ``"yuyv422"``, ``"h264"``);
            None lets the driver choose.

    Returns:
        Options for ``av.open(device, format="v4l2", options=...)``; ``ts`` is ``default`` so that
        frame pts are the kernel's capture timestamps [µs], unconverted.
    """
    if width <= 0 or height <= 0:
        raise ValueError(f"width and height must be positive, got {width}x{height}")
    if not fps > 0:
        raise ValueError(f"fps must be positive, got {fps}")
    rate = Fraction(fps).limit_denominator(1001)
    options = {
        "video_size": f"{width}x{height}",
        "framerate": str(rate.numerator) if rate.denominator == 1 else f"{rate.numerator}/{rate.denominator}",
        "ts": "default",
    }
    if input_format is not None:
        options["input_format"] = input_format
    return options


def _frame_ns(frame: Any) -> int | None:
    """A decoded frame's pts in its time base, as [ns]; None without a pts."""
    if frame.pts is None or frame.time_base is None:
        return None
    return round(Fraction(frame.pts) * Fraction(frame.time_base) * _NS)


def _to_rgb(frame: Any, width: int, height: int) -> npt.NDArray[np.uint8]:
    """A decoded ``av.VideoFrame`` as RGB uint8 of shape (height, width, 3), resized if needed."""
    if frame.width == width and frame.height == height and frame.format.name == "rgb24":
        image: npt.NDArray[np.uint8] = frame.to_ndarray()
    else:
        image = frame.reformat(width=width, height=height, format="rgb24").to_ndarray()
    return image


class _Capture:
    """Thread, counters and ``on_frame`` delivery shared by the capture cameras."""

    def __init__(self, name: str, on_frame: FrameCallback) -> None:
        self.name = name
        self._delivery = FrameDelivery(name, on_frame)
        self._stop_event = threading.Event()
        self._thread: threading.Thread | None = None
        self._late = 0
        self._skipped = 0
        self._decode_ns = 0

    @property
    def stats(self) -> CaptureStats:
        """Counters since :meth:`start`."""
        d = self._delivery
        mean = self._decode_ns / d.frames / 1e6 if d.frames else 0.0
        return CaptureStats(d.frames, self._late, self._skipped, d.callback_errors, mean)

    def stop(self) -> None:
        """Stop capturing and close the source; waits for the frame in progress. Idempotent.

        Called from ``on_frame``, it returns at once and the capture thread ends after that frame.
        """
        self._stop_event.set()
        thread = self._thread
        if thread is None or thread is threading.current_thread():
            return
        thread.join(_STOP_TIMEOUT_S)
        if thread.is_alive():
            _log.warning("%s: capture thread did not stop within %.0f s", self.name, _STOP_TIMEOUT_S)

    def _launch(self, target: Callable[[], None]) -> None:
        self._thread = threading.Thread(target=self._guarded, args=(target,), name=f"camera-{self.name}")
        self._thread.daemon = True
        self._thread.start()

    def _guarded(self, target: Callable[[], None]) -> None:
        try:
            target()
        except Exception as exc:
            if not self._stop_event.is_set():
                _log.error("%s: capture stopped: %s", self.name, exc)
        finally:
            self._stop_event.set()

    def _deliver(self, image: npt.NDArray[np.uint8], device_ns: int, capture_ns: int) -> None:
        self._delivery.deliver(image, device_ns=device_ns, capture_ns=capture_ns)


class V4l2Camera(_Capture):
    """A USB/UVC webcam (any V4L2 device) read through PyAV's ``v4l2`` input on a capture thread.

    Each frame's capture time is the kernel's buffer timestamp mapped onto the common clock by
    a :class:`CaptureClock` (``device_ns`` keeps the raw kernel stamp), so USB transfer and
    decoding delay do not shift it. MJPEG frames are decoded and converted to RGB on the
    capture thread (PyAV releases the GIL while doing so). Frames the driver dropped because
    this thread fell behind show up as gaps in the kernel timestamps and are counted in
    ``stats.skipped``.

    Args:
        name: Camera id from the rig file; the frames' ``camera_id`` and stamp ``source_id``.
        on_frame: Called on the capture thread with each RGB image, uint8, shape (height,
            width, 3) (a fresh array it may keep) and its :class:`CameraFrame`. Must not block.
        device: V4L2 device node, e.g. ``/dev/video0`` (``/dev/v4l/by-id/...`` links are stable
            across reboots).
        width: Image width asked of the device [px]; frames of another size are resized.
        height: Image height asked of the device [px].
        fps: Frame rate asked of the device [Hz].
        input_format: Pixel format asked of the device (``"mjpeg"`` needs the least USB
            bandwidth), or None for the driver's choice.
    """

    def __init__(
        self,
        name: str,
        *,
        on_frame: FrameCallback,
        device: str = "/dev/video0",
        width: int = 640,
        height: int = 480,
        fps: float = 30.0,
        input_format: str | None = "mjpeg",
    ) -> None:
        super().__init__(name, on_frame)
        self.device = device
        self.width = width
        self.height = height
        self.fps = fps
        self.options = v4l2_options(width, height, fps, input_format)
        self.clock = CaptureClock()
        self._container: Any = None

    def start(self) -> None:
        """Open the device and start capturing. Idempotent.

        Raises:
            DeviceError: The device does not exist (the message lists the ``/dev/video*``
                present) or refused the mode.
            RuntimeError: The camera was stopped (cameras are not restarted).
        """
        if self._thread is not None:
            if self._stop_event.is_set():
                raise RuntimeError(f"camera {self.name!r} was stopped; create a new V4l2Camera")
            return
        if not Path(self.device).exists():
            present = ", ".join(list_video_devices()) or "none (is the camera plugged in?)"
            raise DeviceError(f"camera {self.name!r}: {self.device} does not exist. Available: {present}")
        import av

        try:
            self._container = av.open(self.device, format="v4l2", options=dict(self.options))
        except av.FFmpegError as exc:
            mode = f"{self.options['video_size']}@{self.options['framerate']}"
            fmt = self.options.get("input_format", "any format")
            raise DeviceError(
                f"camera {self.name!r}: cannot open {self.device} at {mode} ({fmt}): {exc}. "
                f"List its modes with: v4l2-ctl -d {self.device} --list-formats-ext"
            ) from None
        self._launch(self._capture_loop)

    def __enter__(self) -> V4l2Camera:
        self.start()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()

    def _capture_loop(self) -> None:
        container = self._container
        period_ns = round(_NS / self.fps)
        last_device_ns: int | None = None
        try:
            stream = container.streams.video[0]
            for packet in container.demux(stream):
                if self._stop_event.is_set():
                    return
                arrival_ns, monotonic_ns = _clock_pair()
                t0 = time.perf_counter_ns()
                frames = packet.decode()
                for frame in frames:
                    image = _to_rgb(frame, self.width, self.height)
                    self._decode_ns += time.perf_counter_ns() - t0
                    device_ns = _frame_ns(frame)
                    if device_ns is None:  # no kernel stamp: arrival is the best there is
                        device_ns = monotonic_ns
                    capture_ns = self.clock.map(device_ns, arrival_ns, monotonic_ns)
                    if last_device_ns is not None:
                        self._skipped += max(0, round((device_ns - last_device_ns) / period_ns) - 1)
                    last_device_ns = device_ns
                    if now_ns() - capture_ns > period_ns:
                        self._late += 1
                    self._deliver(image, device_ns, capture_ns)
                    t0 = time.perf_counter_ns()
        finally:
            container.close()


class VideoFileCamera(_Capture):
    """Replays a video file (anything PyAV reads) as a camera, at the file's own timing.

    Frame ``i`` is delivered at ``start + (pts_i - pts_0) / speed`` on an absolute schedule, so
    timing does not drift with decoding time. Its stamp has ``capture_ns`` = the common-clock
    time of delivery (the moment the replayed frame is "captured") and ``device_ns`` = its media
    time since the first frame [ns], growing across loops. A frame more than one frame period
    behind the schedule is dropped and counted in ``stats.skipped`` when ``drop_late`` (as a
    camera would), never delivered in a burst.

    Args:
        name: Camera id; the frames' ``camera_id`` and stamp ``source_id``.
        path: Video file.
        on_frame: As for :class:`V4l2Camera`.
        loop: Start over at the end of the file (media time keeps increasing).
        width: Output width [px]; the file's when None.
        height: Output height [px]; the file's when None.
        speed: Replay speed factor (> 0); 1 is real time.
        drop_late: Drop frames that fell more than a period behind; False delivers every frame.
    """

    def __init__(
        self,
        name: str,
        path: Path | str,
        *,
        on_frame: FrameCallback,
        loop: bool = False,
        width: int | None = None,
        height: int | None = None,
        speed: float = 1.0,
        drop_late: bool = True,
    ) -> None:
        super().__init__(name, on_frame)
        if not speed > 0:
            raise ValueError(f"camera {name!r}: speed must be positive, got {speed}")
        if (width is None) != (height is None) or (width is not None and width <= 0) or (height or 1) <= 0:
            raise ValueError(f"camera {name!r}: give both width and height (positive) or neither")
        self.path = Path(path)
        self.loop = loop
        self.speed = speed
        self.drop_late = drop_late
        self.width = width or 0
        self.height = height or 0
        self.fps = 0.0
        self._done = threading.Event()

    def start(self) -> None:
        """Open the file, read its size and rate, and start replaying. Idempotent.

        Raises:
            DeviceError: The file does not exist or has no video stream PyAV can decode.
            RuntimeError: The camera was stopped (cameras are not restarted).
        """
        if self._thread is not None:
            if self._stop_event.is_set():
                raise RuntimeError(f"camera {self.name!r} was stopped; create a new VideoFileCamera")
            return
        if not self.path.is_file():
            raise DeviceError(f"camera {self.name!r}: video file {self.path} does not exist")
        container = self._open()
        try:
            stream = container.streams.video[0]
            if not self.width:
                self.width, self.height = stream.codec_context.width, stream.codec_context.height
            rate = stream.average_rate or stream.guessed_rate or 30
            self.fps = float(rate)
        finally:
            container.close()
        self._launch(self._replay)

    def wait(self, timeout: float | None = None) -> bool:
        """Wait until the replay ends (the file's last frame, or :meth:`stop`); whether it did."""
        return self._done.wait(timeout)

    def __enter__(self) -> VideoFileCamera:
        self.start()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()

    def _open(self) -> Any:
        import av

        try:
            container = av.open(str(self.path))
        except av.FFmpegError as exc:
            raise DeviceError(f"camera {self.name!r}: PyAV cannot read {self.path}: {exc}") from None
        if not container.streams.video:
            container.close()
            raise DeviceError(f"camera {self.name!r}: {self.path} has no video stream")
        return container

    def _decoded(self) -> Iterator[tuple[int | None, Any]]:
        container = self._open()
        try:
            stream = container.streams.video[0]
            stream.thread_type = "AUTO"
            for frame in container.decode(stream):
                yield _frame_ns(frame), frame
        finally:
            container.close()

    def _replay(self) -> None:
        try:
            self._replay_loop()
        finally:
            self._done.set()

    def _replay_loop(self) -> None:
        period_ns = round(_NS / self.fps)
        origin = time.monotonic_ns()
        base_ns = 0  # media time at which the current pass starts
        while not self._stop_event.is_set():
            first_ns: int | None = None
            media_ns = base_ns
            for index, (file_ns, frame) in enumerate(self._decoded()):
                # A file without timestamps: its nominal rate is all there is.
                pts_ns = index * period_ns if file_ns is None else file_ns
                if first_ns is None:
                    first_ns = pts_ns
                media_ns = base_ns + pts_ns - first_ns
                due = origin + round(media_ns / self.speed)
                wait_ns = due - time.monotonic_ns()
                if wait_ns > 0 and self._stop_event.wait(wait_ns / 1e9):
                    return
                if self._stop_event.is_set():
                    return
                if self.drop_late and time.monotonic_ns() - due > period_ns:
                    self._skipped += 1
                    continue
                t0 = time.perf_counter_ns()
                image = _to_rgb(frame, self.width, self.height)
                self._decode_ns += time.perf_counter_ns() - t0
                self._deliver(image, media_ns, now_ns())
            if not self.loop or first_ns is None:
                return
            base_ns = media_ns + period_ns


if TYPE_CHECKING:  # the protocol is met by every camera; mypy checks it here

    def _is_camera(a: V4l2Camera, b: VideoFileCamera, c: MujocoCamera) -> tuple[Camera, Camera, Camera]:
        return a, b, c
