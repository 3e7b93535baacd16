"""The fake glove: an in-process fake bridge read by the real glove device (open, fist, point, pinch)."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from telerig.devices.fake_glove.config import FakeGloveConfig
from telerig.devices.fake_glove.device import FakeGloveDevice
from telerig.errors import ConfigError
from telerig.ir.types import HandPose, Sample
from telerig.registry import DEVICES


def _collect(device: FakeGloveDevice, seconds: float) -> list[Sample]:
    samples: list[Sample] = []
    device.start(samples.append)
    deadline = time.monotonic() + 10.0
    while time.monotonic() < deadline and len(samples) < seconds * 60:
        time.sleep(0.02)
    device.stop()
    return samples


def test_fake_glove_is_registered_and_builds_with_its_id() -> None:
    assert "fake_glove" in DEVICES.names()
    device = FakeGloveConfig(id="g0").build()
    assert isinstance(device, FakeGloveDevice)
    assert device.id == "g0"


def test_samples_cross_the_glove_protocol_and_the_hand_closes() -> None:
    device = FakeGloveDevice("g0", hand="right", rate_hz=60.0, dwell_s=0.2, transition_s=0.2)
    samples = _collect(device, 1.0)  # open, then the blend into a fist
    assert len(samples) >= 50
    assert all(isinstance(s, HandPose) and s.handedness == "right" for s in samples)
    assert device.bridge.connections == 1
    assert device.bridge.frames_sent >= len(samples)
    seqs = [s.stamp.seq for s in samples]
    assert seqs == sorted(seqs)
    tip_to_wrist = [
        float(np.linalg.norm(s.keypoints[8] - s.keypoints[0])) for s in samples if isinstance(s, HandPose)
    ]
    assert max(tip_to_wrist) - min(tip_to_wrist) > 0.05  # [m] the index curls in


def test_stop_is_idempotent_and_leaves_no_thread_behind() -> None:
    before = set(threading.enumerate())
    device = FakeGloveDevice("g0")
    device.stop()  # before start: a no-op
    _collect(device, 0.2)
    device.stop()
    time.sleep(0.1)
    assert not [t.name for t in set(threading.enumerate()) - before if t.is_alive()]


def test_bad_rate_is_a_one_line_config_error() -> None:
    with pytest.raises(ValueError, match="rate_hz"):
        FakeGloveConfig(id="g0", rate_hz=0)
    with pytest.raises(ConfigError, match="rate_hz must be in"):
        FakeGloveDevice("g0", rate_hz=5000.0)
