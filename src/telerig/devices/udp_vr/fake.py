"""A fake headset companion app: streams VrFrame datagrams of smooth motion over UDP, with impairments."""

from __future__ import annotations

import math
import random
import socket
import threading
import time
from collections.abc import Callable

import numpy as np

from telerig.devices.udp_vr.protocol import FORMAT_VERSION, OPENXR_HAND_JOINTS
from telerig.errors import ConfigError, DeviceError
from telerig.ir._pb import vr_stream_pb2 as pb
from telerig.ir.frames import quat_from_axis_angle, quat_multiply, quat_rotate
from telerig.ir.types import FloatArray

__all__ = ["FakeVrSender", "hand_joints", "typical_payload"]

_X = np.array([1.0, 0.0, 0.0])
_Y = np.array([0.0, 1.0, 0.0])
_IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])
# Finger bone lengths [m]: metacarpal, proximal, intermediate, distal (index .. little).
_FINGER_BONES = (
    (0.068, 0.040, 0.024, 0.020),
    (0.065, 0.044, 0.027, 0.021),
    (0.060, 0.041, 0.026, 0.020),
    (0.056, 0.033, 0.018, 0.018),
)
# Lateral offset of each finger's metacarpal base towards the thumb [m] (index .. little).
_FINGER_OFFSETS = (0.022, 0.007, -0.008, -0.022)
_THUMB_BONES = (0.045, 0.035, 0.030)


def hand_joints(hand: str, curl: float) -> tuple[FloatArray, FloatArray]:
    """The 26 XR_EXT_hand_tracking joints of a simple hand model in the wrist joint's frame.

    Wrist frame (OpenXR joint convention): -z towards the fingers, +y out of the back of the hand.

    Args:
        hand: ``"left"`` or ``"right"`` (the thumb is on the wrist frame's -x side of a right hand).
        curl: Finger flexion in [0, 1]: 0 flat open hand, 1 loose fist.

    Returns:
        Positions [m], shape (26, 3), and orientations (w, x, y, z), shape (26, 4), in
        XR_HAND_JOINT_* order.
    """
    side = -1.0 if hand == "right" else 1.0
    pos = np.zeros((len(OPENXR_HAND_JOINTS), 3))
    ori = np.tile(_IDENTITY, (len(OPENXR_HAND_JOINTS), 1))
    pos[0] = (0.0, 0.0, -0.045)  # palm centre
    # Thumb: from the CMC forward and out to the thumb side; curling swings it across the palm.
    thumb_yaw = -side * (0.7 - 0.9 * curl)
    q = quat_multiply(quat_from_axis_angle(_Y, thumb_yaw), quat_from_axis_angle(_X, -0.3 * curl))
    p = np.array([side * 0.025, -0.012, -0.015])
    for k, length in enumerate((*_THUMB_BONES, 0.0)):
        pos[2 + k], ori[2 + k] = p, q
        p = p + quat_rotate(q, np.array([0.0, 0.0, -length]))
        q = quat_multiply(q, quat_from_axis_angle(_X, -0.6 * curl))
    for f, (bones, offset) in enumerate(zip(_FINGER_BONES, _FINGER_OFFSETS, strict=True)):
        first = 6 + 5 * f
        p = np.array([side * offset, 0.0, -0.01])
        q = _IDENTITY
        for k, length in enumerate((*bones, 0.0)):
            pos[first + k], ori[first + k] = p, q
            p = p + quat_rotate(q, np.array([0.0, 0.0, -length]))
            # Flexion about the joint's +x axis, negative turns the tip towards the palm (-y).
            flex = 0.0 if k == 0 else (1.4, 1.6, 1.0, 0.0)[k - 1] * curl
            q = quat_multiply(q, quat_from_axis_angle(_X, -flex if k < 3 else 0.0))
    return pos, ori


def _set_pose(msg: pb.VrPose, position: FloatArray, q_wxyz: FloatArray) -> None:
    msg.px, msg.py, msg.pz = (float(c) for c in position)
    msg.qw, msg.qx, msg.qy, msg.qz = (float(c) for c in q_wxyz)


