"""Tests for the SpaceMouse family: HID report parsing, normalization, discovery, FIFO device."""

from __future__ import annotations

import math
import queue
import struct
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from telerig.devices.base import Device
from telerig.devices.spacemouse.device import SpaceMouseDevice, find_spacemouse, list_hidraw
from telerig.devices.spacemouse.fake import (
    FakeSpaceMouse,
    button_report,
    rotation_report,
    six_axis_report,
    translation_report,
    typical_payload,
)
from telerig.devices.spacemouse.protocol import (
    FUZZ_TARGET,
    ButtonReport,
    MotionReport,
    OtherReport,
    SpaceMouseNormalizer,
    parse_report,
    split_stream,
)
from telerig.errors import ConfigError, DeviceError, WireError
from telerig.ir.types import ControllerState, Sample, Twist
from telerig.registry import DEVICES

TIMEOUT = 5.0


def twist(norm: SpaceMouseNormalizer, *axes: int) -> Twist:
    out = norm.feed(MotionReport(axes[:3], axes[3:]), 0, 0)  # type: ignore[arg-type]
    assert isinstance(out, Twist)
    return out


def test_parses_real_split_translation_and_rotation_reports() -> None:
    assert parse_report(bytes.fromhex("01 0c00 4cff 1e00".replace(" ", ""))) == MotionReport(
        (12, -180, 30), None
    )
    assert parse_report(bytes.fromhex("02 fbff 0800 8c00".replace(" ", ""))) == MotionReport(
        None, (-5, 8, 140)
    )


def test_parses_six_axis_report() -> None:
    assert parse_report(typical_payload()) == MotionReport((12, -180, 30), (-5, 8, 140))


def test_parses_button_bitmask_and_ignores_battery_report() -> None:
    assert parse_report(b"\x03\x02\x00") == ButtonReport(2)
    assert parse_report(b"\x03\x00\x00\x00\x01") == ButtonReport(1 << 24)
    assert parse_report(b"\x17\x64") == OtherReport(0x17)


@pytest.mark.parametrize("bad", [b"", b"\x01\x00", b"\x01" + bytes(9), b"\x02" + bytes(12), b"\x03"])
def test_wrong_lengths_raise_wire_error(bad: bytes) -> None:
    with pytest.raises(WireError):
        parse_report(bad)


def test_push_away_from_user_is_forward_and_ccw_twist_is_positive_yaw() -> None:
    t = twist(SpaceMouseNormalizer("sm"), 0, -350, 0, 0, 0, -350)
    np.testing.assert_allclose(t.linear, [0.25, 0.0, 0.0])
    np.testing.assert_allclose(t.angular, [0.0, 0.0, 1.0])
    assert t.frame_id == "operator"


def test_right_and_down_map_to_minus_y_and_minus_z() -> None:
    t = twist(SpaceMouseNormalizer("sm", max_linear=1.0), 350, 0, 350, 0, 0, 0)
    np.testing.assert_allclose(t.linear, [0.0, -1.0, -1.0])


def test_roll_and_pitch_follow_the_proper_rotation() -> None:
    t = twist(SpaceMouseNormalizer("sm", max_angular=2.0), 0, 0, 0, 350, 350, 0)
    # op roll (about forward) = -ry, op pitch (about left) = -rx
    np.testing.assert_allclose(t.angular, [-2.0, -2.0, 0.0])


def test_deadband_zeroes_small_counts_and_output_is_continuous() -> None:
    norm = SpaceMouseNormalizer("sm", deadband=10, max_linear=1.0)
    assert twist(norm, 0, -10, 0, 0, 0, 0).linear[0] == 0.0
    assert 0.0 < twist(norm, 0, -11, 0, 0, 0, 0).linear[0] < 0.01


def test_counts_beyond_full_scale_are_clamped() -> None:
    t = twist(SpaceMouseNormalizer("sm"), 32767, -32768, 32767, 32767, -32768, 32767)
    assert np.all(np.abs(t.linear) <= 0.25)
    assert np.all(np.abs(t.angular) <= 1.0)


def test_axis_signs_flip_in_operator_frame() -> None:
    t = twist(SpaceMouseNormalizer("sm", axis_signs=(-1, 1, 1, 1, 1, 1)), 0, -350, 0, 0, 0, 0)
    assert t.linear[0] == pytest.approx(-0.25)


