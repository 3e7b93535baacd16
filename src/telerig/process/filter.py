"""Stage 1, frame filtering: keep the spans of a video that show a hand in a usable frame.

Per video, one decode pass (PyAV) samples frames at ``sample_hz`` and judges each sample on a
small gray copy (``analysis_width`` px wide, gray levels 0-255):

- blur: variance of the Laplacian (a sharp frame has strong second derivatives);
- shake: the fraction of pixels that changed by more than ``shake_pixel_delta`` since the frame
  just before the sample (camera motion moves the whole picture; a moving hand only part of it);
- static: mean absolute difference from the previous sample; a static frame reuses the previous
  sample's hands instead of running the detector again (long empty shots cost little);
- exposure: mean gray level (too dark) and the fraction of blown-out pixels.

Every non-static sample goes, in batches, to the hand detector (:mod:`telerig.process.hands`,
default MediaPipe in the markerless tracker's process). A sample is kept when it has a hand and
passes the heuristics; each kept sample stands for the ``1 / sample_hz`` s around it, spans closer
than ``merge_gap_s`` merge, then grow by ``pad_s``. The kept spans are cut from the original
packets without re-encoding (stream copy): a span starts at the keyframe at or before its start
and ends after the last packet (decode order) that presents before its end, so every kept frame
decodes. Output per video: ``kept.mp4`` (``<stem>.kept.mp4`` when an item has several videos;
``.mkv`` for a codec MP4 cannot hold, such as VP8; ``filter.json`` names the file)
and its entry in ``filter.json``; a video with no kept span is marked ``empty`` and gets no file.
Only the first video stream is kept (audio is dropped).
"""

from __future__ import annotations

import atexit
import contextlib
import io
import logging
import math
import os
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from telerig.config.process import FilterSettings
from telerig.errors import DependencyError, ProcessError
from telerig.process.hands import FrameHands, HandDetector, RGBFrame, build_detector
from telerig.process.stage import Item, StageContext, StageResult, write_json_atomic

__all__ = [
    "FILTER_FILE",
    "FilterStage",
    "PacketInfo",
    "Sample",
    "VideoAnalysis",
    "analyze_video",
    "close_detectors",
    "cut_ranges",
    "frame_metrics",
    "kept_spans",
    "remux",
    "verify",
]

_log = logging.getLogger(__name__)

FILTER_FILE = "filter.json"
#: Frames go to the detector scaled so their longer side is at most this [px] (MediaPipe's palm
#: detector works at 192 x 192; 640 keeps small, distant hands findable at a bounded pipe cost).
_DETECT_MAX_SIDE = 640
_PROGRESS_EVERY_S = 0.25


@dataclass(frozen=True, slots=True)
class PacketInfo:
    """One packet of the video stream, in demux (decode) order.

    Attributes:
        pts: Presentation time [stream time base units].
        dts: Decode time [stream time base units].
        duration: Packet duration [stream time base units] (0 when the container does not say).
        keyframe: Whether the packet starts a decodable picture on its own.
    """

    pts: int
    dts: int
    duration: int
    keyframe: bool


@dataclass(frozen=True, slots=True)
class Sample:
    """One judged frame.

    Attributes:
        t: Presentation time from the video's first frame [s].
        blur: Variance of the Laplacian of the gray analysis frame [levels^2].
        shake: Fraction of pixels changed since the frame before [1].
        diff: Mean absolute difference from the previous sample [levels].
        mean: Mean gray level [levels].
        bright: Fraction of pixels at 250 or more [1].
        static: The detector was not run: the previous sample's hands were reused.
        hands: The frame's hands.
    """

    t: float
    blur: float
    shake: float
    diff: float
    mean: float
    bright: float
    static: bool
    hands: FrameHands

    def problems(self, s: FilterSettings) -> list[str]:
        """Why this sample is unusable: ``blurred``, ``shaken``, ``dark``, ``blown_out`` (or none)."""
        out = []
        if self.blur < s.blur_min_var:
            out.append("blurred")
        if self.shake > s.shake_max_fraction:
            out.append("shaken")
        if self.mean < s.dark_max_mean:
            out.append("dark")
        if self.bright > s.bright_max_fraction:
            out.append("blown_out")
        return out

    def kept(self, s: FilterSettings) -> bool:
        """A hand in a usable frame."""
        return self.hands.count > 0 and not self.problems(s)


