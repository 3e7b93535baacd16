"""VideoEncoder: frame count, capture-time pts, crash safety, dropping and lifecycle."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import threading
from pathlib import Path
from typing import Any

import av
import numpy as np
import pytest

from telerig.cameras import encoder as encoder_module
from telerig.cameras.encoder import PTS_TIME_BASE, VideoEncoder
from telerig.errors import RecordingError

W, H, FPS = 64, 48, 30.0
T0_NS = 1_700_000_000_000_000_000


def _frames(n: int) -> list[np.ndarray]:
    rng = np.random.default_rng(0)
    return [rng.integers(0, 256, (H, W, 3), dtype=np.uint8) for _ in range(n)]


def _jittered_times(n: int) -> list[int]:
    """Capture times [ns] of a ~30 Hz camera with up to 3 ms of jitter."""
    rng = np.random.default_rng(1)
    return [T0_NS + round(i * 1e9 / FPS) + int(rng.integers(0, 3_000_000)) for i in range(n)]


def _encode(path: Path, n: int, codec: Any = "h264") -> tuple[list[int], Any]:
    times = _jittered_times(n)
    enc = VideoEncoder(path, width=W, height=H, fps=FPS, codec=codec, queue_size=n)
    for frame, t in zip(_frames(n), times, strict=True):
        assert enc.submit(frame, t)
    return times, enc.finish()


def _decodable_pts(path: Path) -> list[int]:
    """Pts of every frame that decodes, stopping quietly at a truncated tail."""
    pts: list[int] = []
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        try:
            for packet in container.demux(stream):
                pts.extend(frame.pts for frame in packet.decode())
        except av.error.InvalidDataError:
            pass  # the last, partly written packet of a truncated file
    return pts


def test_decoded_frame_count_equals_submitted(tmp_path: Path) -> None:
    _, result = _encode(tmp_path / "v.mp4", 45)
    assert result.frames == 45
    assert len(_decodable_pts(result.path)) == 45


def test_pts_are_capture_times_relative_to_first_frame(tmp_path: Path) -> None:
    times, result = _encode(tmp_path / "v.mp4", 45)
    with av.open(str(result.path)) as container:
        assert container.streams.video[0].time_base == PTS_TIME_BASE
    expected_us = [(t - times[0]) / 1000 for t in times]
    assert np.allclose(_decodable_pts(result.path), expected_us, atol=1)


def test_result_keeps_capture_timestamps(tmp_path: Path) -> None:
    times, result = _encode(tmp_path / "v.mp4", 20)
    assert result.timestamps_ns == tuple(times)


def test_keyframe_starts_every_second_of_capture_time(tmp_path: Path) -> None:
    _, result = _encode(tmp_path / "v.mp4", 100)
    with av.open(str(result.path)) as container:
        keys = [p.pts for p in container.demux(video=0) if p.is_keyframe]
    assert len(keys) >= 3
    assert max(np.diff(keys)) <= 1_000_000 + 1e6 / FPS


def test_truncated_file_loses_at_most_one_fragment(tmp_path: Path) -> None:
    _, result = _encode(tmp_path / "v.mp4", 100)
    data = result.path.read_bytes()
    with av.open(str(result.path)) as container:
        ends = sorted(p.pos + p.size for p in container.demux(video=0) if p.size)
    for fraction in (0.35, 0.6, 0.9):
        cut = int(len(data) * fraction)
        truncated = tmp_path / f"cut{fraction}.mp4"
        truncated.write_bytes(data[:cut])
        complete = sum(end <= cut for end in ends)
        decoded = len(_decodable_pts(truncated))
        assert complete - FPS <= decoded <= complete


_CRASH_SCRIPT = """
import os, signal, sys, time
from pathlib import Path
import numpy as np
from telerig.cameras.encoder import VideoEncoder

enc = VideoEncoder(Path(sys.argv[1]), width={w}, height={h}, fps={fps}, queue_size={n})
for i in range({n}):
    enc.submit(np.full(({h}, {w}, 3), i, np.uint8), {t0} + i * 33_333_333)
while enc.frames < {n}:
    time.sleep(0.01)