def test_bad_axis_signs_name_the_fix() -> None:
    with pytest.raises(ConfigError, match="axis_signs must be six values"):
        SpaceMouseNormalizer("sm", axis_signs=(1, 1, 1))


def test_split_reports_keep_the_other_half() -> None:
    norm = SpaceMouseNormalizer("sm")
    norm.feed(parse_report(translation_report(0, -350, 0)), 0, 0)
    t = norm.feed(parse_report(rotation_report(0, 0, -350)), 0, 0)
    assert isinstance(t, Twist)
    np.testing.assert_allclose(t.linear, [0.25, 0, 0])
    np.testing.assert_allclose(t.angular, [0, 0, 1.0])
    assert t.stamp.seq == 1


def test_buttons_emit_only_on_change() -> None:
    norm = SpaceMouseNormalizer("sm", button_names=("left", "right"))
    first = norm.feed(parse_report(button_report(0b101)), 5, 6)
    assert isinstance(first, ControllerState)
    assert first.buttons == {"left", "button2"}
    assert first.stamp.source_id == "sm/buttons"
    assert norm.feed(parse_report(button_report(0b101)), 7, 8) is None
    released = norm.feed(parse_report(button_report(0)), 9, 10)
    assert isinstance(released, ControllerState)
    assert released.buttons == frozenset()


def test_split_stream_recovers_report_boundaries() -> None:
    buf = translation_report(1, 2, 3) + rotation_report(4, 5, 6) + button_report(1) + b"\x01\x00"
    reports, rest = split_stream(buf, combined=False)
    assert [r[0] for r in reports] == [1, 2, 3]
    assert rest == b"\x01\x00"


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=70))
def test_fuzz_only_wire_error_escapes_and_output_is_bounded(data: bytes) -> None:
    try:
        out = FUZZ_TARGET(data)
    except WireError:
        return
    if isinstance(out, Twist):
        assert np.all(np.isfinite(out.linear))
        assert np.all(np.isfinite(out.angular))
        assert np.all(np.abs(out.linear) <= 0.25)
        assert np.all(np.abs(out.angular) <= 1.0)


@settings(max_examples=300, deadline=None)
@given(st.lists(st.integers(-32768, 32767), min_size=6, max_size=6))
def test_fuzz_any_counts_give_bounded_finite_twist(axes: list[int]) -> None:
    t = twist(SpaceMouseNormalizer("sm", max_linear=0.5, max_angular=2.0), *axes)
    assert all(math.isfinite(v) and abs(v) <= 0.5 for v in t.linear)
    assert all(math.isfinite(v) and abs(v) <= 2.0 for v in t.angular)


def fake_sysfs(root: Path, nodes: dict[str, str]) -> Path:
    for name, hid_id in nodes.items():
        d = root / name / "device"
        d.mkdir(parents=True)
        (d / "uevent").write_text(f"DRIVER=hid-generic\nHID_ID={hid_id}\nHID_NAME=Dev {name}\n")
    return root


def test_discovery_finds_a_known_spacemouse(tmp_path: Path) -> None:
    root = fake_sysfs(tmp_path, {"hidraw0": "0003:0000046D:0000C52B", "hidraw1": "0003:0000256F:0000C635"})
    info = find_spacemouse(root, "/dev")
    assert (info.path, info.vendor_id, info.product_id) == ("/dev/hidraw1", 0x256F, 0xC635)
    assert len(list_hidraw(root)) == 2


def test_discovery_error_lists_found_devices(tmp_path: Path) -> None:
    root = fake_sysfs(tmp_path, {"hidraw0": "0003:0000046D:0000C52B"})
    with pytest.raises(DeviceError, match=r"found: /dev/hidraw0 \(046d:c52b"):
        find_spacemouse(root)


def test_device_implements_protocol() -> None:
    assert isinstance(SpaceMouseDevice(path="/nonexistent"), Device)


def run_device(dev: SpaceMouseDevice) -> queue.Queue[Sample]:
    q: queue.Queue[Sample] = queue.Queue()
    dev.start(q.put)
    return q


def next_of(q: queue.Queue[Sample], kind: type) -> Sample:
    while True:
        s = q.get(timeout=TIMEOUT)
        if isinstance(s, kind):
            return s