@dataclass
class VideoAnalysis:
    """What one decode pass found: the packets (for the cut) and the judged samples."""

    path: Path
    time_base: Fraction
    start_pts: int
    fps: float
    duration_s: float
    packets: list[PacketInfo] = field(default_factory=list)
    samples: list[Sample] = field(default_factory=list)
    frames_decoded: int = 0
    decode_errors: int = 0


def frame_metrics(gray: npt.NDArray[np.uint8]) -> tuple[float, float, float]:
    """(blur [levels^2], mean [levels], bright fraction [1]) of a gray frame (H, W)."""
    g = gray.astype(np.float32)
    if min(g.shape) < 3:
        return 0.0, float(g.mean()), float(np.count_nonzero(gray >= 250)) / gray.size
    lap = g[:-2, 1:-1] + g[2:, 1:-1] + g[1:-1, :-2] + g[1:-1, 2:] - 4.0 * g[1:-1, 1:-1]
    return float(lap.var()), float(g.mean()), float(np.count_nonzero(gray >= 250)) / gray.size


def _changed(a: npt.NDArray[np.uint8], b: npt.NDArray[np.uint8], delta: float) -> tuple[float, float]:
    """(fraction of pixels changed by more than ``delta``, mean absolute difference) of two frames."""
    d = np.abs(a.astype(np.int16) - b.astype(np.int16))
    return float(np.count_nonzero(d > delta)) / d.size, float(d.mean())


def _av() -> Any:
    try:
        import av
    except ImportError:
        raise DependencyError("frame filtering needs PyAV: pip install 'telerig[process]'") from None
    return av


def _open_video(path: Path) -> Any:
    av = _av()

    try:
        size = path.stat().st_size
    except OSError as exc:
        raise ProcessError(f"cannot read video {path}: {exc.strerror or exc}") from None
    if size == 0:
        raise ProcessError(f"video {path} is empty (0 bytes); re-copy or re-record it")
    try:
        container = av.open(str(path))
    except (av.FFmpegError, OSError, ValueError) as exc:
        raise ProcessError(
            f"video {path} is not a readable video ({_reason(exc)}); re-copy or re-encode it"
        ) from None
    if not container.streams.video:
        container.close()
        raise ProcessError(f"{path} has no video stream")
    return container


def _reason(exc: BaseException) -> str:
    """FFmpeg's words for an error, without errno and path (the message names the file itself)."""
    text = getattr(exc, "strerror", None) or str(exc) or type(exc).__name__
    return str(text).splitlines()[0].split("; last error log:")[0]


def analyze_video(
    path: Path,
    settings: FilterSettings,
    detector: HandDetector,
    progress: Callable[[float], None] = lambda f: None,
) -> VideoAnalysis:
    """Decode ``path`` once: record its packets, judge a frame every ``1 / sample_hz`` s.

    Raises:
        ProcessError: The file is missing, empty, not a video, damaged beyond decoding, or has no
            frames or timestamps (one line naming the file).
    """
    av = _av()

    container = _open_video(path)
    try:
        stream = container.streams.video[0]
        stream.thread_type = "AUTO"
        tb = stream.time_base
        if tb is None:
            raise ProcessError(f"video {path} has no time base; re-mux it (ffmpeg -i in -c copy out.mp4)")
        rate = stream.average_rate or stream.guessed_rate
        fps = float(rate) if rate else 0.0
        expected = float(stream.duration * tb) if stream.duration else 0.0
        if not expected and container.duration:
            expected = container.duration / 1e6
        result = VideoAnalysis(path, Fraction(tb), 0, fps, 0.0)
        _decode_and_judge(container, stream, result, settings, detector, progress, expected)
    except av.FFmpegError as exc:
        raise ProcessError(f"video {path} is damaged ({_reason(exc)}); re-copy or re-encode it") from None
    finally:
        container.close()
    if not result.packets or not result.samples:
        raise ProcessError(f"video {path} has no decodable frames; re-copy or re-encode it")
    return result


