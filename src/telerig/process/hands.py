"""Hand detectors for the frame filter: a batch of RGB frames in, the hands of each frame out.

A detector is a plug-in: a config class with a ``type`` registered in
:data:`telerig.registry.HAND_DETECTORS` (built-ins here; others through the
``telerig.hand_detectors`` entry point group), whose ``build()`` returns a :class:`HandDetector`.
The built-in ``mediapipe`` detector reuses the markerless device's tracker program
(:mod:`telerig.devices.markerless.tracker`) in its own venv and process, in the tracker's batch
mode: frames go down its stdin, the markerless wire messages come back on its stdout. One process
serves every batch until :meth:`HandDetector.close`; MediaPipe's bundled models only, nothing
downloads.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import os
import subprocess
import tempfile
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Annotated, Any, Literal, Protocol, runtime_checkable

import numpy as np
import numpy.typing as npt
from pydantic import BaseModel, ConfigDict, Field

from telerig.devices.markerless import protocol, tracker
from telerig.errors import DependencyError, ProcessError, WireError
from telerig.registry import HAND_DETECTORS

__all__ = [
    "DEFAULT_TRACKER_PYTHON",
    "FrameHands",
    "Hand",
    "HandDetector",
    "HandDetectorConfig",
    "MediaPipeDetectorConfig",
    "MediaPipeHandDetector",
    "RGBFrame",
    "build_detector",
    "decode_hand_image",
]

_log = logging.getLogger(__name__)

#: An RGB frame, uint8, shape (height, width, 3).
RGBFrame = npt.NDArray[np.uint8]

#: Interpreter of the markerless tracker venv, relative to the working directory.
DEFAULT_TRACKER_PYTHON = Path(".venv-markerless/bin/python")
_START_TIMEOUT_S = 60.0
_STOP_TIMEOUT_S = 5.0
_STDERR_TAIL = 5
# Image landmarks may lie a little outside the frame (a hand cut by the border); more is garbage.
_IMAGE_SLACK = 0.5


@dataclass(frozen=True, slots=True)
class Hand:
    """One detected hand.

    Attributes:
        label: The detector's handedness label (MediaPipe's raw ``"left"``/``"right"``; unmirrored
            images swap them), or ``""`` when the detector does not say.
        score: Detection confidence in [0, 1].
        box: (x0, y0, x1, y1) as fractions of the frame's width and height.
        landmarks: Keypoints (N, 2) as fractions of width and height (MediaPipe: N = 21), or None.
    """

    label: str
    score: float
    box: tuple[float, float, float, float]
    landmarks: npt.NDArray[np.float64] | None = None


@dataclass(frozen=True, slots=True)
class FrameHands:
    """The hands of one frame."""

    hands: tuple[Hand, ...] = ()

    @property
    def count(self) -> int:
        """Number of hands in the frame."""
        return len(self.hands)


@runtime_checkable
class HandDetector(Protocol):
    """Finds hands in batches of frames; :meth:`close` ends whatever it started (idempotent)."""

    name: str
    """The registered type name, for reports."""

    def detect(self, frames: Sequence[RGBFrame]) -> list[FrameHands]:
        """The hands of each frame, in order: one :class:`FrameHands` per input frame.

        Raises:
            ProcessError: The detector failed (one line saying why).
        """
        ...

    def close(self) -> None:
        """Release the detector (stop its process); idempotent."""
        ...


class HandDetectorConfig(BaseModel):
    """Base of hand detector configs: a ``type`` naming the registered detector, and ``build()``."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    type: str

    def build(self) -> HandDetector:
        """A new detector (a started process, a loaded model) for these settings."""
        raise NotImplementedError(f"{type(self).__name__} does not build a detector")


Probability = Annotated[float, Field(ge=0, le=1)]


@HAND_DETECTORS.register
class MediaPipeDetectorConfig(HandDetectorConfig):
    """MediaPipe Hands (0.10.21, bundled models) in the markerless tracker venv, in batch mode.

    Attributes:
        python: Interpreter of the venv with ``mediapipe==0.10.21`` (``make markerless``).
        hand_model: ``"full"`` (better recall) or ``"lite"`` (about a third less CPU per frame in
            benchmarks/pipeline.py, but it misses the drawn test hand that ``full`` finds: check
            recall on your own footage before choosing it).
        max_hands: Most hands per frame.
        min_detection_confidence: MediaPipe's palm detection threshold in [0, 1].
        static_image: Detect in every frame on its own (palm detector each time). Subsampled
            frames are 0.2 to 0.5 s apart, too far for MediaPipe's tracking to help reliably,
            and independent frames make the result independent of batch boundaries.
        max_side: Frames are scaled down (keeping aspect) so their longer side is at most this
            [px] before they go down the pipe; the palm detector works at 192 x 192 anyway.
    """

    type: Literal["mediapipe"] = "mediapipe"
    python: Path = DEFAULT_TRACKER_PYTHON
    hand_model: Literal["lite", "full"] = "full"
    max_hands: Annotated[int, Field(ge=1, le=4)] = 2
    min_detection_confidence: Probability = 0.5
    static_image: bool = True
    max_side: Annotated[int, Field(ge=64, le=tracker.MAX_INPUT_SIDE)] = 640

    def build(self) -> MediaPipeHandDetector:
        return MediaPipeHandDetector(self)


