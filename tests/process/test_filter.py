"""Stage 1 (frame filtering) on real H.264 videos: real MediaPipe (markerless venv) finds the hand,
empty, blurred and dark spans are dropped, the kept spans are a stream copy of the original packets."""

from __future__ import annotations

import json
import pickle
from collections.abc import Iterator, Sequence
from fractions import Fraction
from pathlib import Path
from typing import Literal

import av
import numpy as np
import numpy.typing as npt
import pytest

from telerig.config.process import FilterSettings
from telerig.devices.markerless.fake import synthetic_hand_frame
from telerig.process.filter import FILTER_FILE, FilterStage, Sample, kept_spans
from telerig.process.hands import FrameHands, Hand, HandDetectorConfig, MediaPipeHandDetector, RGBFrame
from telerig.process.stage import Item, StageContext, StageResult
from telerig.registry import HAND_DETECTORS

_TRACKER_PYTHON = Path(__file__).resolve().parents[2] / ".venv-markerless" / "bin" / "python"
_W, _H, _FPS, _GOP = 320, 240, 10, 10

Image = npt.NDArray[np.uint8]


def _half(img: Image) -> Image:
    """A 640x480 frame averaged down to 320x240."""
    return np.asarray(img.reshape(_H, 2, _W, 2, 3).mean(axis=(1, 3)), dtype=np.uint8)


def _box_blur(img: Image, r: int) -> Image:
    out = img.astype(np.float64)
    for axis in (0, 1):
        out = sum((np.roll(out, i - r, axis=axis) for i in range(2 * r + 1)), np.zeros_like(out)) / (
            2 * r + 1
        )
    return np.asarray(out.clip(0, 255), dtype=np.uint8)


