"""Tests for the gamepad family: evdev record parsing, normalization, clock mapping, FIFO device."""

from __future__ import annotations

import contextlib
import math
import queue
import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from telerig.devices.base import Device
from telerig.devices.gamepad.device import GamepadDevice, find_gamepad
from telerig.devices.gamepad.fake import FakeGamepad, encode_event, report, typical_payload
from telerig.devices.gamepad.protocol import (
    EV_KEY,
    EV_SYN,
    FUZZ_TARGET,
    GamepadNormalizer,
    InputEvent,
    parse_events,
)
from telerig.errors import ConfigError, DeviceError, WireError
from telerig.ir.types import ControllerState, Sample, Twist
from telerig.registry import DEVICES

TIMEOUT = 5.0
T0 = 1_700_000_000_000_000_000


def feed_all(norm: GamepadNormalizer, data: bytes, receive_ns: int = T0 + 1_000_000) -> list[Sample]:
    return [s for e in parse_events(data) for s in norm.feed(e, receive_ns)]


def by_source(samples: list[Sample]) -> dict[str, Sample]:
    return {s.stamp.source_id: s for s in samples}


def test_parses_a_real_input_event_record() -> None:
    raw = struct.pack("<qqHHi", 1700000000, 123456, 3, 1, -20000)
    assert parse_events(raw) == [InputEvent(1700000000, 123456, 3, 1, -20000)]
    assert parse_events(raw)[0].time_ns == 1_700_000_000_123_456_000


@pytest.mark.parametrize(
    "bad", [b"\x00" * 23, struct.pack("<qqHHi", 1, 1_000_000, 0, 0, 0), struct.pack("<qqHHi", -1, 0, 0, 0, 0)]
)
def test_bad_records_raise_wire_error(bad: bytes) -> None:
    with pytest.raises(WireError):
        parse_events(bad)


def test_sticks_follow_controller_state_convention() -> None:
    out = by_source(feed_all(GamepadNormalizer("gp"), report(T0, {"x": 32767, "y": -32768, "rx": -32768})))
    left, right = out["gp/left"], out["gp/right"]
    assert isinstance(left, ControllerState)
    assert isinstance(right, ControllerState)
    assert left.joystick[0] == pytest.approx(1 / math.sqrt(2), abs=1e-3)  # radial clamp at 1
    assert left.joystick[1] == pytest.approx(1 / math.sqrt(2), abs=1e-3)  # evdev y up = forward
    assert right.joystick[0] == pytest.approx(-1.0)
    assert (left.hand, right.hand) == ("left", "right")


def test_stick_deadzone_is_radial() -> None:
    norm = GamepadNormalizer("gp", stick_deadzone=0.2)
    out = by_source(feed_all(norm, report(T0, {"x": 3000, "y": 3000})))
    assert np.all(out["gp/left"].joystick == 0.0)  # type: ignore[union-attr]


def test_triggers_and_bumpers_fill_trigger_grip_and_buttons() -> None:
    data = report(T0, {"z": 1023, "rz": 511}, {"lb": 1, "a": 1, "y": 1, "select": 1})
    out = by_source(feed_all(GamepadNormalizer("gp"), data))
    left, right = out["gp/left"], out["gp/right"]
    assert isinstance(left, ControllerState)
    assert isinstance(right, ControllerState)
    assert (left.trigger, left.grip, left.buttons) == (1.0, 1.0, {"lb", "select"})
    assert 0.45 < right.trigger < 0.5
    assert (right.grip, right.buttons) == (0.0, {"a", "y"})


def test_playstation_profile_names_face_buttons_by_position() -> None:
    data = report(T0, {"x": 255, "y": 128}, {"x": 1})  # code 0x133 = triangle on hid-playstation
    out = by_source(feed_all(GamepadNormalizer("gp", profile="playstation"), data))
    assert out["gp/right"].buttons == {"y"}  # type: ignore[union-attr]
    assert out["gp/left"].joystick[0] == pytest.approx(1.0, abs=1e-3)  # type: ignore[union-attr]


def test_hat_becomes_dpad_buttons_on_the_left_hand() -> None:
    out = by_source(feed_all(GamepadNormalizer("gp"), report(T0, {"hat0x": -1, "hat0y": -1})))
    assert out["gp/left"].buttons == {"dpad_left", "dpad_up"}  # type: ignore[union-attr]


