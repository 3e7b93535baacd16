"""Capture cameras: v4l2 argument building and errors, kernel-clock mapping, video-file replay."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest

from telerig.cameras import capture
from telerig.cameras.capture import (
    Camera,
    CaptureClock,
    V4l2Camera,
    VideoFileCamera,
    list_video_devices,
    v4l2_options,
)
from telerig.cameras.encoder import VideoEncoder
from telerig.errors import DeviceError
from telerig.ir.types import CameraFrame

W, H, FPS = 64, 48, 30.0
T0_NS = 1_700_000_000_000_000_000
SECOND = 1_000_000_000


class _Sink:
    """An ``on_frame`` that keeps every frame; optionally refuses some or stops the camera."""

    def __init__(self, refuse: set[int] | None = None, stop_after: int | None = None) -> None:
        self.images: list[npt.NDArray[np.uint8]] = []
        self.metas: list[CameraFrame] = []
        self.refuse = refuse or set()
        self.stop_after = stop_after
        self.camera: VideoFileCamera | None = None

    def __call__(self, image: npt.NDArray[np.uint8], meta: CameraFrame) -> bool:
        self.images.append(image)
        self.metas.append(meta)
        if self.stop_after is not None and len(self.metas) >= self.stop_after and self.camera is not None:
            self.camera.stop()
        return len(self.metas) - 1 not in self.refuse


def _write_video(path: Path, levels: list[int], times_ns: list[int]) -> Path:
    """An h264 MP4 of uniform grey frames (``levels``, 0-255) captured at ``times_ns``."""
    with VideoEncoder(path, width=W, height=H, fps=FPS, queue_size=len(levels)) as enc:
        for level, t in zip(levels, times_ns, strict=True):
            assert enc.submit(np.full((H, W, 3), level, dtype=np.uint8), t)
    return path


def _uneven_times(n: int) -> list[int]:
    """~30 Hz capture times [ns] with a 0-4 ms pattern of jitter, so the pts are not index / fps."""
    return [T0_NS + round(i * SECOND / FPS) + (i % 3) * 2_000_000 for i in range(n)]


@pytest.fixture(scope="module")
def video(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[int], list[int]]:
    levels = [20 * i for i in range(12)]
    times = _uneven_times(len(levels))
    path = _write_video(tmp_path_factory.mktemp("video") / "grey.mp4", levels, times)
    return path, levels, times


# --- v4l2 ---------------------------------------------------------------------------------------


def test_v4l2_options_ask_for_mode_and_raw_kernel_timestamps() -> None:
    assert v4l2_options(640, 480, 30.0) == {
        "video_size": "640x480",
        "framerate": "30",
        "ts": "default",
        "input_format": "mjpeg",
    }


def test_v4l2_options_write_ntsc_rate_as_fraction_and_omit_format_when_none() -> None:
    options = v4l2_options(1280, 720, 30000 / 1001, input_format=None)
    assert options["framerate"] == "30000/1001"
    assert "input_format" not in options


def test_v4l2_options_reject_nonpositive_rate() -> None:
    with pytest.raises(ValueError, match="fps must be positive"):
        v4l2_options(640, 480, 0.0)


def test_missing_v4l2_device_error_lists_present_devices(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(capture, "list_video_devices", lambda: ["/dev/video0", "/dev/video2"])
    camera = V4l2Camera("wrist", on_frame=_Sink(), device="/dev/video-telerig-missing")
    with pytest.raises(DeviceError, match=r"does not exist\. Available: /dev/video0, /dev/video2$"):
        camera.start()


def test_missing_v4l2_device_error_says_none_when_no_device_present(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(capture, "list_video_devices", lambda: [])
    with pytest.raises(DeviceError, match="Available: none"):
        V4l2Camera("wrist", on_frame=_Sink(), device="/dev/video-telerig-missing").start()


def test_v4l2_open_failure_is_one_line_device_error() -> None:
    # /dev/null exists but is no V4L2 device: PyAV's v4l2 input refuses it.
    with pytest.raises(DeviceError, match=r"cannot open /dev/null at 640x480@30 \(mjpeg\)") as info:
        V4l2Camera("wrist", on_frame=_Sink(), device="/dev/null").start()
    assert "\n" not in str(info.value)


def test_list_video_devices_sorts_by_number(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(capture.glob, "glob", lambda _: ["/dev/video10", "/dev/video2", "/dev/video0"])
    assert list_video_devices() == ["/dev/video0", "/dev/video2", "/dev/video10"]


# --- clock mapping ------------------------------------------------------------------------------


def test_capture_clock_moves_monotonic_stamps_by_the_clock_difference() -> None:
    clock = CaptureClock()
    mono, wall = 5_000 * SECOND, T0_NS
    captured = clock.map(mono - 20_000_000, arrival_ns=wall, monotonic_ns=mono)
    assert clock.mode == "monotonic"
    assert captured == wall - 20_000_000


def test_capture_clock_keeps_realtime_stamps() -> None:
    clock = CaptureClock()
    assert clock.map(T0_NS - 5_000_000, arrival_ns=T0_NS, monotonic_ns=5_000 * SECOND) == T0_NS - 5_000_000
    assert clock.mode == "realtime"


def test_capture_clock_estimates_offset_of_a_foreign_clock_from_fastest_arrival() -> None:
    clock = CaptureClock()
    mono = 5_000 * SECOND
    # Device counter starting at 0; arrival delays 3, 1, 2 ms: the 1 ms one bounds the offset.
    for i, delay in enumerate((3_000_000, 1_000_000, 2_000_000)):
        device = i * 33_000_000
        captured = clock.map(device, arrival_ns=T0_NS + device + delay, monotonic_ns=mono)
    assert clock.mode == "estimated"
    assert captured == T0_NS + 2 * 33_000_000 + 1_000_000


def test_capture_clock_never_puts_capture_after_arrival() -> None:
    clock = CaptureClock()
    mono = 5_000 * SECOND
    assert clock.map(mono + 1_000_000, arrival_ns=T0_NS, monotonic_ns=mono) == T0_NS


# --- video file replay --------------------------------------------------------------------------


def test_replay_delivers_every_frame_in_order_as_rgb(video: tuple[Path, list[int], list[int]]) -> None:
    path, levels, _ = video
    sink = _Sink()
    camera = VideoFileCamera("replay", path, on_frame=sink, speed=4.0, drop_late=False)
    camera.start()
    assert camera.wait(10.0)
    camera.stop()
    assert len(sink.images) == len(levels)
    assert all(image.shape == (H, W, 3) and image.dtype == np.uint8 for image in sink.images)
    means = [float(image.mean()) for image in sink.images]
    assert means == pytest.approx(levels, abs=4)  # h264 + yuv420p round trip of flat grey


def test_replay_device_time_is_the_files_pts_not_index_over_fps(
    video: tuple[Path, list[int], list[int]],
) -> None:
    path, _, times = video
    sink = _Sink()
    with VideoFileCamera("replay", path, on_frame=sink, speed=4.0, drop_late=False) as camera:
        assert camera.wait(10.0)
    expected = [(t - times[0]) // 1000 * 1000 for t in times]  # the MP4 keeps µs
    assert [m.stamp.device_ns for m in sink.metas] == expected


def test_replay_stamps_capture_times_in_order_and_names_the_camera(
    video: tuple[Path, list[int], list[int]],
) -> None:
    path, _, _ = video
    sink = _Sink()
    with VideoFileCamera("replay", path, on_frame=sink, speed=4.0, drop_late=False) as camera:
        assert camera.wait(10.0)
    captures = [m.stamp.capture_ns for m in sink.metas]
    assert captures == sorted(captures)
    assert {m.camera_id for m in sink.metas} == {"replay"}
    assert [m.stamp.seq for m in sink.metas] == list(range(len(sink.metas)))
    assert camera.stats.frames == len(sink.metas)


def test_replay_refused_frame_gives_its_index_to_the_next(video: tuple[Path, list[int], list[int]]) -> None:
    path, _, _ = video
    sink = _Sink(refuse={1})
    with VideoFileCamera("replay", path, on_frame=sink, speed=4.0, drop_late=False) as camera:
        assert camera.wait(10.0)
    assert [m.frame_index for m in sink.metas[:4]] == [0, 1, 1, 2]


def test_replay_loop_keeps_media_time_increasing(video: tuple[Path, list[int], list[int]]) -> None:
    path, levels, _ = video
    n = len(levels)
    sink = _Sink(stop_after=n + 3)
    camera = VideoFileCamera("replay", path, on_frame=sink, loop=True, speed=4.0, drop_late=False)
    sink.camera = camera
    camera.start()
    assert camera.wait(10.0)
    camera.stop()
    device = [m.stamp.device_ns for m in sink.metas]
    assert len(device) == n + 3
    assert device == sorted(device)
    assert len(set(device)) == len(device)
    assert device[n] == device[n - 1] + round(SECOND / camera.fps)  # next pass starts a period later
    assert float(sink.images[n].mean()) == pytest.approx(levels[0], abs=4)


def test_replay_resizes_when_asked(video: tuple[Path, list[int], list[int]]) -> None:
    path, _, _ = video
    sink = _Sink()
    with VideoFileCamera("replay", path, on_frame=sink, width=32, height=24, speed=4.0) as camera:
        assert camera.wait(10.0)
    assert {image.shape for image in sink.images} == {(24, 32, 3)}
    assert {(m.width, m.height) for m in sink.metas} == {(32, 24)}


def test_replay_stop_from_another_thread_ends_a_looping_replay(
    video: tuple[Path, list[int], list[int]],
) -> None:
    path, _, _ = video
    got_one = threading.Event()
    camera = VideoFileCamera("replay", path, on_frame=lambda *_: got_one.set(), loop=True)
    camera.start()
    assert got_one.wait(10.0)
    camera.stop()
    assert camera.wait(5.0)


def test_replay_missing_file_is_device_error(tmp_path: Path) -> None:
    with pytest.raises(DeviceError, match=r"video file .*nope\.mp4 does not exist"):
        VideoFileCamera("replay", tmp_path / "nope.mp4", on_frame=_Sink()).start()


def test_replay_unreadable_file_is_device_error(tmp_path: Path) -> None:
    junk = tmp_path / "junk.mp4"
    junk.write_bytes(b"not a video at all" * 10)
    with pytest.raises(DeviceError, match="PyAV cannot read"):
        VideoFileCamera("replay", junk, on_frame=_Sink()).start()


def test_capture_cameras_meet_the_camera_protocol(video: tuple[Path, list[int], list[int]]) -> None:
    assert isinstance(VideoFileCamera("a", video[0], on_frame=_Sink()), Camera)
    assert isinstance(V4l2Camera("b", on_frame=_Sink()), Camera)


# --- RealSense (optional extra) -----------------------------------------------------------------


def test_realsense_without_device_is_one_line_device_error() -> None:
    try:
        import pyrealsense2  # noqa: F401
    except ImportError as exc:  # a required component: fail with the fix, never skip
        pytest.fail(f"pyrealsense2 does not load ({exc}): run `make sysdeps` and `make test`", pytrace=False)
    from telerig.cameras.realsense import RealSenseCamera, list_realsense_devices

    if list_realsense_devices():
        pytest.skip("a RealSense device is connected")
    with pytest.raises(DeviceError, match=r"a RealSense device is not connected\. Available: none"):
        RealSenseCamera("d435", on_frame=_Sink()).start()