os.kill(os.getpid(), signal.SIGKILL)  # no finish(): the process dies mid-recording
"""


def test_killed_writer_leaves_file_missing_at_most_one_second(tmp_path: Path) -> None:
    n, path = 100, tmp_path / "crash.mp4"
    script = textwrap.dedent(_CRASH_SCRIPT.format(w=W, h=H, fps=FPS, n=n, t0=T0_NS))
    proc = subprocess.run(
        [sys.executable, "-c", script, str(path)], check=False, capture_output=True, timeout=60
    )
    assert proc.returncode == -9, proc.stderr.decode()
    decoded = len(_decodable_pts(path))
    assert n - FPS <= decoded <= n


def test_full_queue_drops_counts_and_does_not_block(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    release = threading.Event()
    convert = encoder_module.rgb_to_yuv420p

    def stalled(image: np.ndarray) -> Any:
        release.wait()
        return convert(image)

    monkeypatch.setattr(encoder_module, "rgb_to_yuv420p", stalled)
    enc = VideoEncoder(tmp_path / "v.mp4", width=W, height=H, fps=FPS, queue_size=2)
    # The worker is stalled, so a blocking submit would hang here (and the test time out).
    accepted = [enc.submit(frame, T0_NS + i * 33_333_333) for i, frame in enumerate(_frames(10))]
    release.set()
    result = enc.finish()
    assert sum(accepted) in (2, 3)  # queue of 2, plus the frame the worker may already hold
    assert result.dropped == 10 - sum(accepted)
    assert result.frames == sum(accepted)


def test_finish_is_idempotent(tmp_path: Path) -> None:
    enc = VideoEncoder(tmp_path / "v.mp4", width=W, height=H, fps=FPS)
    enc.submit(_frames(1)[0], T0_NS)
    first = enc.finish()
    assert enc.finish() is first


def test_submit_after_finish_is_refused(tmp_path: Path) -> None:
    enc = VideoEncoder(tmp_path / "v.mp4", width=W, height=H, fps=FPS)
    enc.finish()
    assert not enc.submit(_frames(1)[0], T0_NS)


def test_no_frames_writes_no_file(tmp_path: Path) -> None:
    result = VideoEncoder(tmp_path / "v.mp4", width=W, height=H, fps=FPS).finish()
    assert result.frames == 0
    assert not result.path.exists()


def test_wrong_frame_shape_is_rejected(tmp_path: Path) -> None:
    enc = VideoEncoder(tmp_path / "v.mp4", width=W, height=H, fps=FPS)
    with pytest.raises(ValueError, match=r"shape \(48, 64, 3\)"):
        enc.submit(np.zeros((H, W, 4), np.uint8), T0_NS)
    enc.finish()


def test_odd_size_is_rejected(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="even"):
        VideoEncoder(tmp_path / "v.mp4", width=63, height=48, fps=FPS)


def test_missing_directory_is_rejected(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match="does not exist"):
        VideoEncoder(tmp_path / "no" / "v.mp4", width=W, height=H, fps=FPS)


def test_av1_round_trip_keeps_capture_times(tmp_path: Path) -> None:
    # PyAV's wheel (pinned in constraints.txt) bundles SVT-AV1; the codec option depends on it.
    assert "libsvtav1" in av.codecs_available, (
        "PyAV's FFmpeg has no libsvtav1: pip install -c constraints.txt av"
    )
    times, result = _encode(tmp_path / "v.mp4", 30, codec="av1")
    expected_us = [(t - times[0]) / 1000 for t in times]
    assert np.allclose(_decodable_pts(result.path), expected_us, atol=1)


def _x264_settings(path: Path) -> dict[str, str]:
    """The options x264 writes into its SEI message at the start of the stream."""
    text = path.read_bytes().split(b" - options: ", 1)[1].split(b"\x00", 1)[0]
    return dict(item.split("=", 1) for item in text.decode("ascii", "replace").split() if "=" in item)


@pytest.mark.parametrize(
    ("width", "height", "fps", "one_thread"),
    [(640, 480, 30.0, True), (1280, 720, 30.0, True), (1280, 720, 60.0, False), (1920, 1080, 30.0, False)],
)
def test_x264_encodes_on_the_camera_thread_alone_up_to_720p30(
    tmp_path: Path, width: int, height: int, fps: float, one_thread: bool
) -> None:
    enc = VideoEncoder(tmp_path / "v.mp4", width=width, height=height, fps=fps)
    for i in range(2):
        assert enc.submit(np.zeros((height, width, 3), np.uint8), T0_NS + i * 33_000_000)
    settings = _x264_settings(enc.finish().path)
    if one_thread:
        assert (settings["threads"], settings["sliced_threads"]) == ("1", "0")
    else:
        assert int(settings["threads"]) > 1, settings


def test_frames_decode_to_the_submitted_colours_though_the_caller_reuses_its_buffer(tmp_path: Path) -> None:
    # Four flat colour quadrants per frame; the caller writes every frame into one buffer.
    colours = np.array([[[200, 30, 40], [20, 180, 60]], [[40, 50, 220], [128, 128, 128]]], dtype=np.uint8)
    buffer = np.empty((H, W, 3), np.uint8)
    enc = VideoEncoder(tmp_path / "v.mp4", width=W, height=H, fps=FPS, queue_size=8)
    for i in range(8):
        buffer[:] = np.roll(colours, i, axis=1).repeat(H // 2, axis=0).repeat(W // 2, axis=1)
        assert enc.submit(buffer, T0_NS + i * 33_000_000)
    buffer[:] = 0
    enc.finish()
    with av.open(str(tmp_path / "v.mp4")) as container:
        decoded = [frame.to_ndarray(format="rgb24") for frame in container.decode(video=0)]
    assert len(decoded) == 8
    for i, image in enumerate(decoded):
        expected = np.roll(colours, i, axis=1)
        for r in range(2):
            for c in range(2):
                # The middle of each quadrant, away from the chroma of the edges.
                patch = image[r * H // 2 + 6 : (r + 1) * H // 2 - 6, c * W // 2 + 6 : (c + 1) * W // 2 - 6]
                assert np.abs(patch.astype(int) - expected[r, c]).max() <= 6, (i, r, c)


def test_rgb_to_yuv420p_is_bt601_limited_range_with_averaged_chroma() -> None:
    # Black, white and the primaries, each a flat 2x2 block: Y, U and V are BT.601's studio-range values.
    colours = [(0, 0, 0), (255, 255, 255), (255, 0, 0), (0, 255, 0), (0, 0, 255)]
    expected = [(16, 128, 128), (235, 128, 128), (81, 90, 240), (145, 54, 34), (41, 240, 110)]
    image = np.zeros((2, 2 * len(colours), 3), np.uint8)
    for k, rgb in enumerate(colours):
        image[:, 2 * k : 2 * k + 2] = rgb
    planes = encoder_module.rgb_to_yuv420p(image).to_ndarray()  # I420: Y rows, then U, then V
    n = len(colours)
    y, u, v = planes[:2], planes[2:].reshape(-1)[:n], planes[2:].reshape(-1)[n:]
    for k, (ey, eu, ev) in enumerate(expected):
        assert np.abs(y[:, 2 * k : 2 * k + 2].astype(int) - ey).max() <= 1, (colours[k], y[:, 2 * k])
        assert abs(int(u[k]) - eu) <= 1, (colours[k], u[k])
        assert abs(int(v[k]) - ev) <= 1, (colours[k], v[k])
    # A 2x2 block of two colours: chroma is the block's average.
    mixed = np.zeros((2, 2, 3), np.uint8)
    mixed[:, 0] = (255, 0, 0)
    planes = encoder_module.rgb_to_yuv420p(mixed).to_ndarray()
    assert abs(int(planes[2, 0]) - (90 + 128) / 2) <= 1  # U
    assert abs(int(planes[2, 1]) - (240 + 128) / 2) <= 1  # V


def test_rgb_to_yuv420p_agrees_with_swscale_on_a_camera_image() -> None:
    rng = np.random.default_rng(3)
    y, x = np.mgrid[0:H, 0:W]
    image = np.clip(
        np.stack(
            [128 + 90 * np.sin(x / 9), 128 + 90 * np.sin(y / 7), 128 + 60 * np.cos((x + y) / 13)], axis=-1
        )
        + rng.normal(0, 3, (H, W, 3)),
        0,
        255,
    ).astype(np.uint8)
    ours = encoder_module.rgb_to_yuv420p(image).to_ndarray().astype(int)
    swscale = (
        av.VideoFrame.from_ndarray(image, format="rgb24").reformat(format="yuv420p").to_ndarray().astype(int)
    )
    assert np.abs(ours[:H] - swscale[:H]).max() <= 1  # luma
    assert np.abs(ours[H:] - swscale[H:]).mean() <= 2  # chroma, sampled at slightly different places


@pytest.mark.parametrize("height", [2, 6, 90, 482])
def test_rgb_to_yuv420p_keeps_heights_that_are_not_multiples_of_four(height: int) -> None:
    image = np.zeros((height, 8, 3), np.uint8)
    image[-1] = 255  # the last row white: it must reach the frame
    frame = encoder_module.rgb_to_yuv420p(image)
    assert (frame.width, frame.height) == (8, height)
    assert frame.to_ndarray()[height - 1].min() >= 234  # luma of the white row


@pytest.mark.parametrize(
    "image",
    [
        np.zeros((4, 5, 3), np.uint8),  # odd width
        np.zeros((3, 4, 3), np.uint8),  # odd height
        np.zeros((4, 4), np.uint8),  # grey
        np.zeros((4, 4, 4), np.uint8),  # RGBA
        np.zeros((4, 4, 3), np.float32),
        np.zeros((0, 4, 3), np.uint8),
    ],
)
def test_rgb_to_yuv420p_refuses_what_is_not_an_even_rgb_frame_in_one_line(image: np.ndarray) -> None:
    with pytest.raises(
        ValueError,
        match=r"^an RGB frame must be uint8 of shape \(H, W, 3\) with H and W even and positive, got",
    ) as info:
        encoder_module.rgb_to_yuv420p(image)
    assert "\n" not in str(info.value)
