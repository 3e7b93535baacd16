"""MP4 files holding several episodes of one camera back to back, as LeRobot v3.0 stores video.

Each episode occupies ``[from_timestamp, to_timestamp)`` of its file; frame ``k`` of the episode
has pts ``from_timestamp + k / fps`` exactly (stream time base ``1/fps``), so a reader that asks
for ``from_timestamp + timestamp`` finds it well within LeRobot's 1e-4 s tolerance, and every
episode starts on a keyframe.

An episode whose recorded video already is the dataset's frames (one recorded frame per dataset
frame, H.264 yuv420p without B-frames: what telerig's recorder writes) is remuxed: its packets
are copied with rewritten pts, nothing is decoded but its keyframes (for the image stats). Any
other episode is decoded and encoded with libx264 (:data:`ENCODE_OPTIONS`). A file holds either
remuxed or encoded episodes of one codec configuration; a change starts a new file, as do
LeRobot's size limit and :data:`MAX_FILE_SECONDS`.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any

import av
import numpy as np
import numpy.typing as npt
from av.video.frame import PictureType

from telerig.cameras.encoder import rgb_to_yuv420p
from telerig.errors import ExportError
from telerig.export._lerobot_stats import ImageStats, sample_indices

__all__ = ["ENCODE_OPTIONS", "MAX_FILE_SECONDS", "VIDEO_PATH", "VideoFileWriter", "VideoSpan", "remuxable"]

_log = logging.getLogger("telerig.export.lerobot")

#: LeRobot's video file path template, relative to the dataset root.
VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"

#: libx264 settings for episodes that must be re-encoded. LeRobot's default is SVT-AV1 with a
#: keyframe every 2 frames (cheap random access when a training loader decodes one frame); we keep
#: the 2-frame GOP but use H.264, which every PyAV build decodes and which encodes several times
#: faster than AV1 at this quality on one core. No B-frames: pts stay in decode order.
ENCODE_OPTIONS: dict[str, str] = {"preset": "veryfast", "crf": "23"}
ENCODE_GOP = 2

#: Longest video file [s]. LeRobot compares query and frame timestamps as float32 tensors: past
#: 1024 s one float32 step (1.2e-4 s) exceeds its 1e-4 s tolerance and frames fail to load.
MAX_FILE_SECONDS = 1000.0

_UInt8Image = npt.NDArray[np.uint8]


@dataclass(frozen=True, slots=True)
class VideoSpan:
    """Where an episode's frames lie: file ``(chunk, file)``, ``[from_s, to_s)`` in it [s]."""

    chunk: int
    file: int
    from_s: float
    to_s: float


def remuxable(path: Path) -> bool:
    """Whether a recorded MP4 can be copied packet by packet (H.264, yuv420p, no B-frames)."""
    try:
        with av.open(str(path)) as container:
            stream = container.streams.video[0]
            ctx = stream.codec_context
            return bool(ctx.name == "h264" and stream.pix_fmt == "yuv420p" and not ctx.has_b_frames)
    except (av.FFmpegError, IndexError):
        return False


def _advance(chunk: int, file: int, chunks_size: int) -> tuple[int, int]:
    """LeRobot's next (chunk, file): ``chunks_size`` files per chunk directory."""
    return (chunk + 1, 0) if file == chunks_size - 1 else (chunk, file + 1)


