"""The MediaPipe tracker process: video frames in, landmark datagrams (markerless wire v1) out over UDP.

This file runs as a script in its own virtual environment (``.venv-markerless``), because
``mediapipe==0.10.21`` pins ``numpy<2`` and ``protobuf<5`` while telerig pins numpy 2 and
protobuf 7. It therefore imports only the standard library and NumPy at module level (MediaPipe
and PyAV are imported inside :func:`main`) and never imports telerig; telerig imports the wire
layout and encoders below from it.

Wire format v1, little endian, one message per UDP datagram::

    header (32 bytes)  magic b"TRMK" | version u8 = 1 | kind u8 | flags u16 | capture_ns i64 |
                       device_ns i64 | frame u32 | width u16 | height u16
    kind 1 hand        label u8 (MediaPipe's: 0 "Left", 1 "Right") | index u8 | 2 pad |
                       score f32 | 21 x (x, y, z) f32 world landmarks [m] | 21 f32 confidence
    kind 2 pose        33 x (x, y, z, visibility, presence) f32 world landmarks [m]
    kind 3 frame       hands u8 | poses u8 | 2 pad | processing time f32 [ms]
    kind 4 event       code u8 (0 started, 1 end of stream, 2 error) | 3 pad | UTF-8 text
    kind 5 hand image  label u8 | index u8 | 2 pad | score f32 | 21 x (x, y) f32 image landmarks
                       (fractions of the frame's width and height; batch mode only)

flags bit 0: the frames were a mirror image (selfie preview). Landmarks are MediaPipe's raw world
landmarks (image-aligned axes: x right, y down, z away from the camera; hands around the hand's
centre, pose around the hips' midpoint) and labels are MediaPipe's raw labels; telerig converts
them (``telerig.devices.markerless.protocol``). ``frame`` counts decoded frames from 0;
``device_ns`` is the frame's presentation time in the source's own clock [ns]; ``capture_ns`` the
capture time in the common clock (``time.time_ns()``) [ns]: for a V4L2 camera the kernel's
monotonic buffer timestamp shifted onto the wall clock, for a file ``start_ns`` plus the frame's
presentation time after the first frame.

Batch mode (``--stdin-frames``, the annotation pipeline's hand filter): the tracker reads raw RGB
frames from stdin, each an ``INPUT_FRAME`` header (magic b"TRFR" | frame u32 | width u16 |
height u16 | device_ns i64) followed by width x height x 3 bytes, and writes the same messages to
stdout, each prefixed by its length (u16): a started event, per frame its kind 5 hand messages then
its kind 3 frame summary (``frame`` and ``device_ns`` echo the input's), and an end event at the
end of stdin. Nothing is paced or dropped: the caller decides which frames to send (subsampling).
"""

from __future__ import annotations

import argparse
import concurrent.futures
import importlib
import json
import socket
import struct
import sys
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

MAGIC = b"TRMK"
VERSION = 1
KIND_HAND = 1
KIND_POSE = 2
KIND_FRAME = 3
KIND_EVENT = 4
KIND_HAND_IMAGE = 5
FLAG_MIRRORED = 1

EVENT_STARTED = 0
EVENT_END = 1
EVENT_ERROR = 2

HAND_POINTS = 21
POSE_POINTS = 33

HEADER = struct.Struct("<4sBBHqqIHH")
HAND_HEAD = struct.Struct("<BBxxf")
FRAME_BODY = struct.Struct("<BBxxf")
EVENT_HEAD = struct.Struct("<Bxxx")
HAND_SIZE = HEADER.size + HAND_HEAD.size + HAND_POINTS * 4 * 4
POSE_SIZE = HEADER.size + POSE_POINTS * 5 * 4
FRAME_SIZE = HEADER.size + FRAME_BODY.size
HAND_IMAGE_SIZE = HEADER.size + HAND_HEAD.size + HAND_POINTS * 2 * 4
INPUT_MAGIC = b"TRFR"
INPUT_FRAME = struct.Struct("<4sIHHq")
#: Largest frame side batch mode accepts [px] (bounds what one header can make the tracker read).
MAX_INPUT_SIDE = 4096
OUTPUT_LENGTH = struct.Struct("<H")
MAX_EVENT_TEXT = 1000