def test_default_twist_map_drives_base_and_yaw() -> None:
    out = by_source(feed_all(GamepadNormalizer("gp"), report(T0, {"y": -32768, "rx": -32768})))
    t = out["gp"]
    assert isinstance(t, Twist)
    np.testing.assert_allclose(t.linear, [0.25, 0, 0])
    np.testing.assert_allclose(t.angular, [0, 0, 1.0])


def test_twist_expression_sums_and_clamps() -> None:
    norm = GamepadNormalizer("gp", twist_map={"linear_z": "right_trigger - left_trigger"}, max_linear=2.0)
    t = by_source(feed_all(norm, report(T0, {"rz": 1023, "z": 0})))["gp"]
    assert isinstance(t, Twist)
    np.testing.assert_allclose(t.linear, [0, 0, 2.0])


@pytest.mark.parametrize(
    ("twist_map", "match"),
    [
        ({"linear_w": "left_x"}, "unknown output"),
        ({"linear_x": "left_q"}, "unknown input"),
        ({"linear_x": "--left_x"}, "malformed"),
    ],
)
def test_bad_twist_map_names_the_fix(twist_map: dict[str, str], match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        GamepadNormalizer("gp", twist_map=twist_map)


def test_unchanged_hand_is_not_reemitted() -> None:
    norm = GamepadNormalizer("gp")
    feed_all(norm, report(T0, {"x": 20000}))
    again = feed_all(norm, report(T0 + 10_000_000, {"rx": 20000}))
    assert sorted(s.stamp.source_id for s in again) == ["gp", "gp/right"]
    assert by_source(again)["gp/right"].stamp.seq == 1


def test_syn_dropped_discards_until_next_report() -> None:
    norm = GamepadNormalizer("gp")
    feed_all(norm, report(T0))
    dropped = encode_event(T0, EV_SYN, 3, 0) + report(T0 + 1000, buttons={"a": 1})
    assert feed_all(norm, dropped) == []
    assert norm.dropped_reports == 1
    assert feed_all(norm, report(T0 + 2000, buttons={"b": 1}))[0].buttons == {"b"}  # type: ignore[union-attr]


def test_device_stamp_is_event_time_and_capture_is_not_after_arrival() -> None:
    out = feed_all(GamepadNormalizer("gp"), report(T0, {"x": 100}), receive_ns=T0 + 5_000_000)
    assert out[0].stamp.device_ns == T0
    assert T0 <= out[0].stamp.capture_ns <= T0 + 5_000_000


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=24 * 8))
def test_fuzz_bytes_only_wire_error_escapes(data: bytes) -> None:
    with contextlib.suppress(WireError):
        FUZZ_TARGET(data)


event = st.tuples(st.sampled_from([0, 1, 3, 4]), st.integers(0, 0x2FF), st.integers(-(2**31), 2**31 - 1))


@settings(max_examples=300, deadline=None)
@given(st.lists(event, max_size=40), st.sampled_from(["xbox", "playstation"]))
def test_fuzz_event_sequences_keep_ir_in_range(events: list[tuple[int, int, int]], profile: str) -> None:
    norm = GamepadNormalizer("gp", profile=profile, twist_map={"linear_x": "left_y+right_y+dpad_y"})  # type: ignore[arg-type]
    data = b"".join(encode_event(T0, *e) for e in events) + encode_event(T0, EV_SYN, 0, 0)
    for s in feed_all(norm, data):
        if isinstance(s, ControllerState):
            assert np.all(np.abs(s.joystick) <= 1.0)
            assert 0.0 <= s.trigger <= 1.0
            assert 0.0 <= s.grip <= 1.0
        else:
            assert isinstance(s, Twist)
            assert np.all(np.isfinite(s.linear))
            assert np.all(np.abs(s.linear) <= 0.25)
            assert np.all(np.abs(s.angular) <= 1.0)


def fake_sysfs(root: Path, devices: dict[str, tuple[str, str]]) -> Path:
    for name, (label, keys) in devices.items():
        d = root / name / "device" / "capabilities"
        d.mkdir(parents=True)
        (d / "key").write_text(keys + "\n")
        (d.parent / "name").write_text(label + "\n")
    return root


def test_discovery_finds_the_gamepad_by_btn_south(tmp_path: Path) -> None:
    # BTN_SOUTH = 0x130 = bit 48 of the 5th 64-bit word from the right.
    pad_keys = "7fdb000000000000 0 0 0 0"
    kbd_keys = "0 0 0 0 fffffffffffffffe"
    root = fake_sysfs(
        tmp_path, {"event0": ("AT keyboard", kbd_keys), "event7": ("Xbox Wireless Controller", pad_keys)}
    )
    assert find_gamepad(root).path == "/dev/input/event7"