@pytest.mark.parametrize("combined", [True, False])
def test_device_reads_real_reports_from_a_fifo(tmp_path: Path, combined: bool) -> None:
    path = tmp_path / "hidraw"
    with FakeSpaceMouse(path, combined=combined) as fake:
        dev = SpaceMouseDevice("sm", path=str(path), layout="combined" if combined else "split")
        q = run_device(dev)
        try:
            fake.connect()
            fake.motion(0, -350, 0, 0, 0, -350)
            fake.buttons(0b10)
            twists = [next_of(q, Twist) for _ in range(1 if combined else 2)]
            t = twists[-1]
            assert isinstance(t, Twist)
            np.testing.assert_allclose(t.linear, [0.25, 0, 0])
            np.testing.assert_allclose(t.angular, [0, 0, 1.0])
            b = next_of(q, ControllerState)
            assert isinstance(b, ControllerState)
            assert b.buttons == {"right"}
            assert t.stamp.capture_ns > 0
            assert t.stamp.device_ns == t.stamp.capture_ns
        finally:
            dev.stop()
            dev.stop()
    assert dev.stats["wire_error"] == 0


def test_device_plays_smooth_motion_with_increasing_seq(tmp_path: Path) -> None:
    path = tmp_path / "hidraw"
    with FakeSpaceMouse(path) as fake:
        dev = SpaceMouseDevice("sm", path=str(path))
        q = run_device(dev)
        try:
            fake.connect()
            fake.play(duration_s=0.2, rate_hz=200)
            fake.wait(TIMEOUT)
            fake.close()
            samples = [q.get(timeout=TIMEOUT) for _ in range(41)]
        finally:
            dev.stop()
    seqs = [s.stamp.seq for s in samples]
    assert seqs == list(range(41))


def test_device_counts_bad_reports_and_survives(tmp_path: Path) -> None:
    path = tmp_path / "hidraw"
    with FakeSpaceMouse(path, combined=False) as fake:
        dev = SpaceMouseDevice("sm", path=str(path), layout="split")
        q = run_device(dev)
        try:
            fake.connect()
            fake.send(b"\x17\x50")  # battery report: ignored
            fake.send(translation_report(0, -350, 0))
            t = next_of(q, Twist)
            assert isinstance(t, Twist)
            assert t.linear[0] > 0
        finally:
            dev.stop()
    assert dev.stats["ignored_report"] == 1


def test_device_reopens_after_disconnect(tmp_path: Path) -> None:
    path = tmp_path / "hidraw"
    dev = SpaceMouseDevice("sm", path=str(path), layout="combined")
    with FakeSpaceMouse(path) as fake:
        q = run_device(dev)
        try:
            fake.connect()
            fake.motion(0, -350, 0, 0, 0, 0)
            next_of(q, Twist)
            fake.close()
            deadline = time.monotonic() + TIMEOUT
            while dev.stats["disconnected"] == 0 and time.monotonic() < deadline:
                time.sleep(0.01)
            with FakeSpaceMouse(path) as again:
                again.connect()
                again.motion(0, 350, 0, 0, 0, 0)
                t = next_of(q, Twist)
                assert isinstance(t, Twist)
                assert t.linear[0] < 0
        finally:
            dev.stop()
    assert dev.stats["disconnected"] >= 1


def test_start_without_device_raises_with_listing(tmp_path: Path) -> None:
    dev = SpaceMouseDevice("sm", sys_root=fake_sysfs(tmp_path, {}))
    with pytest.raises(DeviceError, match="found: none"):
        dev.start(lambda s: None)


def test_config_builds_device() -> None:
    cfg = DEVICES.parse_config(
        {
            "type": "spacemouse",
            "id": "sm0",
            "path": "/dev/hidraw3",
            "max_linear": 0.5,
            "axis_signs": [1, -1, 1, 1, 1, 1],
        },
        "devices[0]",
    )
    dev = cfg.build()
    assert isinstance(dev, SpaceMouseDevice)
    assert (dev.id, dev.path, dev.normalizer.max_linear) == ("sm0", "/dev/hidraw3", 0.5)
    assert cfg.model_validate(cfg.model_dump()) == cfg


def test_config_rejects_bad_sign() -> None:
    with pytest.raises(ValueError, match="axis_signs"):
        DEVICES.parse_config({"type": "spacemouse", "id": "sm0", "axis_signs": [2, 1, 1, 1, 1, 1]}, "d")


def test_report_builders_match_the_wire_layout() -> None:
    assert struct.unpack("<B6h", six_axis_report(1, 2, 3, 4, 5, 6)) == (1, 1, 2, 3, 4, 5, 6)
    assert six_axis_report(99999, 0, 0, 0, 0, 0)[1:3] == b"\xff\x7f"
