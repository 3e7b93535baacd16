"""The markerless device: runs the MediaPipe tracker process and turns its datagrams into IR samples."""

from __future__ import annotations

import collections
import logging
import os
import socket
import subprocess
import sys
import threading
from pathlib import Path

from telerig.devices.base import SampleSink
from telerig.devices.markerless import protocol, tracker
from telerig.devices.worker import DeviceWorker
from telerig.errors import ConfigError, DependencyError, DeviceError, WireError
from telerig.ir.types import Sample, Stamp

__all__ = ["DEFAULT_TRACKER_PYTHON", "MarkerlessDevice"]

_log = logging.getLogger(__name__)

#: Interpreter of the tracker venv, relative to the working directory (see ``markerless.install``).
DEFAULT_TRACKER_PYTHON = Path(".venv-markerless/bin/python")
_STDERR_TAIL = 20
_STOP_TIMEOUT_S = 3.0


class MarkerlessDevice:
    """Hands and body from a webcam or video file, tracked by MediaPipe in a child process.

    ``start`` binds a UDP socket on ``listen`` and, when ``source`` is given, starts
    ``python tracker.py`` (the MediaPipe venv's interpreter) sending to it; with ``source=None``
    it only listens, for a tracker started by hand (e.g. on the camera's host) or a fake. Each
    datagram is decoded by :mod:`telerig.devices.markerless.protocol` and delivered as
    ``HandPose`` (source ``"<id>/left"`` / ``"<id>/right"``, frame ``hand_frame_id``) or
    ``BodySkeleton`` (source ``"<id>/body"``, frame ``body_frame_id``). Stamps: ``capture_ns``
    is the frame's capture time (see :mod:`telerig.devices.markerless.tracker`), ``device_ns``
    the frame's presentation time in the source's clock, ``confidence`` the handedness score
    (hands) or the arms' mean visibility (body). Bad datagrams are dropped and counted in
    :attr:`stats`; nothing a peer sends can crash the device.
    """

    def __init__(
        self,
        id: str = "cam0",
        *,
        source: str | None = None,
        python: str | Path = DEFAULT_TRACKER_PYTHON,
        listen: tuple[str, int] = ("127.0.0.1", 0),
        hands: bool = True,
        pose: bool = True,
        max_hands: int = 2,
        hand_model: str = "full",
        mirrored: bool = False,
        realtime: bool = True,
        loop: bool = False,
        min_detection_confidence: float = 0.5,
        min_tracking_confidence: float = 0.5,
        width: int = 640,
        height: int = 480,
        fps: float = 30.0,
        input_format: str = "",
        hand_frame_id: str = "hand",
        body_frame_id: str = "hips",
    ) -> None:
        """Args:
        id: Device id; the prefix of the samples' source ids.
        source: Video file path or V4L2 device (``/dev/videoN``); ``None`` to only listen.
        python: Interpreter of the venv with ``mediapipe==0.10.21`` and ``av``.
        listen: UDP (host, port) to receive on; port 0 picks a free one (see :attr:`address`).
        hands: Track hands.
        pose: Track the body.
        max_hands: Most hands per frame, 1 to 4.
        hand_model: ``"full"`` (MediaPipe's default) or ``"lite"`` (about half the time per
            frame) hand models; both ship in the wheel.
        mirrored: The frames are a mirror image (a selfie preview); fixes handedness and y.
        realtime: Pace a video file at its frame rate like a camera (else as fast as possible).
        loop: Restart a video file at its end.
        min_detection_confidence: MediaPipe's detection threshold in [0, 1].
        min_tracking_confidence: MediaPipe's tracking threshold in [0, 1].
        width: Requested camera width [px] (V4L2 only).
        height: Requested camera height [px] (V4L2 only).
        fps: Requested camera frame rate [Hz] (V4L2 only).
        input_format: V4L2 pixel format, e.g. ``"mjpeg"``; empty for the camera's default.
        hand_frame_id: Frame of hand keypoints (operator axes, origin at the hand's centre).
        body_frame_id: Frame of body joints (operator axes, origin between the hips).
        """
        if hand_model not in ("lite", "full"):
            raise ConfigError(f"hand_model must be 'lite' or 'full', got {hand_model!r}")
        if not 1 <= max_hands <= 4:
            raise ConfigError(f"max_hands must be 1 to 4, got {max_hands}")
        for name, value in (
            ("min_detection_confidence", min_detection_confidence),
            ("min_tracking_confidence", min_tracking_confidence),
        ):
            if not 0.0 <= value <= 1.0:
                raise ConfigError(f"{name} must be in [0, 1], got {value}")
        if not (hands or pose):
            raise ConfigError("enable hands, pose or both; a tracker with neither emits nothing")
        self._id = id
        self.source = source
        self.python = Path(python)
        self.listen = listen
        self.hand_frame_id = hand_frame_id
        self.body_frame_id = body_frame_id
        self._args = [
            "--hands" if hands else "--no-hands",
            "--pose" if pose else "--no-pose",
            f"--max-hands={max_hands}",
            f"--hand-model-complexity={1 if hand_model == 'full' else 0}",
            f"--min-detection-confidence={min_detection_confidence}",
            f"--min-tracking-confidence={min_tracking_confidence}",
            "--realtime" if realtime else "--no-realtime",
            f"--width={width}",
            f"--height={height}",
            f"--fps={fps}",
        ]
        if mirrored:
            self._args.append("--mirrored")
        if loop:
            self._args.append("--loop")
        if input_format:
            self._args.append(f"--input-format={input_format}")
        self._lock = threading.Lock()  # guards _stats
        self._worker = DeviceWorker(
            id, kind="markerless device", thread_name=f"telerig-markerless-{id}", log=_log
        )
        self._sock: socket.socket | None = None
        self._proc: subprocess.Popen[bytes] | None = None
        self._watcher: threading.Thread | None = None
        self._stats: collections.Counter[str] = collections.Counter()
        self._seq: dict[str, int] = {}
        self._last_frame: dict[str, int] = {}
        self._stderr_tail: collections.deque[str] = collections.deque(maxlen=_STDERR_TAIL)
        #: Set when the tracker reports the end of its file or an error, or exits.
        self.ended = threading.Event()
        #: The tracker's last error, one line; ``None`` while all is well.
        self.error: str | None = None
        #: Tracker time of the last frame (decode to RGB + MediaPipe) [ms].
        self.last_processing_ms = 0.0

    @property
    def id(self) -> str:
        """Device id."""
        return self._id

    @property
    def address(self) -> tuple[str, int]:
        """The bound UDP (host, port) trackers send to.

        Raises:
            DeviceError: Before :meth:`start`.
        """
        sock = self._sock
        if sock is None:
            raise DeviceError(f"markerless device '{self._id}' is not started; call start() first")
        host, port = sock.getsockname()[:2]
        return str(host), int(port)

    @property
    def stats(self) -> dict[str, int]:
        """Counters: ``hands``, ``bodies``, ``frames`` delivered or seen; drops per reason
        (``malformed``, ``degenerate``, ``reordered``, ``duplicate_hand``, ``sink_error``)."""
        with self._lock:
            stats = dict(self._stats)
        return {**stats, "sink_error": self._worker.sink_errors}

    def tracker_command(self, port: int) -> list[str]:
        """The tracker's command line for sending to 127.0.0.1:``port``."""
        if self.source is None:
            raise DeviceError(f"markerless device '{self._id}' has no source to track")
        return [
            str(self.python),
            str(Path(tracker.__file__).resolve()),
            f"--source={self.source}",
            f"--send-to={self.listen[0]}:{port}",
            *self._args,
        ]

    def start(self, sink: SampleSink) -> None:
        """Bind the socket, start the tracker (if ``source`` is set) and deliver samples to ``sink``.

        Raises:
            DependencyError: If the tracker venv's interpreter does not exist.
            DeviceError: If the device is already running or the socket cannot be bound.
        """
        with self._worker.starting() as launch:
            if self.source is not None and not self.python.exists():
                raise DependencyError(
                    f"markerless tracker interpreter {self.python} does not exist; create the venv with "
                    f"`{sys.executable} -m telerig.devices.markerless.install` or set `python:`"
                )
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            try:
                sock.bind(self.listen)
            except OSError as exc:
                sock.close()
                raise DeviceError(
                    f"markerless device '{self._id}' cannot bind UDP {self.listen}: {exc}"
                ) from None
            sock.settimeout(0.1)
            self._sock = sock
            self.ended.clear()
            self.error = None
            if self.source is None:
                launch(self._receive, sock, sink)
                return
            cmd = self.tracker_command(self.address[1])
            _log.info("%s: starting tracker %s", self._id, " ".join(cmd))
            env = dict(os.environ, GLOG_minloglevel="2", TF_CPP_MIN_LOG_LEVEL="2", PYTHONUNBUFFERED="1")
            try:
                proc = subprocess.Popen(
                    cmd,
                    stdin=subprocess.DEVNULL,
                    stdout=subprocess.DEVNULL,
                    stderr=subprocess.PIPE,
                    env=env,
                )
            except OSError as exc:
                sock.close()
                self._sock = None
                raise DeviceError(f"cannot start the markerless tracker {cmd[0]}: {exc}") from None
            self._proc = proc
            stop = launch(self._receive, sock, sink)
            self._watcher = threading.Thread(
                target=self._watch,
                args=(proc, stop),
                name=f"telerig-markerless-{self._id}-watch",
                daemon=True,
            )
            self._watcher.start()

    def stop(self) -> None:
        """Stop the tracker process and the receiver, and close the socket. Idempotent."""
        self._worker.stop()  # first, so the watcher takes the tracker's exit as asked for
        sock, self._sock = self._sock, None
        proc, self._proc = self._proc, None
        watcher, self._watcher = self._watcher, None
        if proc is not None and proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(_STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        if watcher is not None and watcher is not threading.current_thread():
            watcher.join()
        if sock is not None:
            sock.close()

    def _count(self, key: str) -> None:
        with self._lock:
            self._stats[key] += 1

    def _stamp(self, source_id: str, header: protocol.Header, confidence: float) -> Stamp:
        # The seq is committed by _to_sample only once the sample was built.
        seq = self._seq.get(source_id, 0)
        return Stamp(source_id, seq, header.device_ns, header.capture_ns, confidence=confidence)

    def _fresh(self, source_id: str, frame: int) -> str | None:
        """None if ``frame`` is newer than the source's last; else the drop reason."""
        last = self._last_frame.get(source_id)
        if last is not None and frame <= last:
            return "duplicate_hand" if frame == last else "reordered"
        self._last_frame[source_id] = frame
        return None

    def _to_sample(self, msg: protocol.Message) -> Sample | None:
        if isinstance(msg, protocol.HandMessage):
            source_id = f"{self._id}/{msg.handedness}"
            reason = self._fresh(source_id, msg.header.frame)
            if reason is not None:
                self._count(reason)
                return None
            hand = protocol.hand_pose(msg, self._stamp(source_id, msg.header, msg.score), self.hand_frame_id)
            self._seq[source_id] = hand.stamp.seq + 1
            self._count("hands")
            return hand
        if isinstance(msg, protocol.PoseMessage):
            source_id = f"{self._id}/body"
            reason = self._fresh(source_id, msg.header.frame)
            if reason is not None:
                self._count("reordered")
                return None
            stamp = self._stamp(source_id, msg.header, protocol.body_confidence(msg))
            body = protocol.body_skeleton(msg, stamp, self.body_frame_id)
            self._seq[source_id] = stamp.seq + 1
            self._count("bodies")
            return body
        if isinstance(msg, protocol.FrameMessage):
            self._count("frames")
            self.last_processing_ms = msg.processing_ms
            return None
        self._count(f"event_{msg.code}")
        if msg.code == "started":
            # A (re)started tracker counts frames from 0 again.
            self._last_frame.clear()
            _log.info("%s: %s", self._id, msg.text)
        elif msg.code == "end":
            _log.info("%s: %s", self._id, msg.text)
            self.ended.set()
        else:
            _log.error("%s: tracker error: %s", self._id, msg.text)
            self.error = msg.text
            self.ended.set()
        return None

    def _receive(self, sock: socket.socket, sink: SampleSink, stop: threading.Event) -> None:
        while not stop.is_set():
            try:
                data = sock.recv(65536)
            except TimeoutError:
                continue
            except OSError:
                return
            try:
                sample = self._to_sample(protocol.decode(data))
            except WireError as exc:
                self._count("degenerate" if "degenerate" in str(exc) else "malformed")
                _log.debug("%s: dropped datagram: %s", self._id, exc)
                continue
            if sample is not None:
                self._worker.deliver(sink, sample)

    def _watch(self, proc: subprocess.Popen[bytes], stop: threading.Event) -> None:
        assert proc.stderr is not None
        with proc.stderr:
            for raw in proc.stderr:
                line = raw.decode("utf-8", errors="replace").rstrip()
                if line:
                    self._stderr_tail.append(line)
                    _log.debug("%s tracker: %s", self._id, line)
        code = proc.wait()
        if code != 0 and not stop.is_set():
            if self.error is None:
                tail = " | ".join(list(self._stderr_tail)[-3:])
                self.error = f"tracker exited with code {code}: {tail}"
            _log.error("%s: %s", self._id, self.error)
        self.ended.set()
