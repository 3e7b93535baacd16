"""A fake glove bridge: a local TCP server streaming the telerig glove bridge format (public test utility)."""

from __future__ import annotations

import logging
import math
import random
import socket
import threading
import time
from types import TracebackType

import numpy as np

from telerig.bus.peer_loop import accept_loop
from telerig.devices.glove.gesture import Gesture
from telerig.devices.glove.kinematics import HandModel
from telerig.devices.glove.protocol import GloveFrame, encode_frame
from telerig.devices.worker import wait_until
from telerig.errors import ConfigError
from telerig.ir.types import FloatArray, Handedness

__all__ = ["GESTURE_KEYFRAMES", "FakeGloveBridge", "typical_payload"]

_log = logging.getLogger(__name__)

_EXT = (0.0, 0.05, 0.05, 0.05)
_CURLED = (0.0, 1.5, 1.7, 0.9)
_RELAXED = (0.0, 0.2, 0.2, 0.1)
_THUMB_TUCKED = (-0.2, 0.5, 0.6, 0.4)

#: Joint angles [rad] of each gesture the fake cycles through, rows thumb..little. Shape (5, 4) each.
GESTURE_KEYFRAMES: dict[Gesture, tuple[tuple[float, float, float, float], ...]] = {
    Gesture.OPEN: ((0.2, 0.0, 0.1, 0.1), (0.05, 0.05, 0.05, 0.05), _EXT, (-0.05, 0.05, 0.05, 0.05),
                   (-0.1, 0.05, 0.05, 0.05)),
    Gesture.FIST: (_THUMB_TUCKED, _CURLED, _CURLED, _CURLED, _CURLED),
    Gesture.POINT: (_THUMB_TUCKED, _EXT, _CURLED, _CURLED, _CURLED),
    Gesture.PINCH: ((0.1, 0.7, 0.2, 0.2), (0.0, 0.6, 0.7, 0.4), _RELAXED, _RELAXED, _RELAXED),
}  # fmt: skip
_CYCLE = (Gesture.OPEN, Gesture.FIST, Gesture.POINT, Gesture.PINCH)
_KEYS = [np.array(GESTURE_KEYFRAMES[g]) for g in _CYCLE]


def _min_jerk(u: float) -> float:
    u = 0.0 if u < 0.0 else 1.0 if u > 1.0 else u
    return u * u * u * (10.0 + u * (-15.0 + 6.0 * u))


