"""Scripted twist device: segment twists with minimum-jerk blends, buttons, looping, config errors."""

from __future__ import annotations

import time

import numpy as np
import pytest

from telerig.devices.scripted_twist import ScriptedTwistDevice, TwistSegment
from telerig.devices.scripted_twist.config import ScriptedTwistConfig
from telerig.errors import ConfigError
from telerig.ir.types import ControllerState, Sample
from telerig.runtime.streams import device_stream

SCRIPT = (
    TwistSegment(1.0),
    TwistSegment(1.0, linear=(0.1, 0.0, 0.0), buttons=frozenset({"left"})),
    TwistSegment(1.0, angular=(0.0, 0.0, 0.5)),
)


def test_segments_hold_their_twist_after_a_smooth_blend() -> None:
    device = ScriptedTwistDevice("sm0", segments=SCRIPT, ramp_s=0.2, loop=False)
    assert device.sample_at(0.5).linear.tolist() == [0.0, 0.0, 0.0]
    assert device.sample_at(1.1).linear[0] == pytest.approx(0.05)  # halfway through the blend
    assert device.sample_at(1.5).linear[0] == pytest.approx(0.1)
    sample = device.sample_at(2.5)
    assert sample.linear[0] == pytest.approx(0.0)
    assert sample.angular[2] == pytest.approx(0.5)
    assert device.sample_at(99.0).angular[2] == pytest.approx(0.5)  # not looping: the last twist holds


def test_blends_are_continuous_at_segment_boundaries() -> None:
    device = ScriptedTwistDevice("sm0", segments=SCRIPT, ramp_s=0.2)
    t = np.arange(0.0, 6.0, 0.001)
    linear = np.array([device.twist_at(x)[0][0] for x in t])
    assert np.max(np.abs(np.diff(linear))) < 0.002  # no steps: at most 0.1 m/s * 1.875 * 1 ms / 0.2 s


def test_buttons_follow_the_script_and_the_loop_wraps() -> None:
    device = ScriptedTwistDevice("sm0", segments=SCRIPT)
    assert device.buttons_at(0.5) == frozenset()
    assert device.buttons_at(1.5) == {"left"}
    assert device.buttons_at(4.5) == {"left"}  # second cycle
    assert device.sample_at(3.05).angular[2] > 0.4  # blending from the last segment into the first


def test_running_device_emits_on_the_spacemouse_streams() -> None:
    device = ScriptedTwistDevice("sm0", segments=(TwistSegment(0.05, buttons=frozenset({"left"})), *SCRIPT))
    samples: list[Sample] = []
    device.start(samples.append)
    try:
        deadline = time.monotonic() + 5.0
        while len({device_stream(s) for s in samples}) < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        device.stop()
    device.stop()  # idempotent
    streams = [device_stream(s) for s in samples]
    assert set(streams) == {"twist", "right_controller"}
    buttons = next(s for s in samples if isinstance(s, ControllerState))
    assert buttons.buttons == {"left"}
    assert buttons.stamp.source_id == "sm0/buttons"
    assert all(s.stamp.capture_ns > 0 for s in samples)


def test_bad_scripts_fail_in_one_line() -> None:
    with pytest.raises(ConfigError, match="at least one segment"):
        ScriptedTwistDevice("sm0", segments=())
    with pytest.raises(ConfigError, match=r"segments\[0\].duration_s must be > 0"):
        ScriptedTwistDevice("sm0", segments=(TwistSegment(0.0),))


def test_config_builds_the_device() -> None:
    config = ScriptedTwistConfig.model_validate(
        {"id": "sm0", "segments": [{"duration_s": 1.0, "linear": [0.1, 0, 0], "buttons": ["left"]}]}
    )
    device = config.build()
    assert isinstance(device, ScriptedTwistDevice)
    assert device.segments[0].buttons == {"left"}
