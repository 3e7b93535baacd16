"""Hand detectors: the markerless tracker's batch mode with real MediaPipe, its wire messages, garbage."""

from __future__ import annotations

import contextlib
import math
import struct
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest

from telerig.devices.markerless import tracker
from telerig.devices.markerless.fake import synthetic_hand_frame
from telerig.errors import DependencyError, ProcessError, WireError
from telerig.process.hands import (
    HandDetector,
    MediaPipeDetectorConfig,
    MediaPipeHandDetector,
    build_detector,
    decode_hand_image,
)
from telerig.registry import HAND_DETECTORS

_TRACKER_PYTHON = Path(__file__).resolve().parents[2] / ".venv-markerless" / "bin" / "python"


def _require_venv() -> None:
    if not _TRACKER_PYTHON.exists():  # a required component: fail with the fix, never skip
        pytest.fail(f"{_TRACKER_PYTHON} is missing: run `make markerless` (make unit does it)", pytrace=False)


@pytest.fixture(scope="module")
def detector() -> Iterator[MediaPipeHandDetector]:
    _require_venv()
    with MediaPipeHandDetector(MediaPipeDetectorConfig(python=_TRACKER_PYTHON)) as d:
        yield d


def test_mediapipe_finds_the_drawn_hand_and_nothing_in_black(detector: MediaPipeHandDetector) -> None:
    assert isinstance(detector, HandDetector)
    hand = synthetic_hand_frame(0.0)  # the hand is drawn around (320, 300) in 640 x 480
    black = np.zeros((240, 320, 3), np.uint8)
    big = np.repeat(np.repeat(hand, 2, axis=0), 2, axis=1)  # 1280 x 960: scaled down for the pipe
    found = detector.detect([hand, black, big])
    assert [f.count for f in found] == [1, 0, 1]
    for f in (found[0], found[2]):
        (h,) = f.hands
        x0, y0, x1, y1 = h.box
        assert x0 < 0.5 < x1  # the box holds the hand's centre (0.5, 0.58)...
        assert y0 < 0.58 < y1
        assert (x1 - x0) < 0.6  # ...and not the whole frame
        assert h.landmarks is not None
        assert h.landmarks.shape == (21, 2)
        assert 0.0 < h.score <= 1.0
        assert h.label in ("left", "right")
    # The same process serves the next batch; frame numbers continue.
    again = detector.detect([hand] * 3)
    assert [f.count for f in again] == [1, 1, 1]
    assert detector.frames == 6
    assert detector.detect([]) == []


def test_tracker_refuses_an_oversized_frame_header_in_one_line(detector: MediaPipeHandDetector) -> None:
    # The tracker ends after this (the detector would start a new one on its next batch); so
    # this test runs last among the tests using the fixture.
    d = detector
    d.start()
    try:
        proc = d._proc
        assert proc is not None
        assert proc.stdin is not None
        # 60000 x 60000 would make the tracker read 10 GB; it must refuse before reading.
        proc.stdin.write(tracker.INPUT_FRAME.pack(tracker.INPUT_MAGIC, 0, 60000, 60000, 0))
        proc.stdin.flush()
        with pytest.raises(ProcessError, match=r"bad input frame header .*60000x60000"):
            d._collect(0, 1)
    finally:
        d.close()
    assert d._proc is None
    d.close()  # idempotent


def _hand_image_message(label: int = 1, score: float = 0.9, points: npt.ArrayLike | None = None) -> bytes:
    head = tracker.encode_header(
        tracker.KIND_HAND_IMAGE, capture_ns=1, device_ns=0, frame=3, width=320, height=240, mirrored=False
    )
    pts = np.full((21, 2), 0.5) if points is None else points
    return tracker.encode_hand_image(head, label, 0, score, pts)


def test_hand_image_message_round_trips_and_bad_ones_are_refused() -> None:
    pts = np.linspace(0.2, 0.6, 42).reshape(21, 2)
    header, hand = decode_hand_image(_hand_image_message(points=pts))
    assert header.frame == 3
    assert hand.label == "right"
    assert hand.score == pytest.approx(0.9)
    assert hand.box == pytest.approx((0.2, pts[0, 1], pts[-1, 0], 0.6), abs=1e-6)
    good = _hand_image_message()
    bad = {
        "size": good[:-1],
        "label": _hand_image_message(label=2),
        "score": _hand_image_message(score=math.nan),
        "far": _hand_image_message(points=np.full((21, 2), 5.0)),
        "nan point": _hand_image_message(points=np.full((21, 2), math.nan)),
        "kind": good[:5] + bytes([tracker.KIND_HAND]) + good[6:],
        "magic": b"XXXX" + good[4:],
    }
    for what, data in bad.items():
        with pytest.raises(WireError):
            decode_hand_image(data)
        assert what


