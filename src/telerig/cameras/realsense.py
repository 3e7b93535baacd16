"""Intel RealSense depth camera: colour via ``on_frame``, depth via ``on_depth`` (needs pyrealsense2)."""

from __future__ import annotations

import importlib
import logging
import time
from collections.abc import Callable
from types import TracebackType
from typing import Any

import numpy as np
import numpy.typing as npt

from telerig.cameras.capture import CaptureClock, FrameCallback, _Capture, _clock_pair
from telerig.errors import DependencyError, DeviceError
from telerig.ir.types import CameraFrame, Stamp, now_ns

__all__ = ["DepthCallback", "RealSenseCamera", "list_realsense_devices"]

_log = logging.getLogger("telerig.cameras.realsense")

#: Receives each depth image, uint16 of shape (height, width) in device units (multiply by
#: :attr:`RealSenseCamera.depth_scale` for [m]; 0 means no depth), and its metadata.
DepthCallback = Callable[[npt.NDArray[np.uint16], CameraFrame], None]

_WAIT_MS = 1000
_NS_PER_MS = 1_000_000


def _rs() -> Any:
    try:
        return importlib.import_module("pyrealsense2")
    except ImportError:
        raise DependencyError(
            "RealSense cameras need pyrealsense2: pip install pyrealsense2 (x86_64/aarch64 Linux, Windows)"
        ) from None


def list_realsense_devices() -> list[tuple[str, str]]:
    """``(serial number, product name)`` of each RealSense device connected.

    Raises:
        DependencyError: pyrealsense2 is not installed.
    """
    rs = _rs()
    return [
        (d.get_info(rs.camera_info.serial_number), d.get_info(rs.camera_info.name))
        for d in rs.context().query_devices()
    ]


class RealSenseCamera(_Capture):
    """An Intel RealSense camera (D4xx): RGB colour frames, and depth frames aligned to them.

    Capture times come from the device's frame timestamps: in the ``global_time`` domain
    (the default on D4xx: hardware stamps mapped to the host clock by librealsense) they are
    already host time; in the ``hardware_clock`` domain a :class:`CaptureClock` estimates the
    offset from arrival times. ``device_ns`` keeps the device's timestamp [ns].

    Args:
        name: Camera id; the frames' ``camera_id`` and stamp ``source_id``.
        on_frame: Called on the capture thread with each RGB image, uint8, shape (height,
            width, 3), and its :class:`CameraFrame`. Must not block.
        on_depth: Called with each depth image (see :data:`DepthCallback`) aligned to the colour
            image, same index and stamp as its colour frame; None disables the depth stream.
        serial: Serial number of the device to open; the first one found when None.
        width: Image width [px] (a mode the device has, e.g. 640, 848, 1280).
        height: Image height [px].
        fps: Frame rate [Hz] (6, 15, 30, 60 or 90 depending on the mode).
    """

    def __init__(
        self,
        name: str,
        *,
        on_frame: FrameCallback,
        on_depth: DepthCallback | None = None,
        serial: str | None = None,
        width: int = 640,
        height: int = 480,
        fps: float = 30.0,
    ) -> None:
        super().__init__(name, on_frame)
        if width <= 0 or height <= 0 or not fps > 0:
            raise ValueError(f"camera {name!r}: width, height and fps must be positive")
        self.serial = serial
        self.width = width
        self.height = height
        self.fps = fps
        self.clock = CaptureClock()
        #: Depth unit [m] (e.g. 0.001); set by :meth:`start`.
        self.depth_scale = 0.0
        self._on_depth = on_depth
        self._pipeline: Any = None

    def start(self) -> None:
        """Open the device, start its streams and start capturing. Idempotent.

        Raises:
            DependencyError: pyrealsense2 is not installed.
            DeviceError: No (or not the requested) device is connected, or it refused the mode.
            RuntimeError: The camera was stopped (cameras are not restarted).
        """
        if self._thread is not None:
            if self._stop_event.is_set():
                raise RuntimeError(f"camera {self.name!r} was stopped; create a new RealSenseCamera")
            return
        rs = _rs()
        devices = list_realsense_devices()
        serials = [serial for serial, _ in devices]
        if not devices or (self.serial is not None and self.serial not in serials):
            wanted = "a RealSense device" if self.serial is None else f"RealSense {self.serial}"
            present = ", ".join(f"{s} ({n})" for s, n in devices) or "none (check the USB 3 cable)"
            raise DeviceError(f"camera {self.name!r}: {wanted} is not connected. Available: {present}")
        config = rs.config()
        if self.serial is not None:
            config.enable_device(self.serial)
        rate = round(self.fps)
        config.enable_stream(rs.stream.color, self.width, self.height, rs.format.rgb8, rate)
        if self._on_depth is not None:
            config.enable_stream(rs.stream.depth, self.width, self.height, rs.format.z16, rate)
        pipeline = rs.pipeline()
        try:
            profile = pipeline.start(config)
        except RuntimeError as exc:
            raise DeviceError(
                f"camera {self.name!r}: cannot start {self.width}x{self.height}@{rate}: {exc}. "
                "List the modes with: rs-enumerate-devices"
            ) from None
        if self._on_depth is not None:
            self.depth_scale = float(profile.get_device().first_depth_sensor().get_depth_scale())
        self._pipeline = pipeline
        self._launch(self._capture_loop)

    def __enter__(self) -> RealSenseCamera:
        self.start()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()

    def _capture_loop(self) -> None:
        rs = _rs()
        pipeline = self._pipeline
        align = rs.align(rs.stream.color) if self._on_depth is not None else None
        period_ns = round(1e9 / self.fps)
        last_number: int | None = None
        try:
            while not self._stop_event.is_set():
                frames = pipeline.wait_for_frames(_WAIT_MS)
                arrival_ns, monotonic_ns = _clock_pair()
                t0 = time.perf_counter_ns()
                if align is not None:
                    frames = align.process(frames)
                color = frames.get_color_frame()
                if not color:
                    continue
                image = np.array(np.asanyarray(color.get_data()), dtype=np.uint8, copy=True)
                depth_frame = frames.get_depth_frame() if self._on_depth is not None else None
                depth = (
                    np.array(np.asanyarray(depth_frame.get_data()), dtype=np.uint16, copy=True)
                    if depth_frame
                    else None
                )
                self._decode_ns += time.perf_counter_ns() - t0
                device_ns = round(color.get_timestamp() * _NS_PER_MS)
                capture_ns = self.clock.map(device_ns, arrival_ns, monotonic_ns)
                number = int(color.get_frame_number())
                if last_number is not None:
                    self._skipped += max(0, number - last_number - 1)
                last_number = number
                if now_ns() - capture_ns > period_ns:
                    self._late += 1
                delivery = self._delivery
                index = delivery.index
                self._deliver(image, device_ns, capture_ns)
                if depth is not None and self._on_depth is not None:
                    stamp = Stamp(f"{self.name}/depth", delivery.seq - 1, device_ns, capture_ns)
                    meta = CameraFrame(stamp, f"{self.name}/depth", index, depth.shape[1], depth.shape[0])
                    try:
                        self._on_depth(depth, meta)
                    except Exception:
                        delivery.callback_errors += 1
                        _log.exception("%s: on_depth failed", self.name)
        finally:
            pipeline.stop()