def encode_header(
    kind: int, *, capture_ns: int, device_ns: int, frame: int, width: int, height: int, mirrored: bool
) -> bytes:
    """The 32-byte header of every message."""
    return HEADER.pack(
        MAGIC, VERSION, kind, FLAG_MIRRORED if mirrored else 0, capture_ns, device_ns, frame, width, height
    )


def encode_hand(
    header: bytes, label: int, index: int, score: float, world: npt.ArrayLike, confidence: npt.ArrayLike
) -> bytes:
    """A hand message: ``world`` (21, 3) [m] MediaPipe world landmarks, ``confidence`` (21,) in [0, 1]."""
    w = np.asarray(world, dtype="<f4").reshape(HAND_POINTS, 3)
    c = np.asarray(confidence, dtype="<f4").reshape(HAND_POINTS)
    return header + HAND_HEAD.pack(label, index, score) + w.tobytes() + c.tobytes()


def encode_hand_image(header: bytes, label: int, index: int, score: float, points: npt.ArrayLike) -> bytes:
    """A hand's image landmarks (kind 5): ``points`` (21, 2) as fractions of the frame's width, height."""
    p = np.asarray(points, dtype="<f4").reshape(HAND_POINTS, 2)
    return header + HAND_HEAD.pack(label, index, score) + p.tobytes()


def encode_input_frame(frame: int, rgb: npt.NDArray[np.uint8], device_ns: int = 0) -> bytes:
    """One batch-mode input record: header and the (height, width, 3) RGB pixels."""
    h, w = rgb.shape[:2]
    return INPUT_FRAME.pack(INPUT_MAGIC, frame, w, h, device_ns) + np.ascontiguousarray(rgb).tobytes()


def encode_pose(header: bytes, landmarks: npt.ArrayLike) -> bytes:
    """A pose message: ``landmarks`` (33, 5) rows (x, y, z [m], visibility, presence)."""
    return header + np.asarray(landmarks, dtype="<f4").reshape(POSE_POINTS, 5).tobytes()


def encode_frame(header: bytes, hands: int, poses: int, processing_ms: float) -> bytes:
    """A frame summary, sent after the frame's hand and pose messages."""
    return header + FRAME_BODY.pack(hands, poses, processing_ms)


def encode_event(header: bytes, code: int, text: str) -> bytes:
    """A lifecycle event (started, end of stream, error) with a one-line text."""
    return header + EVENT_HEAD.pack(code) + text.encode("utf-8")[:MAX_EVENT_TEXT]


# ---------------------------------------------------------------------------------------------
# The tracker loop (runs only in the MediaPipe venv).


class _Clock:
    """Maps a frame's presentation time [ns] onto the common clock [ns]."""

    def __init__(self, live: bool, start_ns: int) -> None:
        self.live = live
        self.start_ns = start_ns
        self.first_pts_ns: int | None = None

    def capture_ns(self, pts_ns: int | None) -> int:
        now = time.time_ns()
        if self.live:
            # V4L2 buffers carry CLOCK_MONOTONIC timestamps; shift them onto the wall clock.
            # Anything implausible (another clock, missing pts) falls back to the receive time.
            if pts_ns is not None:
                mono_now = time.monotonic_ns()
                if 0 <= mono_now - pts_ns < 1_000_000_000:
                    return now - (mono_now - pts_ns)
            return now
        if pts_ns is None:
            return now
        if self.first_pts_ns is None:
            self.first_pts_ns = pts_ns
        return self.start_ns + (pts_ns - self.first_pts_ns)


def _open(av: Any, source: str, args: argparse.Namespace) -> Any:
    if source.startswith("/dev/video"):
        options = {"video_size": f"{args.width}x{args.height}", "framerate": f"{args.fps:g}"}
        if args.input_format:
            options["input_format"] = args.input_format
        return av.open(source, format="v4l2", options=options)
    return av.open(source)