def test_random_bytes_raise_only_wire_error() -> None:
    rng = np.random.default_rng(7)
    good = _hand_image_message()
    for _ in range(2000):
        data = bytearray(good)
        for i in rng.integers(0, len(data), int(rng.integers(1, 8))):
            data[i] = int(rng.integers(0, 256))
        with contextlib.suppress(WireError):
            decode_hand_image(bytes(data))
    # Extreme but valid floats: landmarks exactly on the slack border are accepted.
    decode_hand_image(_hand_image_message(points=np.full((21, 2), -0.5)))
    assert struct.calcsize("<4sIHHq") == tracker.INPUT_FRAME.size


def test_missing_venv_names_the_fix(tmp_path: Path) -> None:
    d = MediaPipeHandDetector(MediaPipeDetectorConfig(python=tmp_path / "nope" / "python"))
    with pytest.raises(DependencyError, match="make markerless"):
        d.detect([np.zeros((8, 8, 3), np.uint8)])


def test_registry_knows_mediapipe_and_names_it_for_unknown_types() -> None:
    assert "mediapipe" in HAND_DETECTORS.names()
    assert isinstance(build_detector({"type": "mediapipe", "hand_model": "lite"}), MediaPipeHandDetector)
    with pytest.raises(ProcessError, match=r"unknown hand detector type 'yolo_pose'.*mediapipe"):
        build_detector({"type": "yolo_pose"})
    with pytest.raises(ProcessError, match="max_hands"):
        build_detector({"type": "mediapipe", "max_hands": 99})


def _fake_tracker(tmp_path: Path, body: str) -> Path:
    """An executable standing in for the venv's python: ignores the tracker's arguments, runs ``body``
    (Python, with ``out`` = stdout bytes, ``msg(bytes)`` writing one length-prefixed message)."""
    script = tmp_path / "fake_tracker.py"
    script.write_text(
        "import struct, sys, time\n"
        f"sys.path.insert(0, {str(Path(tracker.__file__).parent)!r})\n"
        "import tracker\n"
        "out = sys.stdout.buffer\n"
        "def msg(data):\n"
        "    out.write(struct.pack('<H', len(data)) + data); out.flush()\n"
        "def event(code, text):\n"
        "    head = tracker.encode_header(tracker.KIND_EVENT, capture_ns=time.time_ns(), device_ns=0,"
        " frame=0, width=0, height=0, mirrored=False)\n"
        "    msg(tracker.encode_event(head, code, text))\n" + body
    )
    exe = tmp_path / "python"
    exe.write_text(f"#!/bin/sh\nexec {sys.executable} {script}\n")
    exe.chmod(0o755)
    return exe


@pytest.mark.parametrize(
    ("body", "expect"),
    [
        (
            "sys.stderr.write('boom: no model\\n'); sys.exit(3)\n",
            r"ended unexpectedly \(exit 3\): boom: no model",
        ),
        (
            "event(0, 'ok'); out.write(b'\\x10\\x00' + bytes(16)); out.flush(); time.sleep(5)\n",
            "sent a bad message",
        ),
        ("event(0, 'ok'); event(2, 'GPU on fire')\n", "markerless tracker failed: GPU on fire"),
        (
            "event(0, 'ok'); sys.stdin.buffer.read(100)\n"
            "head = tracker.encode_header(tracker.KIND_FRAME, capture_ns=1, device_ns=0, frame=7, width=8,"
            " height=8, mirrored=False)\n"
            "msg(tracker.encode_frame(head, 0, 0, 1.0)); time.sleep(5)\n",
            "answered frame 7 with 0 hands, expected frame 0",
        ),
    ],
    ids=["dies", "garbage", "error_event", "wrong_frame"],
)
def test_a_misbehaving_tracker_is_one_process_error(tmp_path: Path, body: str, expect: str) -> None:
    d = MediaPipeHandDetector(MediaPipeDetectorConfig(python=_fake_tracker(tmp_path, body)))
    with pytest.raises(ProcessError, match=expect):
        d.detect([np.zeros((8, 8, 3), np.uint8)])
    assert d._proc is None  # closed: the next batch starts a fresh tracker