def decode_hand_image(data: bytes) -> tuple[protocol.Header, Hand]:
    """Decode and validate a kind 5 (hand image landmarks) message of the tracker's batch mode.

    Raises:
        WireError: Wrong size or kind, a label other than 0/1, a score outside [0, 1], or a
            non-finite landmark or one far outside the frame.
    """
    if len(data) != tracker.HAND_IMAGE_SIZE:
        raise WireError(f"hand image message must be {tracker.HAND_IMAGE_SIZE} bytes, got {len(data)}")
    fields = tracker.HEADER.unpack_from(data)
    if fields[0] != tracker.MAGIC or fields[1] != tracker.VERSION or fields[2] != tracker.KIND_HAND_IMAGE:
        raise WireError(
            f"not a hand image message (magic {fields[0]!r}, version {fields[1]}, kind {fields[2]})"
        )
    head = protocol.Header(fields[2], False, *fields[4:])
    label, _index, score = tracker.HAND_HEAD.unpack_from(data, tracker.HEADER.size)
    if label > 1:
        raise WireError(f"hand label must be 0 (Left) or 1 (Right), got {label}")
    if not 0.0 <= score <= 1.0:  # also false for NaN
        raise WireError(f"hand score must be in [0, 1], got {score}")
    points = np.frombuffer(data, dtype="<f4", offset=tracker.HEADER.size + tracker.HAND_HEAD.size)
    points = points.astype(np.float64).reshape(tracker.HAND_POINTS, 2)
    if not np.all(np.isfinite(points)) or np.abs(points - 0.5).max() > 0.5 + _IMAGE_SLACK:
        raise WireError("hand image landmarks must be finite and near the frame")
    lo, hi = np.clip(points.min(axis=0), 0.0, 1.0), np.clip(points.max(axis=0), 0.0, 1.0)
    box = (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))
    return head, Hand("right" if label == 1 else "left", float(score), box, points)