class FakeVrSender:
    """Plays a headset companion app on 127.0.0.1: smooth head, controller and hand motion.

    Motion, in OpenXR stage space (+y up, -z forward, metres): the head at 1.6 m turning gently;
    each controller circling (radius 5 cm, period ``cycle_s``) in front of the operator at waist
    height with the trigger following a sine and A (right) / X (left) held during the first
    quarter of each cycle; each hand opening and closing (curl 0..1) with the wrist swaying.

    Impairments, each an independent probability per datagram drawn from ``seed``: ``loss``
    (never sent), ``duplicate`` (sent twice), ``reorder`` (held back and sent after the next
    one) and ``garbage`` (an extra datagram of random bytes or a truncated frame). :attr:`stats`
    counts what was done. :meth:`datagram` is pure, for deterministic tests.
    """

    def __init__(
        self,
        port: int,
        host: str = "127.0.0.1",
        *,
        rate_hz: float = 90.0,
        loss: float = 0.0,
        reorder: float = 0.0,
        duplicate: float = 0.0,
        garbage: float = 0.0,
        seed: int = 0,
        stream_id: int | None = None,
        head: bool = True,
        controllers: bool = True,
        hands: bool = True,
        cycle_s: float = 4.0,
        device_clock: Callable[[], int] = time.monotonic_ns,
        device: str = "telerig FakeVrSender",
    ) -> None:
        """Args:
        port: UDP port of the receiver.
        host: Address of the receiver.
        rate_hz: Datagrams per second (> 0, <= 1000); headsets use 72, 90 or 120.
        loss: Probability a datagram is not sent, in [0, 1].
        reorder: Probability a datagram swaps places with the next one, in [0, 1].
        duplicate: Probability a datagram is sent twice, in [0, 1].
        garbage: Probability an invalid datagram is sent after it, in [0, 1].
        seed: Seed of the impairments and of the random stream id.
        stream_id: Stream id on the wire; None picks a random non-zero one from ``seed``.
        head: Send the head pose.
        controllers: Send both controllers.
        hands: Send both tracked hands.
        cycle_s: Period of the motion [s] (> 0).
        device_clock: The "headset" clock [ns] stamped as ``device_time_ns``; by default
            monotonic time, whose origin differs from the common clock as a headset's does.
        device: Device name on the wire.
        """
        if not (math.isfinite(rate_hz) and 0.0 < rate_hz <= 1000.0):
            raise ConfigError(f"rate_hz must be in (0, 1000], got {rate_hz}")
        if not (math.isfinite(cycle_s) and cycle_s > 0.0):
            raise ConfigError(f"cycle_s must be > 0 s, got {cycle_s}")
        for name, p in (("loss", loss), ("reorder", reorder), ("duplicate", duplicate), ("garbage", garbage)):
            if not 0.0 <= p <= 1.0:
                raise ConfigError(f"{name} must be a probability in [0, 1], got {p}")
        self.host, self.port = host, port
        self.rate_hz = float(rate_hz)
        self.loss, self.reorder, self.duplicate, self.garbage = loss, reorder, duplicate, garbage
        self._rng = random.Random(seed)
        self.stream_id = stream_id if stream_id is not None else self._rng.getrandbits(64) | 1
        self.head, self.controllers, self.hands = head, controllers, hands
        self.cycle_s = float(cycle_s)
        self.device_clock = device_clock
        self.device = device
        self.stats: dict[str, int] = dict.fromkeys(
            ("frames", "sent", "lost", "duplicated", "reordered", "garbage"), 0
        )
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._lock = threading.Lock()

    def frame(self, t_s: float, seq: int, device_ns: int | None = None) -> pb.VrFrame:
        """The frame ``t_s`` seconds into the motion; pure and deterministic.

        Args:
            t_s: Motion time [s].
            seq: Sequence number to put on the wire (>= 0).
            device_ns: ``device_time_ns`` on the wire; default ``round(t_s * 1e9)``.
        """
        msg = pb.VrFrame(
            format_version=FORMAT_VERSION,
            stream_id=self.stream_id,
            seq=seq,
            device_time_ns=round(t_s * 1e9) if device_ns is None else device_ns,
            device=self.device,
        )
        phase = 2.0 * math.pi * t_s / self.cycle_s
        if self.head:
            msg.head_tracked = True
            yaw = quat_from_axis_angle(_Y, 0.2 * math.sin(phase))
            _set_pose(msg.head, np.array([0.0, 1.6, 0.0]), yaw)
        if self.controllers:
            for hand, ctl, side in (("left", msg.left, -1.0), ("right", msg.right, 1.0)):
                ctl.tracked = True
                center = np.array([side * 0.25, 1.0, -0.35])
                offset = 0.05 * np.array([math.cos(phase), math.sin(phase), 0.0])
                # Pointing forward and 20 degrees down, rolling slightly with the motion.
                roll = quat_from_axis_angle(np.array([0.0, 0.0, 1.0]), 0.2 * side * math.sin(phase))
                q = quat_multiply(quat_from_axis_angle(_X, -0.35), roll)
                _set_pose(ctl.grip, center + offset, q)
                in_first_quarter = (t_s % self.cycle_s) < 0.25 * self.cycle_s
                bit = pb.VR_BUTTON_BIT_A if hand == "right" else pb.VR_BUTTON_BIT_X
                ctl.buttons = (1 << bit) if in_first_quarter else 0
                ctl.trigger = 0.5 - 0.5 * math.cos(phase)
                ctl.squeeze = 1.0
                ctl.thumbstick_x = 0.5 * math.sin(phase)
                ctl.thumbstick_y = 0.5 * math.cos(phase)
        if self.hands:
            curl = 0.5 - 0.5 * math.cos(phase)
            for hand, hmsg, side in (("left", msg.left_hand, -1.0), ("right", msg.right_hand, 1.0)):
                local_p, local_q = hand_joints(hand, curl)
                wrist_q = quat_from_axis_angle(_Y, 0.15 * math.sin(phase))
                wrist_p = np.array([side * 0.2, 1.05 + 0.03 * math.sin(phase), -0.3])
                world_p = wrist_p + np.array([quat_rotate(wrist_q, p) for p in local_p])
                world_q = np.array([quat_multiply(wrist_q, q) for q in local_q])
                hmsg.tracked = True
                hmsg.joint_positions.extend(world_p.reshape(-1).tolist())
                hmsg.joint_orientations.extend(world_q[:, [1, 2, 3, 0]].reshape(-1).tolist())
                hmsg.joint_radii.extend([0.008] * len(OPENXR_HAND_JOINTS))
        return msg

    def datagram(self, t_s: float, seq: int, device_ns: int | None = None) -> bytes:
        """:meth:`frame` serialized: one datagram's bytes."""
        return self.frame(t_s, seq, device_ns).SerializeToString()

    def send(self, data: bytes) -> None:
        """Send one raw datagram to the receiver now (opens the socket on first use)."""
        with self._lock:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            sock = self._sock
        sock.sendto(data, (self.host, self.port))
        self.stats["sent"] += 1

    @property
    def running(self) -> bool:
        """Whether the streaming thread is running."""
        thread = self._thread
        return thread is not None and thread.is_alive()

    def start(self) -> None:
        """Stream at ``rate_hz`` from a new thread until :meth:`stop`.

        Raises:
            DeviceError: If it is already streaming.
        """
        with self._lock:
            if self._thread is not None:
                raise DeviceError("FakeVrSender is already streaming; call stop() first")
            self._stop = threading.Event()
            self._thread = threading.Thread(
                target=self._run, args=(self._stop,), name="telerig-fake-vr-sender", daemon=True
            )
            self._thread.start()

    def stop(self) -> None:
        """Stop streaming and close the socket. Idempotent."""
        with self._lock:
            thread, self._thread = self._thread, None
            self._stop.set()
        if thread is not None and thread is not threading.current_thread():
            thread.join()
        with self._lock:
            sock, self._sock = self._sock, None
        if sock is not None:
            sock.close()

    def __enter__(self) -> FakeVrSender:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _garbage(self, valid: bytes) -> bytes:
        rng = self._rng
        if rng.random() < 0.5:
            return valid[: rng.randrange(1, max(2, len(valid)))]  # truncated frame
        return rng.randbytes(rng.randrange(1, 256))

    def _run(self, stop: threading.Event) -> None:
        period = 1.0 / self.rate_hz
        t0 = time.perf_counter()
        seq = 0
        held: bytes | None = None
        rng = self._rng
        while not stop.is_set():
            delay = t0 + seq * period - time.perf_counter()
            if delay > 0.0 and stop.wait(delay):
                break
            data = self.datagram(time.perf_counter() - t0, seq, self.device_clock())
            self.stats["frames"] += 1
            seq += 1
            out: list[bytes] = []
            if rng.random() < self.loss:
                self.stats["lost"] += 1
            elif held is None and rng.random() < self.reorder:
                held = data
                self.stats["reordered"] += 1
                continue
            else:
                out.append(data)
                if rng.random() < self.duplicate:
                    out.append(data)
                    self.stats["duplicated"] += 1
            if held is not None:
                out.append(held)
                held = None
            if rng.random() < self.garbage:
                out.append(self._garbage(data))
                self.stats["garbage"] += 1
            for d in out:
                try:
                    self.send(d)
                except OSError:
                    if stop.is_set():
                        return
                    raise


def typical_payload() -> bytes:
    """One typical datagram: head, both controllers and both hands tracked (about 1.9 KB)."""
    return FakeVrSender(0, stream_id=0x5EED).datagram(0.7, seq=1234, device_ns=5_000_000_000)