def _landmark_rows(landmarks: Any, with_scores: bool) -> list[tuple[float, ...]]:
    if with_scores:
        return [(p.x, p.y, p.z, p.visibility, p.presence) for p in landmarks.landmark]
    return [(p.x, p.y, p.z) for p in landmarks.landmark]


def run(args: argparse.Namespace) -> int:
    """Track ``args.source`` until it ends or the process is terminated; return the exit code."""
    host, _, port = (args.send_to or "127.0.0.1:9").rpartition(":")
    dest = (host, int(port))
    timings_ms: list[float] = []
    cpu_ms: list[float] = []
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    live = args.source.startswith("/dev/video")
    mirrored = bool(args.mirrored)

    def header(kind: int, frame: int = 0, capture: int = 0, device: int = 0, w: int = 0, h: int = 0) -> bytes:
        return encode_header(
            kind, capture_ns=capture, device_ns=device, frame=frame, width=w, height=h, mirrored=mirrored
        )

    def event(code: int, text: str) -> None:
        if args.bench:
            print(text, file=sys.stderr)
            return
        sock.sendto(encode_event(header(KIND_EVENT, capture=time.time_ns()), code, text), dest)

    try:
        av = importlib.import_module("av")
        mp = importlib.import_module("mediapipe")
    except ImportError as exc:
        event(EVENT_ERROR, f"tracker venv lacks {exc.name}; install mediapipe==0.10.21 av==18.1.0 into it")
        return 2
    hands = (
        mp.solutions.hands.Hands(
            static_image_mode=False,
            max_num_hands=args.max_hands,
            model_complexity=args.hand_model_complexity,
            min_detection_confidence=args.min_detection_confidence,
            min_tracking_confidence=args.min_tracking_confidence,
        )
        if args.hands
        else None
    )
    # Only the "full" pose landmark model ships inside the wheel (complexity 1); 0 and 2 download.
    pose = (
        mp.solutions.pose.Pose(
            static_image_mode=False,
            model_complexity=1,
            smooth_landmarks=True,
            min_detection_confidence=args.min_detection_confidence,
            min_tracking_confidence=args.min_tracking_confidence,
        )
        if args.pose
        else None
    )
    pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="pose")
    frame_index = 0
    w = h = 0
    while True:
        try:
            container = _open(av, args.source, args)
        except Exception as exc:
            event(EVENT_ERROR, f"cannot open video source {args.source!r}: {exc}")
            return 3
        event(EVENT_STARTED, f"tracking {args.source}")
        clock = _Clock(live, args.start_ns or time.time_ns())
        stream = container.streams.video[0]
        stream.thread_type = "AUTO"
        t_wall0 = time.monotonic_ns()
        try:
            for frame in container.decode(stream):
                pts_ns = None
                if frame.pts is not None and frame.time_base is not None:
                    pts_ns = int(frame.pts * frame.time_base * 1_000_000_000)
                capture = clock.capture_ns(pts_ns)
                if args.realtime and not live and clock.first_pts_ns is not None and pts_ns is not None:
                    # Pace file playback like a camera: frame k is due first_pts + pts after start.
                    due = t_wall0 + (pts_ns - clock.first_pts_ns)
                    delay = due - time.monotonic_ns()
                    if delay > 0:
                        time.sleep(delay / 1e9)
                t0 = time.perf_counter()
                c0 = time.process_time()
                rgb = frame.to_ndarray(format="rgb24")
                h, w = rgb.shape[:2]
                head = header(0, frame_index, capture, pts_ns or 0, w, h)
                n_hands = n_poses = 0
                messages: list[bytes] = []
                # Pose runs on a second thread while hands run here (MediaPipe releases the GIL).
                pose_future = pool.submit(pose.process, rgb) if pose is not None else None
                if hands is not None:
                    res = hands.process(rgb)
                    for world, cls in zip(
                        res.multi_hand_world_landmarks or (), res.multi_handedness or (), strict=False
                    ):
                        top = cls.classification[0]
                        label = 1 if top.label == "Right" else 0
                        score = float(top.score)
                        rows = _landmark_rows(world, with_scores=False)
                        hand_head = head[:5] + bytes([KIND_HAND]) + head[6:]
                        msg = encode_hand(hand_head, label, n_hands, score, rows, [score] * HAND_POINTS)
                        messages.append(msg)
                        n_hands += 1
                if pose_future is not None:
                    res = pose_future.result()
                    if res.pose_world_landmarks is not None:
                        pose_head = head[:5] + bytes([KIND_POSE]) + head[6:]
                        rows = _landmark_rows(res.pose_world_landmarks, with_scores=True)
                        messages.append(encode_pose(pose_head, rows))
                        n_poses = 1
                elapsed_ms = (time.perf_counter() - t0) * 1e3
                frame_head = head[:5] + bytes([KIND_FRAME]) + head[6:]
                messages.append(encode_frame(frame_head, n_hands, n_poses, elapsed_ms))
                if args.bench:
                    timings_ms.append(elapsed_ms)
                    cpu_ms.append((time.process_time() - c0) * 1e3)
                else:
                    for msg in messages:
                        sock.sendto(msg, dest)
                frame_index = (frame_index + 1) & 0xFFFFFFFF
        except Exception as exc:
            event(EVENT_ERROR, f"tracking {args.source!r} failed: {type(exc).__name__}: {exc}")
            return 4
        finally:
            container.close()
        if not args.loop or live:
            break
    event(EVENT_END, f"end of {args.source} after {frame_index} frames")
    if args.bench and timings_ms:
        # The first frames include graph start-up; report steady state.
        steady = sorted(timings_ms[min(5, len(timings_ms) - 1) :])
        print(
            json.dumps(
                {
                    "frames": len(steady),
                    "width": w,
                    "height": h,
                    "ms_mean": sum(steady) / len(steady),
                    "ms_p50": steady[len(steady) // 2],
                    "ms_p95": steady[min(len(steady) - 1, int(0.95 * len(steady)))],
                    "cpu_ms_mean": sum(cpu_ms[len(cpu_ms) - len(steady) :]) / len(steady),
                }
            )
        )
    return 0


def _read_exact(stream: Any, n: int) -> bytes:
    chunks: list[bytes] = []
    while n > 0:
        chunk = stream.read(n)
        if not chunk:
            break
        chunks.append(chunk)
        n -= len(chunk)
    return b"".join(chunks)


def run_batch(args: argparse.Namespace) -> int:
    """Batch mode: RGB frames from stdin, length-prefixed messages to stdout (see module doc)."""
    inp, out = sys.stdin.buffer, sys.stdout.buffer

    def send(msg: bytes) -> None:
        out.write(OUTPUT_LENGTH.pack(len(msg)) + msg)

    def event(code: int, text: str) -> None:
        send(
            encode_event(
                encode_header(
                    KIND_EVENT,
                    capture_ns=time.time_ns(),
                    device_ns=0,
                    frame=0,
                    width=0,
                    height=0,
                    mirrored=False,
                ),
                code,
                text,
            )
        )
        out.flush()

    try:
        mp = importlib.import_module("mediapipe")
    except ImportError as exc:
        event(EVENT_ERROR, f"tracker venv lacks {exc.name}; install mediapipe==0.10.21 into it")
        return 2
    hands = mp.solutions.hands.Hands(
        static_image_mode=args.static_image,
        max_num_hands=args.max_hands,
        model_complexity=args.hand_model_complexity,
        min_detection_confidence=args.min_detection_confidence,
        min_tracking_confidence=args.min_tracking_confidence,
    )
    event(EVENT_STARTED, "tracking frames from stdin")
    count = 0
    while True:
        raw = _read_exact(inp, INPUT_FRAME.size)
        if not raw:
            break
        if len(raw) < INPUT_FRAME.size:
            event(EVENT_ERROR, f"stdin ended inside a frame header ({len(raw)} of {INPUT_FRAME.size} bytes)")
            return 5
        magic, frame, w, h, device_ns = INPUT_FRAME.unpack(raw)
        if magic != INPUT_MAGIC or not (0 < w <= MAX_INPUT_SIDE and 0 < h <= MAX_INPUT_SIDE) or device_ns < 0:
            event(EVENT_ERROR, f"bad input frame header (magic {magic!r}, {w}x{h}, device_ns {device_ns})")
            return 5
        pixels = _read_exact(inp, w * h * 3)
        if len(pixels) < w * h * 3:
            event(EVENT_ERROR, f"stdin ended inside frame {frame} ({len(pixels)} of {w * h * 3} bytes)")
            return 5
        t0 = time.perf_counter()
        res = hands.process(np.frombuffer(pixels, dtype=np.uint8).reshape(h, w, 3))
        head = encode_header(
            0, capture_ns=time.time_ns(), device_ns=device_ns, frame=frame, width=w, height=h, mirrored=False
        )
        n_hands = 0
        for marks, cls in zip(res.multi_hand_landmarks or (), res.multi_handedness or (), strict=False):
            top = cls.classification[0]
            points = [(p.x, p.y) for p in marks.landmark]
            hand_head = head[:5] + bytes([KIND_HAND_IMAGE]) + head[6:]
            send(
                encode_hand_image(
                    hand_head, 1 if top.label == "Right" else 0, n_hands, float(top.score), points
                )
            )
            n_hands += 1
        elapsed_ms = (time.perf_counter() - t0) * 1e3
        send(encode_frame(head[:5] + bytes([KIND_FRAME]) + head[6:], n_hands, 0, elapsed_ms))
        out.flush()
        count += 1
    event(EVENT_END, f"end of stdin after {count} frames")
    return 0


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    """Command-line arguments of the tracker process."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--source", default="", help="video file path or V4L2 device, e.g. /dev/video0")
    p.add_argument(
        "--stdin-frames", action="store_true", help="batch mode: RGB frames on stdin, messages on stdout"
    )
    p.add_argument(
        "--static-image", action="store_true", help="detect in every frame independently (no tracking)"
    )
    p.add_argument("--send-to", default="", help="HOST:PORT receiving the UDP datagrams")
    p.add_argument("--bench", action="store_true", help="send nothing; print per-frame timing as JSON")
    p.add_argument("--hands", action=argparse.BooleanOptionalAction, default=True)
    p.add_argument("--pose", action=argparse.BooleanOptionalAction, default=True)
    p.add_argument("--max-hands", type=int, default=2)
    p.add_argument("--hand-model-complexity", type=int, choices=(0, 1), default=1)
    p.add_argument("--min-detection-confidence", type=float, default=0.5)
    p.add_argument("--min-tracking-confidence", type=float, default=0.5)
    p.add_argument("--mirrored", action="store_true", help="frames are a mirror image (selfie preview)")
    p.add_argument("--realtime", action=argparse.BooleanOptionalAction, default=True)
    p.add_argument("--loop", action="store_true")
    p.add_argument("--start-ns", type=int, default=0, help="common-clock time of a file's first frame")
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--fps", type=float, default=30.0)
    p.add_argument("--input-format", default="", help="V4L2 pixel format, e.g. mjpeg")
    return p.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point: ``python tracker.py --source FILE --send-to 127.0.0.1:PORT``."""
    args = parse_args(argv)
    if args.stdin_frames:
        try:
            return run_batch(args)
        except (KeyboardInterrupt, BrokenPipeError):
            return 0
    if not args.source:
        print("tracker: give --source FILE_OR_DEVICE (or --stdin-frames)", file=sys.stderr)
        return 2
    if not (args.send_to or args.bench):
        print("tracker: give --send-to HOST:PORT (or --bench)", file=sys.stderr)
        return 2
    try:
        return run(args)
    except KeyboardInterrupt:
        return 0


if __name__ == "__main__":
    sys.exit(main())
