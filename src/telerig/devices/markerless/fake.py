"""A fake markerless tracker: sends real wire-v1 datagrams to a device on 127.0.0.1 (tests, dry runs)."""

from __future__ import annotations

import math
import socket
import time
from pathlib import Path

import numpy as np
import numpy.typing as npt

from telerig.devices.markerless import tracker
from telerig.ir.types import FloatArray, Handedness

__all__ = [
    "FakeTracker",
    "operator_to_mediapipe",
    "synthetic_hand_frame",
    "typical_hand",
    "typical_payload",
    "typical_pose",
    "write_synthetic_video",
]


def operator_to_mediapipe(points: npt.ArrayLike) -> FloatArray:
    """Operator axes (x forward, y left, z up) (N, 3) → MediaPipe image axes of an unmirrored camera."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    return np.column_stack((p[:, 1], -p[:, 2], -p[:, 0]))


def typical_hand(handedness: Handedness = "right") -> FloatArray:
    """A relaxed flat hand, palm down, fingers forward; operator axes around its centre [m]. Shape (21, 3)."""
    side = 1.0 if handedness == "right" else -1.0  # the thumb is on the operator's left for a right hand
    pts = [(-0.08, 0.0, 0.0)]
    pts += [(-0.06, 0.025, -0.005), (-0.04, 0.045, -0.01), (-0.02, 0.06, -0.012), (0.0, 0.07, -0.012)]
    for y, lengths in ((0.025, (0.035, 0.025, 0.02)), (0.008, (0.04, 0.028, 0.022))):
        x = 0.0
        pts.append((x, y, 0.0))
        for length in lengths:
            x += length
            pts.append((x, y, -0.004))
    for y, lengths in ((-0.01, (0.037, 0.026, 0.02)), (-0.027, (0.03, 0.02, 0.018))):
        x = -0.005
        pts.append((x, y, 0.0))
        for length in lengths:
            x += length
            pts.append((x, y, -0.004))
    out = np.array(pts)
    out[:, 1] *= side
    return out


def typical_pose() -> FloatArray:
    """A person standing, arms down, facing the camera: 33 rows (x, y, z [m] operator axes around
    the hips' midpoint, visibility, presence), in MediaPipe landmark order. Shape (33, 5)."""
    half = {
        "eye_inner": (0.08, 0.015, 0.66),
        "eye": (0.07, 0.035, 0.66),
        "eye_outer": (0.06, 0.05, 0.66),
        "ear": (0.0, 0.075, 0.63),
        "mouth": (0.08, 0.025, 0.58),
        "shoulder": (0.0, 0.18, 0.5),
        "elbow": (0.02, 0.22, 0.24),
        "wrist": (0.06, 0.24, 0.02),
        "pinky": (0.07, 0.25, -0.06),
        "index": (0.09, 0.24, -0.07),
        "thumb": (0.09, 0.22, -0.03),
        "hip": (0.0, 0.1, 0.0),
        "knee": (0.02, 0.1, -0.45),
        "ankle": (0.0, 0.1, -0.88),
        "heel": (-0.04, 0.1, -0.92),
        "foot_index": (0.12, 0.1, -0.95),
    }
    from telerig.devices.markerless.protocol import POSE_JOINTS

    rows = []
    for name in POSE_JOINTS:
        if name == "nose":
            xyz, vis = (0.1, 0.0, 0.62), 0.99
        else:
            side, _, part = name.partition("_")
            if part in {"left", "right"}:  # "mouth_left" / "mouth_right"
                side, part = part, side
            x, y, z = half[part]
            xyz = (x, y if side == "left" else -y, z)
            vis = 0.5 if part in ("knee", "ankle", "heel", "foot_index") else 0.98
        rows.append((*xyz, vis, 0.99))
    return np.array(rows)


class FakeTracker:
    """Sends wire-v1 datagrams to ``address`` as the MediaPipe tracker would (unmirrored camera).

    Positions are given in operator axes and converted to MediaPipe's raw image axes and labels,
    so a device receiving them must give back what was put in.
    """

    def __init__(
        self, address: tuple[str, int], *, mirrored: bool = False, width: int = 640, height: int = 480
    ):
        self.address = address
        self.mirrored = mirrored
        self.width = width
        self.height = height
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)

    def close(self) -> None:
        """Close the socket. Idempotent."""
        self._sock.close()

    def __enter__(self) -> FakeTracker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def header(
        self, kind: int, frame: int, capture_ns: int | None = None, device_ns: int | None = None
    ) -> bytes:
        """A header for ``frame`` captured at ``capture_ns`` (default now) [ns]."""
        capture = time.time_ns() if capture_ns is None else capture_ns
        return tracker.encode_header(
            kind,
            capture_ns=capture,
            device_ns=frame * 33_333_333 if device_ns is None else device_ns,
            frame=frame,
            width=self.width,
            height=self.height,
            mirrored=self.mirrored,
        )

    def _mediapipe(self, points: npt.ArrayLike) -> FloatArray:
        mp = operator_to_mediapipe(points)
        if self.mirrored:
            mp[:, 0] = -mp[:, 0]
        return mp

    def hand_bytes(
        self,
        frame: int,
        handedness: Handedness = "right",
        keypoints: npt.ArrayLike | None = None,
        score: float = 0.95,
        capture_ns: int | None = None,
    ) -> bytes:
        """A hand datagram; ``keypoints`` (21, 3) [m] in operator axes (default :func:`typical_hand`)."""
        pts = typical_hand(handedness) if keypoints is None else keypoints
        # MediaPipe labels as if mirrored: the operator's right hand is "Left" on an unmirrored image.
        label = int((handedness == "right") == self.mirrored)
        head = self.header(tracker.KIND_HAND, frame, capture_ns)
        return tracker.encode_hand(head, label, 0, score, self._mediapipe(pts), [score] * tracker.HAND_POINTS)

    def pose_bytes(
        self, frame: int, rows: npt.ArrayLike | None = None, capture_ns: int | None = None
    ) -> bytes:
        """A pose datagram; ``rows`` (33, 5) as in :func:`typical_pose` (operator axes, person's sides)."""
        r = np.array(typical_pose() if rows is None else rows, dtype=np.float64).reshape(
            tracker.POSE_POINTS, 5
        )
        if self.mirrored:
            from telerig.devices.markerless.protocol import _MIRROR_PERM

            r = r[_MIRROR_PERM]
        wire = np.column_stack((self._mediapipe(r[:, :3]), r[:, 3:]))
        return tracker.encode_pose(self.header(tracker.KIND_POSE, frame, capture_ns), wire)

    def send(self, data: bytes) -> None:
        """Send one raw datagram."""
        self._sock.sendto(data, self.address)

    def send_frame(self, frame: int, hands: tuple[Handedness, ...] = ("right",), pose: bool = True) -> None:
        """Send one frame's worth: its hands, its body, then the frame summary."""
        capture = time.time_ns()
        for hand in hands:
            self.send(self.hand_bytes(frame, hand, capture_ns=capture))
        if pose:
            self.send(self.pose_bytes(frame, capture_ns=capture))
        head = self.header(tracker.KIND_FRAME, frame, capture)
        self.send(tracker.encode_frame(head, len(hands), int(pose), 12.5))

    def send_event(self, code: int, text: str) -> None:
        """Send a lifecycle event (``tracker.EVENT_STARTED`` / ``EVENT_END`` / ``EVENT_ERROR``)."""
        self.send(tracker.encode_event(self.header(tracker.KIND_EVENT, 0), code, text))


