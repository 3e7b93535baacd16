"""Video encoder worker: RGB frames in, a crash-safe fragmented MP4 with capture-time pts out."""

from __future__ import annotations

import logging
import os
import queue
import threading
from collections.abc import Callable
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from types import TracebackType
from typing import Any, Literal

import av
import cv2
import numpy as np
import numpy.typing as npt
from av.video.frame import PictureType

from telerig import priority
from telerig.errors import DependencyError, RecordingError

__all__ = ["DEFAULT_QUEUE_SIZE", "PTS_TIME_BASE", "Codec", "EncodeResult", "VideoEncoder", "rgb_to_yuv420p"]

_log = logging.getLogger("telerig.cameras.encoder")

Codec = Literal["h264", "av1"]

#: Time base of the video stream's pts: microseconds (the MP4 muxer keeps it as the track timescale).
PTS_TIME_BASE = Fraction(1, 1_000_000)
#: Frames the input queue holds before :meth:`VideoEncoder.submit` starts dropping.
DEFAULT_QUEUE_SIZE = 8

# Each keyframe starts a new MP4 fragment (moof + mdat), written to the file as soon as it is complete,
# so a crash loses at most the fragment being built: ``keyframe_interval_s`` of video.
_MUX_OPTIONS = {"movflags": "frag_keyframe+empty_moov+default_base_moof", "flush_packets": "1"}

# FFmpeg encoder names per codec, in order of preference, with their low-latency options.
_ENCODERS: dict[Codec, tuple[tuple[str, dict[str, str]], ...]] = {
    "h264": (("libx264", {"preset": "ultrafast", "tune": "zerolatency"}),),
    # lp=1 keeps SVT-AV1 on one core; rtc=1 is its real-time (low-delay, no lookahead) mode.
    "av1": (("libsvtav1", {"preset": "11", "svtav1-params": "lp=1:rtc=1"}),),
}

_PRESET_KEY = {"libx264": "preset", "libsvtav1": "preset"}

#: Pixel rate [px/s] up to which libx264 encodes on the camera's worker thread alone: 1280x720 at
#: 30 Hz, which one thread encodes in about a quarter of the frame period here (640x480: 2.4 ms).
#: Each camera has a worker of its own, so cameras already encode in parallel; x264's default of 1.5
#: threads per core, sliced under ``tune=zerolatency``, only adds threads that wait on each other:
#: six 640x480@30 cameras on 2 cores took 4-7 % more CPU with them, and 2-3 more threads per camera
#: (``benchmarks/recording.py``). Above this rate one thread may not keep up, and x264 picks its count.
_X264_ONE_THREAD_MAX_PX_S = 1280 * 720 * 30

_Frame = npt.NDArray[np.uint8]

#: Full-range luma and chroma to BT.601 limited range: 16-235 and 16-240.
_LUMA_SCALE = 219.0 / 255.0
_CHROMA_SCALE = 224.0 / 255.0

# Each camera's encoder converts its frames on its own worker thread; OpenCV's thread pool (a thread
# per core by default) would only make those workers wait on each other.
cv2.setNumThreads(1)


@dataclass(frozen=True, slots=True)
class EncodeResult:
    """What a finished :class:`VideoEncoder` wrote.

    Attributes:
        path: The MP4 file; it exists only when ``frames > 0``.
        frames: Frames encoded into the file.
        dropped: Frames refused by :meth:`VideoEncoder.submit` because the input queue was full.
        timestamps_ns: Capture time of each encoded frame in the rig's common clock [ns], in file
            order: ``timestamps_ns[i]`` belongs to frame ``i``. Length ``frames``.
    """

    path: Path
    frames: int
    dropped: int
    timestamps_ns: tuple[int, ...]


def _pick_encoder(codec: Codec) -> tuple[str, dict[str, str]]:
    if codec not in _ENCODERS:
        raise ValueError(f"codec {codec!r} is not supported. Available: {', '.join(_ENCODERS)}")
    candidates = _ENCODERS[codec]
    for name, options in candidates:
        if name in av.codecs_available:
            return name, dict(options)
    names = ", ".join(name for name, _ in candidates)
    raise DependencyError(
        f"PyAV's FFmpeg has no {codec} encoder ({names}). "
        "Install the PyPI wheels, which bundle them: pip install --force-reinstall 'telerig[record]'"
    )