def _decode_and_judge(
    container: Any,
    stream: Any,
    out: VideoAnalysis,
    s: FilterSettings,
    detector: HandDetector,
    progress: Callable[[float], None],
    expected_s: float,
) -> None:
    av = _av()
    tb = out.time_base
    period = 1.0 / s.sample_hz
    frame_s = 1.0 / out.fps if out.fps > 0 else period
    next_t = 0.0
    start_pts: int | None = None
    prev_gray: npt.NDArray[np.uint8] | None = None  # the frame just before the next sample
    last_sample_gray: npt.NDArray[np.uint8] | None = None
    pending: list[tuple[float, float, float, float, float, float, bool]] = []
    batch: list[RGBFrame] = []
    batch_index: list[int] = []
    hands: list[FrameHands | None] = []
    last_progress = time.monotonic()
    end_pts = 0

    def flush() -> None:
        if batch:
            found = detector.detect(batch)
            if len(found) != len(batch):
                raise ProcessError(f"hand detector answered {len(found)} frames for {len(batch)}")
            for i, f in zip(batch_index, found, strict=True):
                hands[i] = f
            batch.clear()
            batch_index.clear()

    for packet in container.demux(stream):
        if packet.size:  # the last, empty packet only flushes the decoder
            if packet.pts is None or packet.dts is None:
                raise ProcessError(f"video {out.path} has packets without timestamps; re-mux it")
            out.packets.append(PacketInfo(packet.pts, packet.dts, packet.duration or 0, packet.is_keyframe))
            end_pts = max(end_pts, packet.pts + (packet.duration or 0))
        try:
            decoded = packet.decode()
        except av.error.InvalidDataError:
            # A damaged packet: counted and skipped; the decoder resyncs at the next keyframe.
            out.decode_errors += 1
            if out.decode_errors > max(10, len(out.packets) // 2):
                raise
            continue
        for frame in decoded:
            out.frames_decoded += 1
            if frame.pts is None:
                continue
            if start_pts is None:
                start_pts = frame.pts
            t = float((frame.pts - start_pts) * tb)
            is_sample = t >= next_t - 1e-6
            if not is_sample and t < next_t - 1.5 * frame_s:
                continue  # neither a sample nor the frame just before one: not converted
            h, w = frame.height, frame.width
            aw = min(s.analysis_width, w)
            ah = max(2, round(h * aw / w))
            gray = frame.reformat(width=aw, height=ah, format="gray").to_ndarray()
            if not is_sample:
                prev_gray = gray
                continue
            blur, mean, bright = frame_metrics(gray)
            shake = _changed(gray, prev_gray, s.shake_pixel_delta)[0] if prev_gray is not None else 0.0
            diff = _changed(gray, last_sample_gray, 0)[1] if last_sample_gray is not None else math.inf
            static = diff < s.static_max_diff
            pending.append((t, blur, shake, diff, mean, bright, static))
            hands.append(None)
            if not static:
                scale = min(1.0, _DETECT_MAX_SIDE / max(h, w))
                dw, dh = max(2, round(w * scale)), max(2, round(h * scale))
                batch.append(frame.reformat(width=dw, height=dh, format="rgb24").to_ndarray())
                batch_index.append(len(hands) - 1)
                if len(batch) >= s.batch_frames:
                    flush()
            last_sample_gray = gray
            prev_gray = None
            while next_t <= t + 1e-6:
                next_t += period
            now = time.monotonic()
            if expected_s > 0 and now - last_progress >= _PROGRESS_EVERY_S:
                progress(min(0.99, t / expected_s))
                last_progress = now
    flush()
    first_pts = min((p.pts for p in out.packets), default=0)
    out.start_pts = first_pts
    out.duration_s = float((end_pts - first_pts) * tb)
    # Sample times counted from the first decoded frame; the cut counts from the first packet's
    # presentation time. They differ only when the decoder dropped leading frames (damage).
    offset = float(((start_pts if start_pts is not None else first_pts) - first_pts) * tb)
    previous = FrameHands()
    for (t, blur, shake, diff, mean, bright, static), found in zip(pending, hands, strict=True):
        current = previous if found is None else found
        out.samples.append(Sample(t + offset, blur, shake, diff, mean, bright, static, current))
        previous = current


def kept_spans(samples: Sequence[Sample], s: FilterSettings, duration_s: float) -> list[tuple[float, float]]:
    """The spans [s] to keep: each kept sample covers ``1 / sample_hz`` s around it; spans closer
    than ``merge_gap_s`` merge, then grow by ``pad_s``, are clipped to the video and those shorter
    than ``min_span_s`` dropped."""
    half = 0.5 / s.sample_hz
    spans: list[list[float]] = []
    for sample in samples:
        if not sample.kept(s):
            continue
        a, b = sample.t - half, sample.t + half
        if spans and a - spans[-1][1] <= s.merge_gap_s:
            spans[-1][1] = b
        else:
            spans.append([a, b])
    out: list[tuple[float, float]] = []
    for lo, hi in spans:
        a, b = max(0.0, lo - s.pad_s), min(duration_s, hi + s.pad_s)
        if out and a <= out[-1][1]:
            out[-1] = (out[-1][0], b)
        else:
            out.append((a, b))
    return [(a, b) for a, b in out if b - a >= s.min_span_s and b > a]


def cut_ranges(analysis: VideoAnalysis, spans: Sequence[tuple[float, float]]) -> list[tuple[int, int]]:
    """Packet index ranges [first, last] (decode order) that stream-copy ``spans`` [s].

    A range starts at the keyframe at or before the span's start and ends at the last packet that
    presents before the span's end (with B-frames this includes the references it needs).
    Overlapping or touching ranges merge.
    """
    packets = analysis.packets
    tb, t0 = analysis.time_base, analysis.start_pts
    times = [float((p.pts - t0) * tb) for p in packets]
    keys = [i for i, p in enumerate(packets) if p.keyframe] or [0]
    ranges: list[tuple[int, int]] = []
    for a, b in spans:
        first = keys[0]
        for k in keys:
            if times[k] <= a + 1e-9:
                first = k
            else:
                break
        last = first
        for i in range(first, len(packets)):
            if float((packets[i].dts - t0) * tb) >= b - 1e-9:
                break  # decode times only grow and pts >= dts: no later packet presents before b
            if times[i] < b - 1e-9:
                last = i
        if ranges and first <= ranges[-1][1] + 1:
            ranges[-1] = (ranges[-1][0], max(ranges[-1][1], last))
        else:
            ranges.append((first, last))
    return ranges


def _range_times(analysis: VideoAnalysis, r: tuple[int, int]) -> tuple[float, float]:
    """Source presentation span [s] a packet range covers."""
    tb, t0 = analysis.time_base, analysis.start_pts
    packets = analysis.packets[r[0] : r[1] + 1]
    start = min(p.pts for p in packets)
    end = max(p.pts + p.duration for p in packets)
    if all(p.duration == 0 for p in packets) and analysis.fps > 0:
        end += round(1 / (analysis.fps * tb))
    return float((start - t0) * tb), float((end - t0) * tb)


def _output_format(av: Any, stream: Any) -> str:
    """``mp4``, or ``matroska`` for a codec MP4 cannot hold (VP8, ...; Matroska holds them all)."""
    probe = av.open(io.BytesIO(), "w", format="mp4")
    try:
        probe.add_stream_from_template(stream)
    except ValueError:  # "'mp4' format does not support '<codec>' codec"
        return "matroska"
    finally:
        with contextlib.suppress(Exception):
            probe.close()
    return "mp4"


def remux(
    analysis: VideoAnalysis, ranges: Sequence[tuple[int, int]], out_dir: Path, stem: str
) -> tuple[str, int]:
    """Write the packets of ``ranges`` (stream copy, no re-encode) back to back in time to
    ``<stem>.mp4`` in ``out_dir`` (``<stem>.mkv`` when MP4 cannot hold the codec); return the file
    name and its packet count. Written to a temp name, then renamed.

    Raises:
        ProcessError: The input cannot be re-read or the output cannot be written.
    """
    av = _av()

    wanted = [False] * len(analysis.packets)
    starts = {r[0] for r in ranges}
    for a, b in ranges:
        for i in range(a, b + 1):
            wanted[i] = True
    written = 0
    out_path = out_dir / f"{stem}.mp4"
    tmp = out_dir / f".{stem}.{os.getpid()}.tmp"
    try:
        with _open_video(analysis.path) as src:
            istream = src.streams.video[0]
            fmt = _output_format(av, istream)
            out_path = out_path.with_suffix(".mp4" if fmt == "mp4" else ".mkv")
            with av.open(str(tmp), "w", format=fmt) as dst:
                ostream = dst.add_stream_from_template(istream)
                index = -1
                shift = 0
                cursor = 0  # end of what was written so far [stream time base units]
                last_dts: int | None = None
                for packet in src.demux(istream):
                    if packet.size == 0:
                        continue
                    index += 1
                    if index >= len(wanted):
                        break
                    if not wanted[index]:
                        continue
                    if index in starts:
                        shift = cursor - packet.pts
                        if last_dts is not None and packet.dts + shift <= last_dts:
                            shift += last_dts + 1 - (packet.dts + shift)
                    packet.pts += shift
                    packet.dts += shift
                    last_dts = packet.dts
                    cursor = max(cursor, packet.pts + (packet.duration or 1))
                    packet.stream = ostream
                    dst.mux(packet)
                    written += 1
        os.replace(tmp, out_path)
    except (av.FFmpegError, ValueError) as exc:
        raise ProcessError(f"cannot write {out_path} from {analysis.path}: {_reason(exc)}") from None
    except OSError as exc:
        raise ProcessError(f"cannot write {out_path}: {exc.strerror or exc}") from None
    finally:
        if tmp.exists():
            tmp.unlink()
    return out_path.name, written


def verify(path: Path, packets: int) -> float:
    """Check a written ``kept.mp4`` (or ``.mkv``): it holds ``packets`` packets and its keyframes
    decode (those not damaged in the source already); return its duration [s].

    Raises:
        ProcessError: It does not (the stream copy went wrong; nothing downstream may read it).
    """
    av = _av()

    count = 0
    end = 0
    start: int | None = None
    decoded = 0
    try:
        with av.open(str(path)) as c:
            stream = c.streams.video[0]
            stream.codec_context.skip_frame = "NONKEY"
            tb = stream.time_base
            for packet in c.demux(stream):
                if packet.size == 0:
                    for _ in packet.decode():
                        decoded += 1
                    continue
                count += 1
                if packet.pts is not None:
                    start = packet.pts if start is None else min(start, packet.pts)
                    end = max(end, packet.pts + (packet.duration or 0))
                if packet.is_keyframe:
                    # One damaged in the source too (counted there) stays damaged: a copy keeps it.
                    with contextlib.suppress(av.error.InvalidDataError):
                        decoded += len(packet.decode())
    except av.FFmpegError as exc:
        raise ProcessError(f"{path} does not decode: {_reason(exc)}") from None
    if count != packets or decoded == 0 or tb is None:
        raise ProcessError(f"{path} holds {count} packets ({decoded} keyframes decoded), expected {packets}")
    return float((end - (start or 0)) * tb)


def _summary(analysis: VideoAnalysis, s: FilterSettings) -> dict[str, int]:
    counts = dict.fromkeys(("blurred", "shaken", "dark", "blown_out", "static", "hands"), 0)
    for sample in analysis.samples:
        for p in sample.problems(s):
            counts[p] += 1
        counts["static"] += sample.static
        counts["hands"] += sample.hands.count > 0
    return counts


def _samples_json(analysis: VideoAnalysis, s: FilterSettings) -> list[dict[str, Any]]:
    return [
        {
            "t": round(x.t, 3),
            "hands": [
                {"label": h.label, "score": round(h.score, 3), "box": [round(v, 4) for v in h.box]}
                for h in x.hands.hands
            ],
            "blur": round(x.blur, 1),
            "shake": round(x.shake, 3),
            "mean": round(x.mean, 1),
            "bright": round(x.bright, 3),
            "static": x.static,
            "kept": x.kept(s),
            "problems": x.problems(s),
        }
        for x in analysis.samples
    ]


def _label(item: Item, video: Path) -> str:
    """How ``filter.json`` names a video: relative to its episode (``cameras/front.mp4``), else its path."""
    if item.episode_dir is not None and video.is_relative_to(item.episode_dir):
        return video.relative_to(item.episode_dir).as_posix()
    return str(video)


class _Shared:
    """One detector per config per process, used by one caller at a time.

    The runner pickles its stages into each pool or Dask task, so a stage object is new for every
    item; the detector (a MediaPipe process takes seconds to start) must outlive it. The tracker
    ends with this process: at exit, or when its stdin closes because this process died.
    """

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.detectors: dict[str, tuple[HandDetector, threading.Lock]] = {}
        atexit.register(self.close_all)

    def get(self, config: Any) -> tuple[HandDetector, threading.Lock]:
        key = config.model_dump_json()
        with self.lock:
            found = self.detectors.get(key)
            if found is None:
                found = (build_detector(config), threading.Lock())
                self.detectors[key] = found
            return found

    def close_all(self) -> None:
        with self.lock:
            detectors, self.detectors = list(self.detectors.values()), {}
        for detector, lock in detectors:
            with lock:
                detector.close()


_SHARED = _Shared()


def close_detectors() -> None:
    """End the hand detectors the filter started in this process (idempotent; also at exit)."""
    _SHARED.close_all()


class FilterStage:
    """Stage 1 (see the module docstring). Holds no process state, so it pickles into pool and Dask
    tasks; the hand detector built from the settings is shared by every filter run in the process
    (see :func:`close_detectors`).

    Args:
        detector: A detector to use instead of the settings' one (the caller closes it).
    """

    name = "filter"
    version = "1"

    def __init__(self, detector: HandDetector | None = None) -> None:
        self._given = detector

    def close(self) -> None:
        """End the detectors this process's filter runs started (idempotent)."""
        if self._given is None:
            close_detectors()

    def __enter__(self) -> FilterStage:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _detector(self, settings: FilterSettings) -> tuple[HandDetector, threading.Lock | None]:
        if self._given is not None:
            return self._given, None
        return _SHARED.get(settings.detector)

    def run(self, item: Item, ctx: StageContext) -> StageResult:
        """Filter every video of ``item`` into ``ctx.out_dir``; a bad video fails the item (one line)."""
        settings: FilterSettings = ctx.settings if ctx.settings is not None else FilterSettings()
        several = len(item.videos) > 1
        entries: list[dict[str, Any]] = []
        outputs: list[str] = []
        totals = dict.fromkeys(
            ("seconds_in", "seconds_kept", "frames_sampled", "hand_frames", "segments", "detector_frames"),
            0.0,
        )
        totals.update(dict.fromkeys(("blurred", "shaken", "dark", "blown_out", "static"), 0.0))
        try:
            detector, lock = self._detector(settings)
            for k, video in enumerate(item.videos):

                def part(f: float, k: int = k) -> None:
                    ctx.progress((k + f) / len(item.videos))

                with lock or contextlib.nullcontext():
                    entry = self._one(
                        video, settings, detector, ctx.out_dir, several, part, _label(item, video)
                    )
                entries.append(entry)
                if entry["output"]:
                    outputs.append(entry["output"])
                outputs.append(entry["samples_file"])
                totals["seconds_in"] += entry["duration_s"]
                totals["seconds_kept"] += entry["seconds_kept"]
                totals["frames_sampled"] += entry["frames_sampled"]
                totals["hand_frames"] += entry["hands_frames"]
                totals["segments"] += len(entry["kept"])
                totals["detector_frames"] += entry["frames_sampled"] - entry["counts"]["static"]
                for key in ("blurred", "shaken", "dark", "blown_out", "static"):
                    totals[key] += entry["counts"][key]
        except ProcessError as exc:
            return StageResult("failed", (), {}, str(exc).replace("\n", " "))
        write_json_atomic(
            ctx.out_dir / FILTER_FILE, {"schema": 1, "version": self.version, "videos": entries}
        )
        ctx.progress(1.0)
        totals["kept_fraction"] = (
            totals["seconds_kept"] / totals["seconds_in"] if totals["seconds_in"] else 0.0
        )
        totals["videos"] = float(len(entries))
        totals["videos_empty"] = float(sum(e["empty"] for e in entries))
        metrics = {k: round(v, 4) for k, v in totals.items()}
        outs = (FILTER_FILE, *outputs)
        if all(e["empty"] for e in entries):
            why = "; ".join(f"{Path(e['video']).name}: {e['why_empty']}" for e in entries)
            return StageResult("empty", outs, metrics, f"no hands kept ({why})")
        return StageResult("ok", outs, metrics)

    def _one(
        self,
        video: Path,
        s: FilterSettings,
        detector: HandDetector,
        out_dir: Path,
        several: bool,
        progress: Callable[[float], None],
        label: str,
    ) -> dict[str, Any]:
        analysis = analyze_video(video, s, detector, progress)
        spans = kept_spans(analysis.samples, s, analysis.duration_s)
        ranges = cut_ranges(analysis, spans)
        kept = [_range_times(analysis, r) for r in ranges]
        counts = _summary(analysis, s)
        stem = f"{video.stem}." if several else ""
        samples_file = f"{stem}samples.json"
        write_json_atomic(out_dir / samples_file, _samples_json(analysis, s))
        output = None
        out_duration = 0.0
        packets = 0
        if ranges:
            output, packets = remux(analysis, ranges, out_dir, f"{stem}kept")
            out_duration = verify(out_dir / output, packets)
        seconds_kept = sum(b - a for a, b in kept)
        why = ""
        if not ranges:
            why = (
                "no sample had a hand"
                if counts["hands"] == 0
                else f"{counts['hands']} samples had hands but none in a usable frame "
                f"(blurred {counts['blurred']}, shaken {counts['shaken']}, dark {counts['dark']}, "
                f"blown out {counts['blown_out']})"
            )
        _log.info("%s: kept %.1f of %.1f s in %d spans", video, seconds_kept, analysis.duration_s, len(kept))
        return {
            "video": label,
            "fps": round(analysis.fps, 3),
            "duration_s": round(analysis.duration_s, 3),
            "kept": [[round(a, 3), round(b, 3)] for a, b in kept],
            "detected": [[round(a, 3), round(b, 3)] for a, b in spans],
            "kept_fraction": round(seconds_kept / analysis.duration_s, 4) if analysis.duration_s > 0 else 0.0,
            "seconds_kept": round(seconds_kept, 3),
            "hands_frames": counts["hands"],
            "frames_sampled": len(analysis.samples),
            "frames_decoded": analysis.frames_decoded,
            "decode_errors": analysis.decode_errors,
            "counts": counts,
            "empty": not ranges,
            "why_empty": why,
            "output": output,
            "output_packets": packets,
            "output_duration_s": round(out_duration, 3),
            "samples_file": samples_file,
        }
