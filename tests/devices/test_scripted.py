"""Tests for the scripted VR controller: trajectory shape (pure, sampled) and the emitting thread."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from telerig.devices.base import Device
from telerig.devices.scripted import POINTING_DOWN, ButtonPress, ScriptedVRController
from telerig.errors import ConfigError, DeviceError
from telerig.ir.types import ControllerState, Sample

DT = 0.001  # s, sampling step for finite differences


def trajectory(dev: ScriptedVRController, cycles: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    t = np.arange(0.0, cycles * dev.cycle_s, DT)
    states = [dev.sample_at(float(ti)) for ti in t]
    positions = np.array([s.position for s in states])
    triggers = np.array([s.trigger for s in states])
    return t, positions, triggers


def test_implements_device_protocol() -> None:
    assert isinstance(ScriptedVRController(), Device)


def test_sample_at_is_deterministic() -> None:
    a, b = ScriptedVRController(), ScriptedVRController()
    for t in (0.0, 1.234, 4.5, 9.99, 23.7):
        sa, sb = a.sample_at(t, seq=3), b.sample_at(t, seq=3)
        assert (sa.stamp, sa.trigger, sa.buttons, sa.position.tolist(), sa.orientation.tolist()) == (
            sb.stamp,
            sb.trigger,
            sb.buttons,
            sb.position.tolist(),
            sb.orientation.tolist(),
        )


def test_position_is_continuous_with_bounded_velocity() -> None:
    _, p, _ = trajectory(ScriptedVRController(), cycles=2.0)
    speed = np.linalg.norm(np.diff(p, axis=0), axis=1) / DT
    assert speed.max() < 0.6  # m/s; min-jerk peak is 1.875 * distance / duration


def test_acceleration_is_bounded() -> None:
    _, p, _ = trajectory(ScriptedVRController(), cycles=2.0)
    acc = np.linalg.norm(np.diff(p, n=2, axis=0), axis=1) / DT**2
    assert acc.max() < 3.0  # m/s^2; no steps at segment joins or cycle wrap


def test_trigger_closes_at_the_pick_point() -> None:
    dev = ScriptedVRController()
    _, p, g = trajectory(dev)
    closing = (g > 0.01) & (g < 0.99) & (np.arange(len(g)) < len(g) // 2)
    assert closing.any()
    assert np.linalg.norm(p[closing] - dev.pick, axis=1).max() < 1e-9


def test_trigger_opens_at_the_place_point() -> None:
    dev = ScriptedVRController()
    _, p, g = trajectory(dev)
    opening = (g > 0.01) & (g < 0.99) & (np.arange(len(g)) >= len(g) // 2)
    assert opening.any()
    assert np.linalg.norm(p[opening] - dev.place, axis=1).max() < 1e-9


def test_trigger_is_held_while_carrying() -> None:
    dev = ScriptedVRController()
    t, _, g = trajectory(dev)
    carrying = np.array([dev.phase_at(float(ti)) in ("lift", "transfer", "lower") for ti in t])
    assert (g[carrying] == 1.0).all()


def test_trigger_ramp_takes_about_300ms() -> None:
    _, _, g = trajectory(ScriptedVRController())
    moving = np.count_nonzero((g > 0.0) & (g < 1.0)) * DT / 2  # two ramps per cycle
    assert moving == pytest.approx(0.3, abs=0.01)


def test_phases_follow_the_pick_and_place_order() -> None:
    dev = ScriptedVRController(cycle_s=10.0)
    t = np.arange(0.0, dev.cycle_s, 0.01)
    phases = [dev.phase_at(float(ti)) for ti in t]
    order = [p for i, p in enumerate(phases) if i == 0 or p != phases[i - 1]]
    expected = ["approach", "descend", "grasp", "lift", "transfer", "lower", "release", "retreat", "return"]
    assert order == [*expected, "idle"]


def test_cycle_starts_and_ends_at_home() -> None:
    dev = ScriptedVRController()
    np.testing.assert_allclose(dev.sample_at(0.0).position, dev.home)
    np.testing.assert_allclose(dev.sample_at(dev.cycle_s - 1e-6).position, dev.home, atol=1e-9)


def test_orientation_points_down() -> None:
    state = ScriptedVRController().sample_at(2.0)
    np.testing.assert_array_equal(state.orientation, POINTING_DOWN)


def test_button_press_is_held_inside_its_window() -> None:
    dev = ScriptedVRController(presses=[ButtonPress("a", 1.0, 1.5)])
    assert [dev.sample_at(t).buttons for t in (0.9, 1.2, 1.6)] == [frozenset(), {"a"}, frozenset()]


def test_bad_position_raises_config_error() -> None:
    with pytest.raises(ConfigError, match="pick"):
        ScriptedVRController(pick=(0.1, 0.2))


class Collector:
    def __init__(self) -> None:
        self.samples: list[ControllerState] = []
        self.lock = threading.Lock()

    def __call__(self, sample: Sample) -> None:
        assert isinstance(sample, ControllerState)
        with self.lock:
            self.samples.append(sample)


@pytest.fixture(scope="module")
def emitted() -> list[ControllerState]:
    """Run the thread once at 200 Hz for 0.3 s; the tests below inspect what it emitted."""
    dev = ScriptedVRController(rate_hz=200.0)
    sink = Collector()
    dev.start(sink)
    time.sleep(0.3)
    dev.stop()
    return sink.samples


def test_start_emits_at_about_the_rate(emitted: list[ControllerState]) -> None:
    assert 45 <= len(emitted) <= 65


def test_start_emits_increasing_seq(emitted: list[ControllerState]) -> None:
    assert [s.stamp.seq for s in emitted] == list(range(len(emitted)))


def test_start_emits_increasing_capture_ns(emitted: list[ControllerState]) -> None:
    capture = np.array([s.stamp.capture_ns for s in emitted])
    assert (np.diff(capture) > 0).all()


def test_start_stamps_source_id(emitted: list[ControllerState]) -> None:
    assert {s.stamp.source_id for s in emitted} == {"vr0/right"}


def test_stop_is_idempotent() -> None:
    dev = ScriptedVRController()
    dev.start(Collector())
    dev.stop()
    dev.stop()
    assert not dev.running


def test_stop_before_start_is_a_no_op() -> None:
    dev = ScriptedVRController()
    dev.stop()
    assert not dev.running
    sink = Collector()
    dev.start(sink)  # the early stop left nothing that blocks a start
    try:
        assert dev.running
    finally:
        dev.stop()
    assert not dev.running


def test_second_start_raises_device_error() -> None:
    dev = ScriptedVRController()
    dev.start(Collector())
    try:
        with pytest.raises(DeviceError):
            dev.start(Collector())
    finally:
        dev.stop()