def test_discovery_error_lists_event_devices(tmp_path: Path) -> None:
    root = fake_sysfs(tmp_path, {"event0": ("AT keyboard", "0 0 0 0 fffffffffffffffe")})
    with pytest.raises(DeviceError, match=r"found: /dev/input/event0 \(AT keyboard\)"):
        find_gamepad(root)


def test_device_implements_protocol() -> None:
    assert isinstance(GamepadDevice(path="/nonexistent"), Device)


def next_where(q: queue.Queue[Sample], source: str) -> Sample:
    while True:
        s = q.get(timeout=TIMEOUT)
        if s.stamp.source_id == source:
            return s


def test_device_reads_real_records_from_a_fifo(tmp_path: Path) -> None:
    path = tmp_path / "event0"
    q: queue.Queue[Sample] = queue.Queue()
    with FakeGamepad(path) as fake:
        dev = GamepadDevice("gp", path=str(path))
        dev.start(q.put)
        try:
            fake.connect()
            fake.send({"y": -32768}, {"b": 1})
            right = next_where(q, "gp/right")
            t = next_where(q, "gp")
        finally:
            dev.stop()
            dev.stop()
    assert isinstance(right, ControllerState)
    assert right.buttons == {"b"}
    assert isinstance(t, Twist)
    assert t.linear[0] == pytest.approx(0.25)
    assert t.stamp.capture_ns <= t.stamp.device_ns + 10**9


def test_device_survives_split_garbage_and_overflow(tmp_path: Path) -> None:
    path = tmp_path / "event0"
    q: queue.Queue[Sample] = queue.Queue()
    with FakeGamepad(path) as fake:
        dev = GamepadDevice("gp", path=str(path))
        dev.start(q.put)
        try:
            fake.connect()
            fake.send_raw(struct.pack("<qqHHi", 1, 5_000_000, 0, 0, 0))  # bad tv_usec
            fake.overflow()
            fake.send(buttons={"a": 1})  # discarded: state unreliable until this SYN_REPORT
            rec = report(T0, buttons={"x": 1})
            fake.send_raw(rec[:10])  # a record split across writes
            fake.send_raw(rec[10:])
            right = next_where(q, "gp/right")
        finally:
            dev.stop()
    assert right.buttons == {"x"}  # type: ignore[union-attr]
    assert dev.stats["wire_error"] == 1
    assert dev.stats["sync_dropped"] == 1


def test_device_plays_smooth_motion(tmp_path: Path) -> None:
    path = tmp_path / "event0"
    q: queue.Queue[Sample] = queue.Queue()
    with FakeGamepad(path) as fake:
        dev = GamepadDevice("gp", path=str(path))
        dev.start(q.put)
        try:
            fake.connect()
            fake.play(duration_s=0.2, rate_hz=200)
            fake.wait(TIMEOUT)
            twists = [next_where(q, "gp") for _ in range(10)]
        finally:
            dev.stop()
    assert [t.stamp.seq for t in twists] == list(range(10))


def test_config_builds_device() -> None:
    cfg = DEVICES.parse_config(
        {
            "type": "gamepad",
            "id": "pad",
            "path": "/dev/input/event3",
            "profile": "playstation",
            "twist_map": {"linear_z": "right_trigger-left_trigger"},
            "axis_ranges": {"z": [0, 255]},
        },
        "devices[0]",
    )
    dev = cfg.build()
    assert isinstance(dev, GamepadDevice)
    assert (dev.id, dev.path, dev.normalizer.profile) == ("pad", "/dev/input/event3", "playstation")
    assert cfg.model_validate(cfg.model_dump()) == cfg


def test_config_rejects_unknown_twist_input() -> None:
    with pytest.raises(ValueError, match="unknown input 'stick'"):
        DEVICES.parse_config({"type": "gamepad", "id": "pad", "twist_map": {"linear_x": "stick"}}, "d")


def test_key_event_value_2_is_autorepeat_and_held() -> None:
    norm = GamepadNormalizer("gp")
    data = encode_event(T0, EV_KEY, 0x130, 2) + encode_event(T0, EV_SYN, 0, 0)
    assert by_source(feed_all(norm, data))["gp/right"].buttons == {"a"}  # type: ignore[union-attr]


def test_typical_payload_parses() -> None:
    assert len(feed_all(GamepadNormalizer("gp"), typical_payload())) == 3