class _Frames:
    """The test footage: an empty shaded scene, a drawn hand (MediaPipe finds it), black."""

    def __init__(self) -> None:
        self.rng = np.random.default_rng(0)
        self.hands = [_half(synthetic_hand_frame(t)) for t in (0.0, 0.5)]
        shade = (0.7 + 0.6 * np.arange(_W, dtype=np.float32) / _W)[None, :, None]
        self.background = np.broadcast_to(np.array([40.0, 60.0, 90.0], np.float32) * shade, (_H, _W, 3))

    def noisy(self, img: npt.NDArray[np.generic]) -> Image:
        noise = self.rng.integers(-3, 4, img.shape)
        return np.asarray((img.astype(np.int16) + noise).clip(0, 255), dtype=np.uint8)

    def empty(self, n: int) -> list[Image]:
        return [self.noisy(self.background) for _ in range(n)]

    def hand(self, n: int) -> list[Image]:
        return [self.noisy(self.hands[(k // 5) % 2]) for k in range(n)]

    def blurred_hand(self, n: int) -> list[Image]:
        return [_box_blur(self.noisy(self.hands[0]), 6) for _ in range(n)]

    def black(self, n: int) -> list[Image]:
        return [np.zeros((_H, _W, 3), np.uint8) for _ in range(n)]


def _write(path: Path, frames: Sequence[Image], *, b_frames: int = 0, gop: int = _GOP) -> Path:
    """H.264 at 10 fps, a keyframe every ``gop`` frames exactly."""
    with av.open(str(path), "w") as c:
        st = c.add_stream("libx264", rate=_FPS)
        st.width, st.height, st.pix_fmt = _W, _H, "yuv420p"
        st.options = {
            "preset": "ultrafast",
            "crf": "23",
            "g": str(gop),
            "keyint_min": str(gop),
            "sc_threshold": "0",
            "bf": str(b_frames),
        }
        for img in frames:
            for packet in st.encode(av.VideoFrame.from_ndarray(img, format="rgb24")):
                c.mux(packet)
        for packet in st.encode():
            c.mux(packet)
    return path


@pytest.fixture(scope="module")
def frames() -> _Frames:
    return _Frames()


@pytest.fixture(scope="module")
def stage() -> Iterator[FilterStage]:
    """One MediaPipe tracker process for the whole module (it takes seconds to start)."""
    if not _TRACKER_PYTHON.exists():  # a required component: fail with the fix, never skip
        pytest.fail(f"{_TRACKER_PYTHON} is missing: run `make markerless` (make unit does it)", pytrace=False)
    settings = FilterSettings(detector={"type": "mediapipe", "python": str(_TRACKER_PYTHON)})
    with MediaPipeHandDetector(settings.detector) as detector, FilterStage(detector) as st:
        yield st


def _run(
    stage: FilterStage, videos: Sequence[Path], out: Path, settings: FilterSettings | None = None
) -> StageResult:
    out.mkdir(parents=True, exist_ok=True)
    item = Item("item", "video", tuple(videos), None, "0" * 64, {})
    seen: list[float] = []
    result = stage.run(item, StageContext(out, out.parent, {}, settings or FilterSettings(), seen.append))
    assert not seen or seen[-1] == 1.0 or result.status == "failed"
    return result


def _packets(path: Path) -> list[tuple[bytes, bool]]:
    with av.open(str(path)) as c:
        return [(bytes(p), p.is_keyframe) for p in c.demux(c.streams.video[0]) if p.size]


def _decoded_frames(path: Path) -> int:
    with av.open(str(path)) as c:
        return sum(1 for _ in c.decode(video=0))


def test_hand_span_is_kept_as_stream_copy(tmp_path: Path, stage: FilterStage, frames: _Frames) -> None:
    # 0-1.5 s empty scene, 1.5-3.5 s hand, 3.5-4.5 s blurred hand, 4.5-6 s black.
    src = _write(
        tmp_path / "ego.mp4",
        frames.empty(15) + frames.hand(20) + frames.blurred_hand(10) + frames.black(15),
    )
    result = _run(stage, [src], tmp_path / "out")
    assert result.status == "ok", result.message
    doc = json.loads((tmp_path / "out" / FILTER_FILE).read_text())
    (video,) = doc["videos"]
    # Hand samples at 1.5..3.0 s cover [1.25, 3.25], padded by 0.25 s; the cut starts at the
    # keyframe at or before 1.0 s (keyframes every 1 s) and ends at the last frame before 3.5 s.
    assert video["kept"] == [[1.0, 3.5]]
    assert not video["empty"]
    assert video["duration_s"] == pytest.approx(6.0)
    assert video["kept_fraction"] == pytest.approx(2.5 / 6.0, abs=1e-3)
    assert video["counts"]["blurred"] >= 2  # the blurred hand is found by MediaPipe, dropped by blur
    samples = json.loads((tmp_path / "out" / "samples.json").read_text())
    assert [s["t"] for s in samples if s["kept"]] == [1.5, 2.0, 2.5, 3.0]
    # Stream copy: the output's packets are the source's packets 10..34, byte for byte, same codec.
    src_packets, out_packets = _packets(src), _packets(tmp_path / "out" / "kept.mp4")
    assert out_packets == src_packets[10:35]
    with av.open(str(src)) as a, av.open(str(tmp_path / "out" / "kept.mp4")) as b:
        sa, sb = a.streams.video[0], b.streams.video[0]
        assert (sb.codec_context.name, sb.codec_context.extradata) == (
            sa.codec_context.name,
            sa.codec_context.extradata,
        )
        assert (sb.width, sb.height) == (sa.width, sa.height)
    assert _decoded_frames(tmp_path / "out" / "kept.mp4") == 25
    assert video["output_duration_s"] == pytest.approx(2.5)
    m = result.metrics
    assert (m["seconds_in"], m["seconds_kept"], m["frames_sampled"], m["hand_frames"]) == (
        6.0,
        2.5,
        12.0,
        6.0,
    )
    assert m["kept_fraction"] == pytest.approx(0.4167, abs=1e-3)
    assert set(result.outputs) == {FILTER_FILE, "kept.mp4", "samples.json"}


def test_video_without_hands_is_marked_empty(tmp_path: Path, stage: FilterStage, frames: _Frames) -> None:
    src = _write(tmp_path / "nohands.mp4", frames.empty(20) + frames.black(10))
    result = _run(stage, [src], tmp_path / "out")
    assert result.status == "empty"
    assert "no sample had a hand" in result.message
    doc = json.loads((tmp_path / "out" / FILTER_FILE).read_text())
    assert doc["videos"][0]["empty"] is True
    assert doc["videos"][0]["kept"] == []
    assert not (tmp_path / "out" / "kept.mp4").exists()
    assert result.metrics["kept_fraction"] == 0.0
    assert result.metrics["seconds_in"] == pytest.approx(3.0)


def _truncated(tmp_path: Path, frames: _Frames) -> Path:
    whole = _write(tmp_path / "whole.mp4", frames.empty(10)).read_bytes()
    path = tmp_path / "truncated.mp4"
    path.write_bytes(whole[: len(whole) // 2])
    return path


@pytest.mark.parametrize(
    ("case", "expect"),
    [
        ("zero", "is empty (0 bytes)"),
        ("garbage", "is not a readable video"),
        ("truncated", "is not a readable video"),
        ("missing", "cannot read video"),
        ("audio_only", "has no video stream"),
    ],
)
def test_bad_video_fails_with_one_line(
    tmp_path: Path, stage: FilterStage, frames: _Frames, case: str, expect: str
) -> None:
    path = tmp_path / f"{case}.mp4"
    if case == "zero":
        path.write_bytes(b"")
    elif case == "garbage":
        path.write_bytes(np.random.default_rng(1).integers(0, 256, 100_000, dtype=np.uint8).tobytes())
    elif case == "truncated":
        path = _truncated(tmp_path, frames)
    elif case == "audio_only":
        with av.open(str(path), "w") as c:
            st = c.add_stream("aac", rate=8000)
            frame = av.AudioFrame.from_ndarray(np.zeros((1, 1024), np.float32), format="fltp", layout="mono")
            frame.sample_rate = 8000
            for packet in [*st.encode(frame), *st.encode()]:
                c.mux(packet)
    result = _run(stage, [path], tmp_path / "out")
    assert result.status == "failed"
    assert expect in result.message
    assert str(path) in result.message
    assert "\n" not in result.message
    assert not (tmp_path / "out" / FILTER_FILE).exists()


def test_spans_merge_short_gaps_and_pad() -> None:
    s = FilterSettings(sample_hz=2.0, merge_gap_s=1.0, pad_s=0.25)
    hand = FrameHands((Hand("right", 0.9, (0.1, 0.1, 0.2, 0.2)),))

    def sample(t: float, hands: bool, blur: float = 100.0) -> Sample:
        return Sample(t, blur, 0.0, 5.0, 100.0, 0.0, False, hand if hands else FrameHands())

    # Kept at 1.0-2.0, one missed sample at 2.5, kept 3.0; a blurred hand at 6.0; kept 8.0.
    samples = [sample(0.5 * k, 2 <= k <= 4 or k in (6, 16)) for k in range(20)]
    samples[12] = sample(6.0, True, blur=1.0)
    assert kept_spans(samples, s, 10.0) == [(0.5, 3.5), (7.5, 8.5)]
    assert kept_spans(samples, s.model_copy(update={"min_span_s": 1.5}), 10.0) == [(0.5, 3.5)]


# --- a detector plug-in registered by name (no MediaPipe: a real, simple colour detector) -------


class _RedBlobDetector:
    """Finds saturated red regions (the 'hands' of the plug-in test) by thresholding."""

    name = "red_blob"

    def __init__(self) -> None:
        self.calls = 0
        self.closed = False

    def detect(self, frames: Sequence[RGBFrame]) -> list[FrameHands]:
        self.calls += 1
        out = []
        for f in frames:
            red = (f[..., 0] > 180) & (f[..., 1] < 80) & (f[..., 2] < 80)
            if red.sum() < 50:
                out.append(FrameHands())
                continue
            ys, xs = np.nonzero(red)
            h, w = red.shape
            box = (xs.min() / w, ys.min() / h, (xs.max() + 1) / w, (ys.max() + 1) / h)
            out.append(FrameHands((Hand("", 1.0, tuple(float(v) for v in box)),)))  # type: ignore[arg-type]
        return out

    def close(self) -> None:
        self.closed = True


_BUILT: list[_RedBlobDetector] = []


@HAND_DETECTORS.register
class _RedBlobConfig(HandDetectorConfig):
    type: Literal["test_red_blob"] = "test_red_blob"

    def build(self) -> _RedBlobDetector:
        detector = _RedBlobDetector()
        _BUILT.append(detector)
        return detector


def test_detector_plugin_registered_by_name(tmp_path: Path, frames: _Frames) -> None:
    scenes = frames.empty(36)
    for k in range(12, 24):  # a red square from 1.2 s to 2.4 s
        scenes[k] = scenes[k].copy()
        scenes[k][100:140, 140:180] = (230, 20, 20)
    # B-frames and a 12-frame GOP: the cut must keep the references the kept frames need.
    src = _write(tmp_path / "red.mp4", scenes, b_frames=2, gop=12)
    # blur_min_var=0: the flat test scene has no texture for the blur measure (that is tested above).
    settings = FilterSettings(
        sample_hz=5.0, detector={"type": "test_red_blob"}, merge_gap_s=0.0, pad_s=0.0, blur_min_var=0.0
    )
    built = len(_BUILT)
    with FilterStage() as stage:
        result = _run(stage, [src], tmp_path / "out", settings)
        # The runner pickles a stage into every task: a copy reuses the process's detector.
        copy = pickle.loads(pickle.dumps(stage))
        assert _run(copy, [src], tmp_path / "again", settings).status == "ok"
        assert len(_BUILT) == built + 1
        assert _BUILT[-1].calls >= 2
    assert _BUILT[-1].closed  # closing the stage ends the detectors it started
    assert result.status == "ok", result.message
    doc = json.loads((tmp_path / "out" / FILTER_FILE).read_text())
    (video,) = doc["videos"]
    # Samples 1.2..2.2 s hold the square: [1.1, 2.3]; cut from the keyframe at 0.0 s up to the
    # packets the frames before 2.3 s need (decode order) -> at least 0.0-2.3 s.
    assert video["detected"] == [[1.1, 2.3]]
    start, end = video["kept"][0]
    assert start == 0.0
    assert end >= 2.3
    assert _decoded_frames(tmp_path / "out" / "kept.mp4") == video["output_packets"]
    src_packets = _packets(src)
    assert _packets(tmp_path / "out" / "kept.mp4") == src_packets[: video["output_packets"]]
    with av.open(str(tmp_path / "out" / "kept.mp4")) as c:
        assert c.streams.video[0].time_base is not None
        assert Fraction(c.streams.video[0].average_rate or 0) == _FPS


def _red_square_video(path: Path, frames: _Frames, n: int = 30) -> Path:
    scenes = frames.empty(n)
    for k in range(n // 3, 2 * n // 3):
        scenes[k] = scenes[k].copy()
        scenes[k][100:140, 140:180] = (230, 20, 20)
    return _write(path, scenes)


_RED = FilterSettings(detector={"type": "test_red_blob"}, blur_min_var=0.0)


def test_damaged_packets_are_counted_not_fatal(tmp_path: Path, frames: _Frames) -> None:
    data = bytearray(_red_square_video(tmp_path / "red.mp4", frames).read_bytes())
    start, end = data.find(b"mdat") + 2000, data.find(b"moov") - 2000  # frame data only
    rng = np.random.default_rng(3)
    for i in rng.integers(start, end, 300):
        data[i] = int(rng.integers(0, 256))
    damaged = tmp_path / "damaged.mp4"
    damaged.write_bytes(bytes(data))
    with FilterStage() as stage:
        result = _run(stage, [damaged], tmp_path / "out", _RED)
    assert result.status in ("ok", "empty"), result.message
    doc = json.loads((tmp_path / "out" / FILTER_FILE).read_text())
    assert doc["videos"][0]["frames_decoded"] + doc["videos"][0]["decode_errors"] >= 20


def test_a_codec_mp4_cannot_hold_is_copied_into_matroska(tmp_path: Path, frames: _Frames) -> None:
    scenes = frames.empty(30)
    for k in range(10, 20):
        scenes[k] = scenes[k].copy()
        scenes[k][100:140, 140:180] = (230, 20, 20)
    src = tmp_path / "vp8.webm"
    with av.open(str(src), "w") as c:
        st = c.add_stream("libvpx", rate=_FPS)
        st.width, st.height, st.pix_fmt = _W // 2, _H // 2, "yuv420p"
        st.options = {"g": "10", "keyint_min": "10", "deadline": "realtime", "cpu-used": "8"}
        for img in scenes:
            small = np.ascontiguousarray(img[::2, ::2])
            for packet in st.encode(av.VideoFrame.from_ndarray(small, format="rgb24")):
                c.mux(packet)
        for packet in st.encode():
            c.mux(packet)
    with FilterStage() as stage:
        result = _run(stage, [src], tmp_path / "out", _RED)
    assert result.status == "ok", result.message
    assert "kept.mkv" in result.outputs
    doc = json.loads((tmp_path / "out" / FILTER_FILE).read_text())
    assert doc["videos"][0]["output"] == "kept.mkv"
    n = doc["videos"][0]["output_packets"]
    first = round(doc["videos"][0]["kept"][0][0] * _FPS)
    assert _packets(tmp_path / "out" / "kept.mkv") == _packets(src)[first : first + n]


def test_episode_with_two_cameras_names_outputs_per_camera(tmp_path: Path, frames: _Frames) -> None:
    episode = tmp_path / "ep"
    (episode / "cameras").mkdir(parents=True)
    front = _red_square_video(episode / "cameras" / "front.mp4", frames)
    wrist = _write(episode / "cameras" / "wrist.mp4", frames.empty(20))
    item = Item("ep1", "episode", (front, wrist), episode, "0" * 64, {})
    out = tmp_path / "out"
    out.mkdir()
    with FilterStage() as stage:
        result = stage.run(item, StageContext(out, tmp_path, {}, _RED, lambda f: None))
    assert result.status == "ok", result.message  # one camera with a hand is enough
    assert set(result.outputs) == {FILTER_FILE, "front.kept.mp4", "front.samples.json", "wrist.samples.json"}
    videos = json.loads((out / FILTER_FILE).read_text())["videos"]
    assert [(v["video"], v["empty"]) for v in videos] == [
        ("cameras/front.mp4", False),
        ("cameras/wrist.mp4", True),
    ]
    assert result.metrics["videos_empty"] == 1.0
    assert result.metrics["seconds_in"] == pytest.approx(5.0)


def test_single_frame_and_tiny_videos(tmp_path: Path) -> None:
    red = np.zeros((16, 16, 3), np.uint8)
    red[...] = (230, 20, 20)
    one = tmp_path / "one.mp4"
    with av.open(str(one), "w") as c:
        st = c.add_stream("libx264", rate=_FPS)
        st.width, st.height, st.pix_fmt = 16, 16, "yuv420p"
        for packet in [*st.encode(av.VideoFrame.from_ndarray(red, format="rgb24")), *st.encode()]:
            c.mux(packet)
    with FilterStage() as stage:
        result = _run(stage, [one], tmp_path / "out", _RED.model_copy(update={"dark_max_mean": 0.0}))
    assert result.status == "ok", result.message
    doc = json.loads((tmp_path / "out" / FILTER_FILE).read_text())
    assert doc["videos"][0]["frames_sampled"] == 1
    assert doc["videos"][0]["output_packets"] == 1
    assert _decoded_frames(tmp_path / "out" / "kept.mp4") == 1


def test_unknown_detector_names_the_registered_ones() -> None:
    with pytest.raises(ValueError, match=r"unknown hand detector type 'yolo'.*mediapipe"):
        FilterSettings(detector={"type": "yolo"})
    assert FilterSettings(detector="test_red_blob").detector == _RedBlobConfig()  # name shorthand