def _scaled(frame: RGBFrame, max_side: int) -> RGBFrame:
    """``frame`` with its longer side at most ``max_side`` [px] (nearest-pixel decimation: cheap)."""
    h, w = frame.shape[:2]
    step = -(-max(h, w) // max_side)
    return frame if step <= 1 else frame[::step, ::step]


class MediaPipeHandDetector:
    """The markerless tracker in batch mode as a :class:`HandDetector` (see the module docstring).

    The process starts on the first :meth:`detect` (or :meth:`start`) and serves every batch until
    :meth:`close`; use it as a context manager. Not thread-safe: one caller at a time.
    """

    name = "mediapipe"

    def __init__(self, config: MediaPipeDetectorConfig | None = None) -> None:
        self.config = config or MediaPipeDetectorConfig()
        self._proc: subprocess.Popen[bytes] | None = None
        self._stderr: IO[bytes] | None = None
        self._next_frame = 0
        #: Frames sent to the tracker and MediaPipe's time for them [ms] (its own measurement).
        self.frames = 0
        self.processing_ms = 0.0

    def __enter__(self) -> MediaPipeHandDetector:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def command(self) -> list[str]:
        """The tracker's command line in batch mode."""
        c = self.config
        return [
            str(c.python),
            str(Path(tracker.__file__).resolve()),
            "--stdin-frames",
            "--no-pose",
            f"--max-hands={c.max_hands}",
            f"--hand-model-complexity={1 if c.hand_model == 'full' else 0}",
            f"--min-detection-confidence={c.min_detection_confidence}",
            *(["--static-image"] if c.static_image else []),
        ]

    def start(self) -> None:
        """Start the tracker process and wait for its started event.

        Raises:
            DependencyError: The tracker venv is missing (names the command that creates it).
            ProcessError: The tracker did not start (its error, one line).
        """
        if self._proc is not None:
            return
        if not self.config.python.exists():
            raise DependencyError(
                f"markerless tracker interpreter {self.config.python} does not exist; create the venv "
                "with `make markerless` (python -m telerig.devices.markerless.install) or set "
                "process.filter.detector.python"
            )
        env = dict(os.environ, GLOG_minloglevel="2", TF_CPP_MIN_LOG_LEVEL="2", PYTHONUNBUFFERED="1")
        # stderr to a file, not a pipe: MediaPipe's logging must never block the tracker.
        self._stderr = tempfile.TemporaryFile()  # noqa: SIM115 (closed by close())
        try:
            self._proc = subprocess.Popen(
                self.command(), stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self._stderr, env=env
            )
        except OSError as exc:
            self.close()
            raise ProcessError(f"cannot start the markerless tracker {self.config.python}: {exc}") from None
        msg = self._read_message()
        if not (isinstance(msg, protocol.EventMessage) and msg.code == "started"):
            text = msg.text if isinstance(msg, protocol.EventMessage) else type(msg).__name__
            self._abort()
            raise ProcessError(f"markerless tracker did not start: {text}")

    def detect(self, frames: Sequence[RGBFrame]) -> list[FrameHands]:
        """The hands of each frame (see :class:`HandDetector`); frames go down the pipe at most
        ``max_side`` [px] on their longer side.

        Raises:
            ProcessError: The tracker reported an error, sent garbage or died (with its stderr).
        """
        if not frames:
            return []
        self.start()
        proc = self._proc
        if proc is None or proc.stdin is None:
            raise ProcessError("markerless tracker is not running")
        stdin = proc.stdin
        first = self._next_frame
        records = [
            tracker.encode_input_frame(
                (first + k) & 0xFFFFFFFF, _scaled(np.asarray(f, np.uint8), self.config.max_side)
            )
            for k, f in enumerate(frames)
        ]
        self._next_frame = (first + len(frames)) & 0xFFFFFFFF

        def write() -> None:
            # A thread, so the tracker's replies are read while frames are still going down. A
            # failed write (the tracker died; ValueError: closed after a failed read) shows on the
            # read side as the end of its output, with its exit code and stderr.
            with contextlib.suppress(OSError, ValueError):
                for record in records:
                    stdin.write(record)
                stdin.flush()

        writer = threading.Thread(target=write, name="telerig-hands-writer", daemon=True)
        writer.start()
        try:
            return self._collect(first, len(frames))
        finally:
            writer.join()

    def _collect(self, first: int, n: int) -> list[FrameHands]:
        out: list[FrameHands] = []
        pending: list[Hand] = []
        while len(out) < n:
            expected = (first + len(out)) & 0xFFFFFFFF
            msg = self._read_message()
            if isinstance(msg, Hand):
                pending.append(msg)
            elif isinstance(msg, protocol.FrameMessage):
                if msg.header.frame != expected or msg.hands != len(pending):
                    self._abort()
                    raise ProcessError(
                        f"markerless tracker answered frame {msg.header.frame} with {msg.hands} hands, "
                        f"expected frame {expected} with {len(pending)}"
                    )
                out.append(FrameHands(tuple(pending)))
                pending = []
                self.frames += 1
                self.processing_ms += msg.processing_ms
            elif isinstance(msg, protocol.EventMessage) and msg.code == "error":
                self._abort()
                raise ProcessError(f"markerless tracker failed: {msg.text}")
        return out

    def _read_message(self) -> protocol.Message | Hand:
        proc = self._proc
        if proc is None or proc.stdout is None:
            raise ProcessError("markerless tracker is not running")
        raw = proc.stdout.read(tracker.OUTPUT_LENGTH.size)
        data = proc.stdout.read(tracker.OUTPUT_LENGTH.unpack(raw)[0]) if len(raw) == 2 else b""
        if not data:
            try:  # stdout closed: the tracker is ending; give it a moment to say how
                code: int | None = proc.wait(1.0)
            except subprocess.TimeoutExpired:
                code = None
            tail = self._stderr_tail()
            self._abort()
            raise ProcessError(
                f"markerless tracker ended unexpectedly (exit {code}){': ' + tail if tail else ''}"
            )
        try:
            if len(data) >= tracker.HEADER.size and data[5] == tracker.KIND_HAND_IMAGE:
                return decode_hand_image(data)[1]
            return protocol.decode(data)
        except WireError as exc:
            self._abort()
            raise ProcessError(f"markerless tracker sent a bad message: {exc}") from None

    def _stderr_tail(self) -> str:
        f = self._stderr
        if f is None:
            return ""
        try:
            f.seek(0)
            lines = [
                ln.strip() for ln in f.read().decode("utf-8", errors="replace").splitlines() if ln.strip()
            ]
        except (OSError, ValueError):
            return ""
        keep = collections.deque((ln for ln in lines if not ln.startswith(("W0000", "I0000"))), _STDERR_TAIL)
        return " | ".join(list(keep)[-3:])

    def _abort(self) -> None:
        """End a misbehaving tracker at once. Killed before its pipes close: the writer thread may
        be blocked writing a frame it will never read, holding the pipe's lock that close() needs."""
        proc = self._proc
        if proc is not None and proc.poll() is None:
            proc.kill()
        self.close()

    def close(self) -> None:
        """End the tracker (close its stdin, then terminate if it lingers); idempotent."""
        proc, self._proc = self._proc, None
        if proc is not None:
            for pipe in (proc.stdin, proc.stdout):
                try:
                    if pipe is not None:
                        pipe.close()
                except OSError:
                    pass
            try:
                proc.wait(_STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                proc.terminate()
                try:
                    proc.wait(_STOP_TIMEOUT_S)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
        stderr, self._stderr = self._stderr, None
        if stderr is not None:
            stderr.close()


def build_detector(config: Any) -> HandDetector:
    """The detector for a config (a registered :class:`HandDetectorConfig` or a raw mapping).

    Raises:
        ProcessError: Unknown type or invalid fields (one line naming the valid ones).
    """
    try:
        parsed = HAND_DETECTORS.parse_config(config, "process.filter.detector")
    except ValueError as exc:
        raise ProcessError(str(exc)) from None
    detector: HandDetector = parsed.build()
    return detector