class VideoFileWriter:
    """Appends episodes of one camera to rolling MP4 files under a staging root.

    Args:
        stage_root: Directory that mirrors the dataset root; files go to ``stage_root/VIDEO_PATH``.
        video_key: Feature key (``observation.images.scene``).
        fps: Dataset frame rate [Hz].
        start: (chunk, file) of the first file to write; it must not exist in the dataset.
        chunks_size: Files per chunk directory.
        max_mb: File size that starts a new file [MiB] (LeRobot: 200).
        max_seconds: File duration that starts a new file [s].
    """

    def __init__(
        self,
        stage_root: Path,
        video_key: str,
        fps: int,
        start: tuple[int, int],
        *,
        chunks_size: int,
        max_mb: float,
        max_seconds: float = MAX_FILE_SECONDS,
    ) -> None:
        self._root = stage_root
        self._key = video_key
        self._fps = fps
        self._time_base = Fraction(1, fps)
        self._index = start
        self._chunks_size = chunks_size
        self._max_bytes = max_mb * 1024 * 1024
        self._max_frames = int(max_seconds * fps)
        self._container: Any = None
        self._stream: Any = None
        self._config: tuple[object, ...] | None = None
        self._frames = 0  # frames in the open file
        self._bytes = 0  # packet bytes in the open file
        #: Paths written, relative to the dataset root, in order.
        self.written: list[str] = []
        #: Seconds spent remuxing, and decoding + encoding (the video share of an export).
        self.remux_s = 0.0
        self.encode_s = 0.0

    # -- files ---------------------------------------------------------------------------------

    def _roll(self, config: tuple[object, ...], frames: int, est_bytes: float) -> bool:
        """Closes the open file when the episode does not fit it; returns whether one is open."""
        if self._container is None:
            return False
        fits = (
            config == self._config
            and self._bytes + est_bytes < self._max_bytes
            and self._frames + frames <= self._max_frames
        )
        if fits:
            return True
        self._close_file()
        self._index = _advance(*self._index, self._chunks_size)
        return False

    def _open_file(self, config: tuple[object, ...]) -> Any:
        rel = VIDEO_PATH.format(video_key=self._key, chunk_index=self._index[0], file_index=self._index[1])
        path = self._root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        self._container = av.open(str(path), mode="w", format="mp4")
        self._config = config
        self._frames = 0
        self._bytes = 0
        self.written.append(rel)
        return self._container

    def _close_file(self) -> None:
        if self._container is None:
            return
        try:
            if self._config is not None and self._config[0] == "encode":
                for packet in self._stream.encode(None):
                    self._mux(packet)
        finally:
            self._container.close()
            self._container = None
            self._stream = None
            self._config = None

    def close(self) -> None:
        """Finishes the open file. Idempotent."""
        self._close_file()

    def _mux(self, packet: Any) -> None:
        self._bytes += packet.size
        self._container.mux(packet)

    def _span(self, frames: int) -> VideoSpan:
        start = self._frames
        self._frames += frames
        return VideoSpan(self._index[0], self._index[1], start / self._fps, self._frames / self._fps)

    # -- episodes ------------------------------------------------------------------------------

    def add_remux(self, source: Path, frames: int, stats: ImageStats) -> VideoSpan:
        """Copies the first ``frames`` packets of a recorded MP4 as the episode's frames.

        Keyframes are decoded and counted into ``stats`` (LeRobot samples ~``frames**0.75`` frames;
        decoding only keyframes keeps the remux at hundreds of times real time).

        Raises:
            ExportError: The recording holds fewer frames, or its frames are not in pts order.
        """
        with av.open(str(source)) as source_container:
            in_stream = source_container.streams.video[0]
            ctx = in_stream.codec_context
            config = (
                "remux",
                ctx.name,
                in_stream.width,
                in_stream.height,
                in_stream.pix_fmt,
                bytes(ctx.extradata or b""),
            )
            est = source.stat().st_size * frames / max(in_stream.frames or frames, 1)
            if not self._roll(config, frames, est):
                container = self._open_file(config)
                self._stream = container.add_stream_from_template(template=in_stream, opaque=True)
                self._stream.time_base = self._time_base
            ctx.skip_frame = "NONKEY"
            base = self._frames
            copied = 0
            last_pts: int | None = None
            for packet in source_container.demux(in_stream):
                if packet.size == 0 or packet.pts is None:
                    continue
                if copied == frames:
                    break
                if last_pts is not None and packet.pts <= last_pts:
                    raise ExportError(
                        f"{source}: packet pts go backwards (B-frames?); it cannot be remuxed. "
                        "Export re-encodes such videos: report this recording"
                    )
                last_pts = packet.pts
                if packet.is_keyframe:
                    for frame in packet.decode():
                        stats.add(frame.to_ndarray(format="rgb24"))
                elif copied == 0:
                    raise ExportError(f"{source}: the first frame is not a keyframe; it cannot be remuxed")
                packet.stream = self._stream
                packet.time_base = self._time_base
                packet.pts = base + copied
                packet.dts = base + copied
                packet.duration = 1
                self._mux(packet)
                copied += 1
            for frame in ctx.decode(None):
                stats.add(frame.to_ndarray(format="rgb24"))
        if copied < frames:
            raise ExportError(f"{source}: holds {copied} frames, the episode needs {frames}")
        return self._span(frames)

    def add_encoded(
        self, images: Iterable[_UInt8Image], frames: int, height: int, width: int, stats: ImageStats
    ) -> VideoSpan:
        """Encodes an episode's RGB frames (H, W, 3) ``uint8``; LeRobot's sampled frames go to ``stats``."""
        config = ("encode", height, width)
        per_frame = self._bytes / self._frames if self._frames else 0.0
        if not self._roll(config, frames, per_frame * frames):
            container = self._open_file(config)
            stream = container.add_stream("libx264", rate=self._fps, options=dict(ENCODE_OPTIONS))
            stream.width = width
            stream.height = height
            stream.pix_fmt = "yuv420p"
            stream.time_base = self._time_base
            stream.codec_context.time_base = self._time_base
            stream.codec_context.gop_size = ENCODE_GOP
            stream.codec_context.max_b_frames = 0
            self._stream = stream
        sampled = set(sample_indices(frames))
        base = self._frames
        count = 0
        for k, image in enumerate(images):
            if k >= frames:
                break
            if image.shape != (height, width, 3):
                raise ExportError(
                    f"{self._key}: frame {k} has shape {image.shape}, expected {(height, width, 3)}"
                )
            if k in sampled:
                stats.add(image)
            frame = rgb_to_yuv420p(image)
            frame.pts = base + k
            frame.time_base = self._time_base
            if k == 0:
                frame.pict_type = PictureType.I  # every episode starts on a keyframe
            for packet in self._stream.encode(frame):
                self._mux(packet)
            count += 1
        if count < frames:
            raise ExportError(f"{self._key}: the episode yielded {count} frames, expected {frames}")
        return self._span(frames)