def typical_payload() -> bytes:
    """One typical message: a right hand datagram (344 bytes)."""
    with FakeTracker(("127.0.0.1", 9)) as fake:
        return fake.hand_bytes(1, "right", capture_ns=1_700_000_000_000_000_000)


def _segment_distance(
    px: FloatArray, py: FloatArray, a: tuple[float, float], b: tuple[float, float]
) -> FloatArray:
    dx, dy = b[0] - a[0], b[1] - a[1]
    t = np.clip(((px - a[0]) * dx + (py - a[1]) * dy) / (dx * dx + dy * dy), 0.0, 1.0)
    return np.asarray(np.hypot(px - (a[0] + t * dx), py - (a[1] + t * dy)))


def synthetic_hand_frame(
    t: float = 0.0, *, width: int = 640, height: int = 480, center: tuple[float, float] = (320.0, 300.0)
) -> npt.NDArray[np.uint8]:
    """A drawn open hand (palm, four fingers, thumb) on a shaded background, RGB (height, width, 3).

    Not a photograph, but MediaPipe 0.10.21's palm detector does find it, which is what the
    end-to-end test needs without downloading footage. The fingers wave slowly with ``t`` [s];
    the hand (about 200 x 260 px) must lie inside the frame.
    """
    cx, cy = center
    x0, y0 = int(cx) - 140, int(cy) - 200
    if x0 < 0 or y0 < 0 or x0 + 240 > width or y0 + 280 > height:
        raise ValueError(f"center {center} puts the hand outside a {width}x{height} frame")
    # Draw in a 240 x 280 px box around the hand; the rest is a horizontal shading.
    yy, xx = np.mgrid[y0 : y0 + 280, x0 : x0 + 240].astype(np.float32)
    mask = ((xx - cx) / 62.0) ** 2 + ((yy - (cy - 20.0)) / 70.0) ** 2 <= 1.0
    v = (cy - yy) / 95.0
    mask |= (v >= 0.0) & (v <= 1.0) & (np.abs(xx - cx) <= 55.0 + 5.0 * v)
    for base_x, length, tilt_deg in (
        (-45.0, 70.0, -12.0),
        (-15.0, 85.0, -4.0),
        (15.0, 80.0, 4.0),
        (42.0, 62.0, 12.0),
    ):
        a = np.radians(tilt_deg + 5.0 * np.sin(np.pi * t))
        root = (cx + base_x, cy - 90.0)
        tip = (root[0] + np.sin(a) * length, root[1] - np.cos(a) * length)
        mask |= _segment_distance(xx, yy, root, tip) <= 12.0
    mask |= _segment_distance(xx, yy, (cx - 55.0, cy - 20.0), (cx - 110.0, cy - 65.0)) <= 13.0
    shade = (0.7 + 0.6 * np.arange(width, dtype=np.float32) / width)[None, :, None]
    img = np.broadcast_to(np.array([40.0, 60.0, 90.0], np.float32) * shade, (height, width, 3)).copy()
    box = img[y0 : y0 + 280, x0 : x0 + 240]
    box[mask] = (120.0, 160.0, 220.0)
    kernel = np.array([1.0, 4.0, 6.0, 4.0, 1.0], np.float32) / 16.0  # the detector wants soft edges
    for axis in (0, 1):
        blurred = np.zeros_like(box)
        for i, k in enumerate(kernel):
            blurred += np.roll(box, i - 2, axis=axis) * k
        box = blurred
    img[y0 + 2 : y0 + 278, x0 + 2 : x0 + 238] = box[2:-2, 2:-2]
    noise = np.random.default_rng(round(t * 1000)).integers(-6, 7, img.shape, dtype=np.int16)
    return np.asarray((img + noise).clip(0, 255), dtype=np.uint8)


def write_synthetic_video(path: str | Path, frames: int = 30, fps: int = 30) -> Path:
    """Write ``frames`` frames of :func:`synthetic_hand_frame` (swaying sideways) as H.264 MP4.

    Needs PyAV (telerig's ``record`` extra). Returns ``path``.
    """
    import av

    out = Path(path)
    with av.open(str(out), "w") as container:
        stream = container.add_stream("libx264", rate=fps)
        stream.width, stream.height, stream.pix_fmt = 640, 480, "yuv420p"
        stream.options = {"preset": "ultrafast", "crf": "18"}
        for k in range(frames):
            img = synthetic_hand_frame(k / fps, center=(320.0 + 60.0 * math.sin(k / fps), 300.0))
            for packet in stream.encode(av.VideoFrame.from_ndarray(img, format="rgb24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    return out