class FakeGloveBridge:
    """A glove bridge on 127.0.0.1 that streams smooth finger motion cycling open, fist, point, pinch.

    Each gesture is held for ``dwell_s`` then blends into the next over ``transition_s`` (minimum
    jerk), with a small breathing wiggle. Every accepted client gets its own stream from frame 0.
    Faults, for tests: ``garbage_every`` inserts random garbage (containing a partial magic) after
    every N-th frame; ``corrupt_every`` flips a byte of every N-th frame (CRC failure);
    ``disconnect_after`` closes each connection after N frames (the client must reconnect).

    Args:
        hand: Handedness streamed.
        rate_hz: Frame rate [Hz].
        port: TCP port (0 picks a free one; read :attr:`port`).
        fingertips: Include fingertip positions (from the default hand model) in each frame.
        wrist: Include wrist angles (a slow wave) in each frame.
        dwell_s: Hold time of each gesture [s].
        transition_s: Blend time between gestures [s].
        seed: Seed of the garbage generator.
    """

    def __init__(
        self,
        *,
        hand: Handedness = "right",
        rate_hz: float = 120.0,
        port: int = 0,
        fingertips: bool = True,
        wrist: bool = False,
        dwell_s: float = 0.6,
        transition_s: float = 0.4,
        garbage_every: int = 0,
        corrupt_every: int = 0,
        disconnect_after: int = 0,
        seed: int = 0,
    ) -> None:
        if not (math.isfinite(rate_hz) and 0.0 < rate_hz <= 2000.0):
            raise ConfigError(f"rate_hz must be in (0, 2000], got {rate_hz}")
        if dwell_s < 0.0 or transition_s <= 0.0:
            raise ConfigError(f"dwell_s must be >= 0 and transition_s > 0, got {dwell_s}, {transition_s}")
        self.hand: Handedness = hand
        self.rate_hz = float(rate_hz)
        self.fingertips = fingertips
        self.wrist = wrist
        self.dwell_s = float(dwell_s)
        self.transition_s = float(transition_s)
        self.garbage_every = garbage_every
        self.corrupt_every = corrupt_every
        self.disconnect_after = disconnect_after
        self._model = HandModel.default()
        self._rng = random.Random(seed)
        self._requested_port = port
        self._sock: socket.socket | None = None
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._lock = threading.Lock()
        self.frames_sent = 0
        self.connections = 0
        self.garbage_bytes_sent = 0
        self.corrupted_frames = 0

    # -- pure trajectory --------------------------------------------------------------------

    @property
    def cycle_s(self) -> float:
        """Duration of one open -> fist -> point -> pinch cycle [s]."""
        return len(_CYCLE) * (self.dwell_s + self.transition_s)

    def gesture_at(self, t_s: float) -> Gesture:
        """The gesture held at ``t_s``, or NONE during a transition."""
        step = self.dwell_s + self.transition_s
        k, r = divmod(t_s % self.cycle_s, step)
        return _CYCLE[int(k) % len(_CYCLE)] if r < self.dwell_s else Gesture.NONE

    def angles_at(self, t_s: float) -> FloatArray:
        """Joint angles [rad] at ``t_s`` seconds after the stream start. Shape (5, 4)."""
        step = self.dwell_s + self.transition_s
        k, r = divmod(t_s % self.cycle_s, step)
        i = int(k) % len(_KEYS)
        a, b = _KEYS[i], _KEYS[(i + 1) % len(_KEYS)]
        s = _min_jerk((r - self.dwell_s) / self.transition_s)
        angles: FloatArray = a + s * (b - a)
        wiggle = 0.02 * math.sin(2.0 * math.pi * 0.5 * t_s)
        angles[:, 1] += wiggle
        return angles

    def frame_at(self, t_s: float, seq: int = 0, device_ns: int = 0) -> GloveFrame:
        """The frame streamed at ``t_s`` seconds (pure; the stream stamps real clocks)."""
        angles = self.angles_at(t_s)
        wrist = None
        if self.wrist:
            wrist = np.array(
                [0.3 * math.sin(2.0 * math.pi * 0.2 * t_s), 0.1 * math.sin(2.0 * math.pi * 0.3 * t_s)]
            )
        tips = None
        if self.fingertips:
            kp = self._model.keypoints(angles, self.hand)
            tips = kp[[4, 8, 12, 16, 20]] * 1e3
        conf = np.full(5, 0.95)
        return GloveFrame(seq, device_ns, self.hand, angles, wrist, tips, conf)

    # -- server -----------------------------------------------------------------------------

    @property
    def port(self) -> int:
        """The listening TCP port (valid after :meth:`start`)."""
        if self._sock is None:
            raise ConfigError("the fake glove bridge is not started; call start() first")
        return int(self._sock.getsockname()[1])

    @property
    def address(self) -> tuple[str, int]:
        """(host, port) to connect to."""
        return ("127.0.0.1", self.port)

    def start(self) -> FakeGloveBridge:
        """Listen on 127.0.0.1 and serve clients from a background thread."""
        with self._lock:
            if self._sock is not None:
                return self
            sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind(("127.0.0.1", self._requested_port))
            sock.listen(4)
            sock.settimeout(0.05)
            self._sock = sock
            self._stop.clear()
            thread = threading.Thread(
                target=accept_loop,
                args=(sock, self._stop, self._client),
                name="telerig-fake-glove",
                daemon=True,
            )
            self._threads.append(thread)
            thread.start()
        return self

    def stop(self) -> None:
        """Close the server and every client connection; idempotent."""
        with self._lock:
            self._stop.set()
            threads, self._threads = self._threads, []
        for thread in threads:
            thread.join()
        with self._lock:
            if self._sock is not None:
                self._sock.close()
                self._sock = None

    def __enter__(self) -> FakeGloveBridge:
        return self.start()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()

    def _client(self, conn: socket.socket, address: tuple[str, int]) -> None:
        with self._lock:
            self.connections += 1
            thread = threading.Thread(target=self._serve, args=(conn,), name="telerig-fake-glove-client")
            thread.daemon = True
            self._threads.append(thread)
        thread.start()

    def _garbage(self) -> bytes:
        n = self._rng.randint(1, 40)
        junk = bytes(self._rng.getrandbits(8) for _ in range(n))
        return junk + b"TG" + junk[: n // 2]  # a partial magic to exercise resync

    def _serve(self, conn: socket.socket) -> None:
        period = 1.0 / self.rate_hz
        t0 = time.perf_counter()
        k = 0
        try:
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            while not self._stop.is_set():
                if wait_until(t0 + k * period, self._stop):
                    return
                data = bytearray(
                    encode_frame(self.frame_at(k * period, seq=k, device_ns=time.monotonic_ns()))
                )
                k += 1
                if self.corrupt_every and k % self.corrupt_every == 0:
                    data[len(data) // 2] ^= 0x5A
                    self.corrupted_frames += 1
                if self.garbage_every and k % self.garbage_every == 0:
                    junk = self._garbage()
                    data += junk
                    self.garbage_bytes_sent += len(junk)
                conn.sendall(data)
                self.frames_sent += 1
                if self.disconnect_after and k >= self.disconnect_after:
                    return
        except OSError as exc:
            _log.debug("fake glove bridge: client went away (%s)", exc)
        finally:
            conn.close()


def typical_payload() -> bytes:
    """One typical frame (right hand, 20 angles, fingertips): what a bridge sends 120 times a second."""
    return encode_frame(FakeGloveBridge().frame_at(1.3, seq=156, device_ns=1_000_000_000))