def rgb_to_yuv420p(image: _Frame) -> Any:
    """Convert an RGB image (H, W, 3), uint8, even width and height, to a yuv420p ``av.VideoFrame``
    for the H.264 encoder: BT.601, limited range, chroma averaged over each 2x2 block.

    On OpenCV's SIMD kernels, one thread: luma is the BT.601 weighted sum scaled to 16-235
    (``cvtColor`` to grey, ``convertScaleAbs``); chroma is the same conversion of the image averaged
    over 2x2 blocks (``resize`` with ``INTER_AREA``, ``cvtColor`` to YCrCb, scaled to 16-240). 0.5 ms
    per 640x480 frame where swscale's rgb24 to yuv420p took 0.9-1.3 ms; within 1 of swscale's luma.
    (OpenCV's own ``COLOR_RGB2YUV_I420`` is faster still but takes each block's chroma from its
    top-left pixel: 10 % larger H.264 files at 0.7 dB lower PSNR on the recording benchmark's frames.)
    PyAV wraps the planes in place (``from_numpy_buffer``; a copy adds 0.25 ms) where the height is
    a multiple of 4: PyAV 18 reads the height of a yuv420p buffer as ``rows // 6 * 4``, 480 for a
    482-row image, so other heights go through a copy.

    Raises:
        ValueError: ``image`` is not uint8 (H, W, 3) with H and W even and positive.
    """
    shape = image.shape
    if (
        image.dtype != np.uint8
        or len(shape) != 3
        or shape[2] != 3
        or not image.size
        or shape[0] % 2
        or shape[1] % 2
    ):
        raise ValueError(
            "an RGB frame must be uint8 of shape (H, W, 3) with H and W even and positive, "
            f"got {image.dtype} {shape}"
        )
    height, width = shape[:2]
    image = np.ascontiguousarray(image)
    i420 = np.empty((height * 3 // 2, width), np.uint8)
    luma = i420[:height]
    cv2.cvtColor(image, cv2.COLOR_RGB2GRAY, dst=luma)
    cv2.convertScaleAbs(luma, dst=luma, alpha=_LUMA_SCALE, beta=16.0)
    half = cv2.resize(image, (width // 2, height // 2), interpolation=cv2.INTER_AREA)
    ycrcb = cv2.cvtColor(half, cv2.COLOR_RGB2YCrCb)  # full range: 0-255, chroma centred on 128
    cv2.convertScaleAbs(ycrcb, dst=ycrcb, alpha=_CHROMA_SCALE, beta=128.0 * (1.0 - _CHROMA_SCALE))
    chroma = i420[height:].reshape(2, height // 2, width // 2)  # the U plane, then the V plane
    cv2.extractChannel(ycrcb, 2, chroma[0])
    cv2.extractChannel(ycrcb, 1, chroma[1])
    if height % 4 == 0:
        return av.VideoFrame.from_numpy_buffer(i420, format="yuv420p")
    return av.VideoFrame.from_ndarray(i420, format="yuv420p")


class VideoEncoder:
    """Encodes RGB frames into a fragmented MP4 on a worker thread; :meth:`submit` never blocks.

    The video's pts are the frames' capture times relative to the first frame, in
    :data:`PTS_TIME_BASE` (µs), so the file carries real timing rather than ``index / fps``.
    A keyframe, and with it an MP4 fragment, starts every ``keyframe_interval_s`` of capture
    time: a crash loses at most that much video, and the rest still decodes.

    The worker is a thread, not a process: OpenCV and PyAV release the GIL while converting
    and encoding, so a 100 Hz loop in the same process measured the same tick jitter with a
    thread as with a subprocess fed through shared memory (p99 +0.15 ms over idle at
    640x480@30 h264), and a thread needs no shared memory or spawn. The thread is one of
    :data:`_WORKERS`, which outlive their videos: an episode's encoder runs on the thread (and
    so in the C heap arena) an earlier episode's encoder left idle (see :class:`_Workers`).

    The worker starts with the first :meth:`submit` (or :meth:`start`); :meth:`finish`
    drains the queue, flushes the encoder and closes the file. Use as a context manager or
    call :meth:`finish`; it is idempotent.

    Args:
        path: Output file (``.mp4``); its directory must exist. Not created when no frame arrives.
        width: Frame width [px]; even.
        height: Frame height [px]; even.
        fps: Nominal frame rate [Hz]; written as the stream's rate. Timing comes from the pts.
        codec: ``"h264"`` (libx264) or ``"av1"`` (libsvtav1).
        preset: Encoder speed preset; default ``"ultrafast"`` (x264) or ``"11"`` (SVT-AV1).
        crf: Constant rate factor (quality; lower is better); default the encoder's own.
        keyframe_interval_s: Capture time between keyframes [s]; bounds what a crash loses.
        queue_size: Frames waiting for the worker before :meth:`submit` drops.

    Raises:
        ValueError: A size, rate or interval is out of range.
        RecordingError: The output directory does not exist.
        DependencyError: PyAV's FFmpeg lacks the codec's encoder.
    """

    def __init__(
        self,
        path: Path,
        *,
        width: int,
        height: int,
        fps: float,
        codec: Codec = "h264",
        preset: str | None = None,
        crf: int | None = None,
        keyframe_interval_s: float = 1.0,
        queue_size: int = DEFAULT_QUEUE_SIZE,
    ) -> None:
        if width <= 0 or height <= 0 or width % 2 or height % 2:
            raise ValueError(f"width and height must be positive and even (yuv420p), got {width}x{height}")
        if not fps > 0:
            raise ValueError(f"fps must be positive, got {fps}")
        if not keyframe_interval_s > 0:
            raise ValueError(f"keyframe_interval_s must be positive, got {keyframe_interval_s}")
        if queue_size < 1:
            raise ValueError(f"queue_size must be at least 1, got {queue_size}")
        if not Path(path).parent.is_dir():
            raise RecordingError(f"video {path}: directory {Path(path).parent} does not exist")
        self._encoder_name, self._options = _pick_encoder(codec)
        if preset is not None:
            self._options[_PRESET_KEY[self._encoder_name]] = preset
        if crf is not None:
            self._options["crf"] = str(crf)
        if self._encoder_name == "libx264" and width * height * fps <= _X264_ONE_THREAD_MAX_PX_S:
            self._options["threads"] = "1"
        self.path = Path(path)
        self.width = width
        self.height = height
        self.fps = fps
        self.codec: Codec = codec
        self._keyframe_interval_us = round(keyframe_interval_s * 1e6)
        # Half a frame of slack, so frames that arrive a little early still start the next fragment.
        self._keyframe_slack_us = round(0.5e6 / fps)
        self._queue: queue.Queue[tuple[_Frame, int] | None] = queue.Queue(maxsize=queue_size)
        self._lock = threading.Lock()
        self._done: threading.Event | None = None  # set when the worker has finished this video
        self._opened = threading.Event()
        self._finishing = False
        self._error: BaseException | None = None
        self._result: EncodeResult | None = None
        self._submitted = 0
        self._dropped = 0
        self._timestamps: list[int] = []

    # -- producer side -------------------------------------------------------------------------

    @property
    def frames(self) -> int:
        """Frames encoded so far."""
        return len(self._timestamps)

    @property
    def dropped(self) -> int:
        """Frames dropped so far because the input queue was full."""
        return self._dropped

    def start(self) -> None:
        """Open the file and start the worker, waiting until it is ready. Idempotent.

        Optional: the first :meth:`submit` starts the worker without waiting.

        Raises:
            RecordingError: The file or the encoder could not be opened.
        """
        self._ensure_worker()
        self._opened.wait()
        if self._error is not None:
            raise RecordingError(f"video {self.path}: {self._error}") from self._error

    def submit(self, frame: _Frame, capture_ns: int) -> bool:
        """Queue one frame for encoding; never blocks.

        The frame is copied, so the caller may reuse its buffer.

        Args:
            frame: RGB image, uint8. Shape (height, width, 3).
            capture_ns: Capture time of the frame in the rig's common clock [ns]. Should
                increase; a frame not later than the previous one gets pts previous + 1 µs.

        Returns:
            True if queued; False if dropped (queue full, counted in ``dropped``), or if the
            encoder has finished or failed.

        Raises:
            ValueError: ``frame`` has the wrong shape or dtype.
        """
        if frame.shape != (self.height, self.width, 3) or frame.dtype != np.uint8:
            raise ValueError(
                f"frame must be uint8 with shape ({self.height}, {self.width}, 3), "
                f"got {frame.dtype} {frame.shape}"
            )
        with self._lock:
            if self._finishing or self._error is not None:
                return False
            self._ensure_worker()
            try:
                self._queue.put_nowait((np.array(frame, dtype=np.uint8, copy=True), int(capture_ns)))
            except queue.Full:
                self._dropped += 1
                return False
            self._submitted += 1
            return True

    def finish(self) -> EncodeResult:
        """Encode what is queued, flush the encoder and close the file. Idempotent.

        Returns:
            What was written.

        Raises:
            RecordingError: Encoding or writing failed (raised again on every call).
        """
        with self._lock:
            self._finishing = True
            done = self._done
        if done is not None:
            # The worker drains the queue, so this put waits at most for the frames ahead of it.
            if not done.is_set():
                self._queue.put(None)
            done.wait()
        if self._error is not None:
            raise RecordingError(f"video {self.path}: {self._error}") from self._error
        if self._result is None:
            self._result = EncodeResult(self.path, self.frames, self._dropped, tuple(self._timestamps))
            _log.info(
                "%s: %d frames encoded, %d dropped", self.path.name, self._result.frames, self._result.dropped
            )
        return self._result

    def __enter__(self) -> VideoEncoder:
        self.start()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.finish()

    def _ensure_worker(self) -> None:
        # Callers hold self._lock or are the only thread touching the encoder.
        if self._done is None:
            self._done = _WORKERS.run(self._run, f"encoder-{self.path.name}")

    # -- worker side ---------------------------------------------------------------------------

    def _run(self) -> None:
        # Below the control loop; libx264's threads, started from here, inherit it.
        priority.enter("work")
        try:
            self._encode_all()
        except Exception as exc:  # reported by finish(); the producer must never see it
            _log.error("%s: encoding failed: %s", self.path, exc)
            self._error = exc
            self._opened.set()
            self._discard_queue()

    def _encode_all(self) -> None:
        if self._encoder_name == "libsvtav1":
            # SVT-AV1 prints its banner and warnings to stderr unless told otherwise (1 = errors).
            os.environ.setdefault("SVT_LOG", "1")
        container: Any = av.open(str(self.path), mode="w", format="mp4", options=dict(_MUX_OPTIONS))
        try:
            stream: Any = container.add_stream(
                self._encoder_name, rate=Fraction(self.fps).limit_denominator(1001), options=self._options
            )
            stream.width = self.width
            stream.height = self.height
            stream.pix_fmt = "yuv420p"
            stream.time_base = PTS_TIME_BASE
            stream.codec_context.time_base = PTS_TIME_BASE
            # Keyframes are forced by capture time below; this only caps a GOP if that ever fails.
            stream.codec_context.gop_size = max(1, round(4 * self.fps * self._keyframe_interval_us / 1e6))
            stream.codec_context.open()  # now, so that bad options fail start() and not the first frame
            self._opened.set()
            self._encode_queue(container, stream)
            for packet in stream.encode(None):
                container.mux(packet)
        finally:
            self._opened.set()
            # PyAV creates the file with the first packet, so without frames there is no file.
            container.close()

    def _encode_queue(self, container: Any, stream: Any) -> None:
        first_ns: int | None = None
        last_pts = -1
        last_key_pts: int | None = None
        while True:
            item = self._queue.get()
            if item is None:
                return
            image, capture_ns = item
            if first_ns is None:
                first_ns = capture_ns
            pts = (capture_ns - first_ns) // 1000
            if pts <= last_pts:
                _log.warning(
                    "%s: capture time did not increase (%d ns); pts bumped", self.path.name, capture_ns
                )
                pts = last_pts + 1
            frame = rgb_to_yuv420p(image)
            frame.pts = pts
            frame.time_base = PTS_TIME_BASE
            if (
                last_key_pts is None
                or pts - last_key_pts >= self._keyframe_interval_us - self._keyframe_slack_us
            ):
                frame.pict_type = PictureType.I
                last_key_pts = pts
            for packet in stream.encode(frame):
                container.mux(packet)
            last_pts = pts
            self._timestamps.append(capture_ns)

    def _discard_queue(self) -> None:
        # After a failure, keep emptying the queue so finish()'s sentinel never waits on a full one.
        while True:
            try:
                item = self._queue.get(timeout=0.05)
            except queue.Empty:
                if self._finishing:
                    return
                continue
            if item is None:
                return


class _Workers:
    """Encoder threads that outlive their videos: a video runs on the thread the last finished one
    left idle, or on a new one when every thread is busy (one per concurrent camera).

    Why not a fresh thread per video: glibc's malloc serves each thread from an arena (at most
    8 per core), hands a new thread the next arena round-robin once they all exist, and never gives
    the top of a thread's arena back to the kernel when :func:`~telerig.runtime.realtime.keep_heap`
    has turned trimming off (``malloc_trim`` does not trim those tops either). libx264 and FFmpeg
    take about 11 MiB of working memory per 640x480 video; with a fresh thread per episode each
    episode left that resident in another arena: the demo rig's station grew 11.5 MiB of heap
    (5-6 MiB RSS) per episode, 15 MiB/min in the soak. On a thread that stays, the next
    video reuses the same arena's free memory: measured with ``keep_heap`` and the arenas taken
    (20 other threads), 10 videos of 90 frames grew RSS by 10.8 MiB each with a thread per video,
    and by nothing after the first on a kept thread.

    Idle threads beyond :data:`_MAX_IDLE` end. A forked child starts with none.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._idle: list[_Worker] = []
        self._started = 0

    def run(self, job: Callable[[], None], name: str) -> threading.Event:
        """Run ``job`` (which must not raise) on an idle worker, or a new one, with the thread named
        ``name`` meanwhile; the returned event is set once it returned."""
        with self._lock:
            worker = self._idle.pop() if self._idle else None
            self._started += worker is None
            number = self._started
        if worker is None:
            worker = _Worker(self, f"encoder-idle-{number}")
        done = threading.Event()
        worker.jobs.put((job, name, done))
        return done

    def _release(self, worker: _Worker) -> bool:
        """Put ``worker`` back on the idle stack; False (the thread should end) when it is full."""
        with self._lock:
            if len(self._idle) >= _MAX_IDLE:
                return False
            self._idle.append(worker)
            return True

    def _forget(self) -> None:
        """In a forked child: the parent's threads do not exist there."""
        self._lock = threading.Lock()
        self._idle = []


class _Worker:
    def __init__(self, pool: _Workers, name: str) -> None:
        self.jobs: queue.SimpleQueue[tuple[Callable[[], None], str, threading.Event]] = queue.SimpleQueue()
        self._pool = pool
        self._name = name
        threading.Thread(target=self._loop, name=name, daemon=True).start()

    def _loop(self) -> None:
        me = threading.current_thread()
        while True:
            job, name, done = self.jobs.get()
            me.name = name
            try:
                job()
            except BaseException as exc:
                _log.error("%s: encoder worker failed: %s", name, exc)
            me.name = self._name
            # Idle again before the waiter wakes, so the next episode's encoder gets this thread.
            keep = self._pool._release(self)
            done.set()
            if not keep:
                return


#: Idle encoder threads kept for the next videos (one per camera recorded at once is enough).
_MAX_IDLE = 16
#: The process's encoder threads.
_WORKERS = _Workers()
if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_WORKERS._forget)
