"""Data glove device: a TCP client of a glove bridge, emitting ``HandPose`` samples and gestures."""

from __future__ import annotations

import logging
import math
import socket
import threading
import time
from collections.abc import Callable, Mapping

from telerig.devices.base import SampleSink
from telerig.devices.glove.gesture import Gesture, GestureThresholds, GestureTracker
from telerig.devices.glove.kinematics import HandModel, glove_hand_pose
from telerig.devices.glove.protocol import GloveFrame, GloveStreamDecoder
from telerig.devices.worker import DeviceWorker
from telerig.errors import ConfigError
from telerig.ir.clock import ClockOffsetEstimator
from telerig.ir.types import Handedness, Stamp, now_ns

__all__ = ["DEFAULT_PORT", "GestureCallback", "GloveDevice"]

_log = logging.getLogger(__name__)

#: Default TCP port of a telerig glove bridge.
DEFAULT_PORT = 47810

#: Called from the device thread when a hand's debounced gesture changes: (hand, gesture).
GestureCallback = Callable[[Handedness, Gesture], None]

_DECODER_KEYS = ("garbage_bytes", "header", "crc", "version", "values")


class GloveDevice:
    """Reads a glove bridge stream (see :mod:`.protocol`) and emits one ``HandPose`` per frame.

    Samples are in the ``"<hand>_glove"`` frame (see :mod:`.kinematics`), stamped with source id
    ``"<id>/<hand>"``, a per-source ``seq``, ``device_ns`` = the bridge's timestamp and
    ``capture_ns`` = ``device_ns`` + an offset estimated per connection as the windowed minimum of
    (arrival - device) (the bridge's clock is not the common clock), confidence = mean finger
    confidence. The connection is re-opened every ``reconnect_s`` after a failure, a disconnect or
    ``stale_timeout_s`` without bytes; garbage in the stream is skipped (resync on the magic).

    ``stats`` counts: ``frames`` (decoded), ``samples`` (delivered), ``connects``,
    ``connect_failures``, ``disconnects``, ``stale``, ``gaps`` (bridge frames missing by seq),
    ``garbage_bytes``, and drops per reason: ``drop_header``, ``drop_crc``, ``drop_version``,
    ``drop_values``, ``drop_hand`` (other hand than configured), ``drop_time`` (device timestamp
    not increasing), ``sink_errors``.

    Args:
        id: Device id.
        host: Bridge host.
        port: Bridge TCP port.
        hand: Accept only this hand's frames (None: both; a bridge may interleave two gloves).
        model: Hand geometry for the forward kinematics.
        use_measured_tips: Use the bridge's fingertip positions for the tip keypoints when present.
        gestures: Track gestures (:attr:`gesture`, ``on_gesture``).
        gesture_thresholds: Thresholds of the gesture trackers.
        gesture_hold_samples: Samples a new gesture must persist before it is reported.
        on_gesture: Called from the device thread when a hand's gesture changes; must not block.
        reconnect_s: Delay between connection attempts [s].
        connect_timeout_s: TCP connect timeout [s].
        stale_timeout_s: Reconnect after this long without bytes [s].
    """

    def __init__(
        self,
        id: str = "glove0",
        *,
        host: str = "127.0.0.1",
        port: int = DEFAULT_PORT,
        hand: Handedness | None = None,
        model: HandModel | None = None,
        use_measured_tips: bool = True,
        gestures: bool = True,
        gesture_thresholds: GestureThresholds | None = None,
        gesture_hold_samples: int = 3,
        on_gesture: GestureCallback | None = None,
        reconnect_s: float = 0.5,
        connect_timeout_s: float = 2.0,
        stale_timeout_s: float = 2.0,
    ) -> None:
        if hand not in (None, "left", "right"):
            raise ConfigError(f"hand must be 'left', 'right' or None, got {hand!r}")
        if not 0 < port < 65536:
            raise ConfigError(f"port must be in 1..65535, got {port}")
        for name, value in (
            ("reconnect_s", reconnect_s),
            ("connect_timeout_s", connect_timeout_s),
            ("stale_timeout_s", stale_timeout_s),
        ):
            if not (math.isfinite(value) and value > 0.0):
                raise ConfigError(f"{name} must be > 0 s, got {value}")
        self._id = id
        self.host = host
        self.port = port
        self.hand = hand
        self.model = model or HandModel.default()
        self.use_measured_tips = use_measured_tips
        self.reconnect_s = reconnect_s
        self.connect_timeout_s = connect_timeout_s
        self.stale_timeout_s = stale_timeout_s
        self.on_gesture = on_gesture
        thresholds = gesture_thresholds or GestureThresholds()
        self._trackers: dict[Handedness, GestureTracker] | None = (
            {h: GestureTracker(thresholds, hold_samples=gesture_hold_samples) for h in ("left", "right")}
            if gestures
            else None
        )
        self._stats: dict[str, int] = dict.fromkeys(
            (
                "frames",
                "connects",
                "connect_failures",
                "disconnects",
                "stale",
                "gaps",
                "garbage_bytes",
                *(f"drop_{k}" for k in _DECODER_KEYS[1:]),
                "drop_hand",
                "drop_time",
            ),
            0,
        )
        self._seq: dict[Handedness, int] = {"left": 0, "right": 0}
        self._lock = threading.Lock()  # guards _stats
        self._worker = DeviceWorker(id, kind="glove", thread_name=f"telerig-glove-{id}", log=_log)
        self._connected = threading.Event()

    @property
    def id(self) -> str:
        """Device id."""
        return self._id

    @property
    def stats(self) -> Mapping[str, int]:
        """A snapshot of the counters (see the class docstring)."""
        worker = self._worker
        with self._lock:
            stats = dict(self._stats)
        return {**stats, "samples": worker.samples - worker.sink_errors, "sink_errors": worker.sink_errors}

    @property
    def connected(self) -> bool:
        """Whether a bridge connection is open."""
        return self._connected.is_set()

    def gesture(self, hand: Handedness) -> Gesture:
        """The current debounced gesture of ``hand`` (NONE if gestures are off or no data yet)."""
        if self._trackers is None:
            return Gesture.NONE
        return self._trackers[hand].gesture

    def start(self, sink: SampleSink) -> None:
        """Connect (and keep reconnecting) on a new thread, delivering ``HandPose`` samples to ``sink``.

        Raises:
            DeviceError: If the device is already running.
        """
        self._worker.start(self._run, sink)

    def stop(self) -> None:
        """Close the connection and join the thread. Idempotent."""
        self._worker.stop()

    def _count(self, key: str, n: int = 1) -> None:
        with self._lock:
            self._stats[key] += n

    def _run(self, sink: SampleSink, stop: threading.Event) -> None:
        while not stop.is_set():
            try:
                sock = socket.create_connection((self.host, self.port), timeout=self.connect_timeout_s)
            except OSError as exc:
                self._count("connect_failures")
                _log.debug("%s: cannot connect to %s:%d (%s)", self._id, self.host, self.port, exc)
                stop.wait(self.reconnect_s)
                continue
            self._count("connects")
            _log.info("%s: connected to glove bridge %s:%d", self._id, self.host, self.port)
            self._connected.set()
            try:
                self._read(sock, sink, stop)
            finally:
                self._connected.clear()
                sock.close()
            if not stop.is_set():
                stop.wait(self.reconnect_s)

    def _read(self, sock: socket.socket, sink: SampleSink, stop: threading.Event) -> None:
        sock.settimeout(0.1)  # bounded so stop() is noticed promptly
        decoder = GloveStreamDecoder()
        clock = ClockOffsetEstimator(window_ns=2_000_000_000)
        last_seq: dict[Handedness, int] = {}
        last_device_ns: dict[Handedness, int] = {}
        last_bytes = time.monotonic()
        reported = dict.fromkeys(_DECODER_KEYS, 0)
        try:
            while not stop.is_set():
                try:
                    data = sock.recv(65536)
                except TimeoutError:
                    if time.monotonic() - last_bytes > self.stale_timeout_s:
                        self._count("stale")
                        _log.warning("%s: no data for %.1f s; reconnecting", self._id, self.stale_timeout_s)
                        return
                    continue
                except OSError as exc:
                    self._count("disconnects")
                    _log.info("%s: connection lost (%s)", self._id, exc)
                    return
                if not data:
                    self._count("disconnects")
                    _log.info("%s: bridge closed the connection", self._id)
                    return
                arrival = now_ns()
                last_bytes = time.monotonic()
                frames = decoder.feed(data)
                with self._lock:
                    for key in _DECODER_KEYS:
                        value = decoder.stats[key]
                        stat = key if key == "garbage_bytes" else f"drop_{key}"
                        self._stats[stat] += value - reported[key]
                        reported[key] = value
                    self._stats["frames"] += len(frames)
                for frame in frames:
                    self._deliver(frame, arrival, clock, last_seq, last_device_ns, sink)
        finally:
            if self._trackers is not None:
                for tracker in self._trackers.values():
                    tracker.reset()

    def _deliver(
        self,
        frame: GloveFrame,
        arrival: int,
        clock: ClockOffsetEstimator,
        last_seq: dict[Handedness, int],
        last_device_ns: dict[Handedness, int],
        sink: SampleSink,
    ) -> None:
        hand = frame.handedness
        if self.hand is not None and hand != self.hand:
            self._count("drop_hand")
            return
        previous = last_device_ns.get(hand)
        if previous is not None and frame.device_ns <= previous:
            self._count("drop_time")
            return
        last_device_ns[hand] = frame.device_ns
        prev_seq = last_seq.get(hand)
        if prev_seq is not None:
            gap = (frame.seq - prev_seq - 1) & 0xFFFFFFFF
            if 0 < gap < 1_000_000:
                self._count("gaps", gap)
        last_seq[hand] = frame.seq
        offset = clock.update(frame.device_ns, arrival)
        seq = self._seq[hand]
        self._seq[hand] = seq + 1
        stamp = Stamp(
            f"{self._id}/{hand}",
            seq,
            frame.device_ns,
            frame.device_ns + offset,
            arrival,
            float(frame.confidence.mean()),
        )
        sample = glove_hand_pose(frame, self.model, stamp, use_measured_tips=self.use_measured_tips)
        if self._trackers is not None:
            tracker = self._trackers[hand]
            tracker.update(sample)
            if tracker.changed and self.on_gesture is not None:
                try:
                    self.on_gesture(hand, tracker.gesture)
                except Exception:
                    _log.exception("%s: gesture callback raised; continuing", self._id)
        self._worker.deliver(sink, sample)
