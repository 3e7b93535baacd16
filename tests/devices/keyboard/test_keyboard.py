"""Tests for the terminal keyboard: escape decoding, hold detection, pty device, termios restore."""

from __future__ import annotations

import os
import queue
import termios
import time
from collections.abc import Callable

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from telerig.devices.base import Device
from telerig.devices.keyboard.device import KeyboardDevice
from telerig.devices.keyboard.fake import FakeTerminal, typical_payload
from telerig.devices.keyboard.protocol import FUZZ_TARGET, KeyboardNormalizer, KeyDecoder, decode_keys
from telerig.errors import ConfigError, DeviceError, WireError
from telerig.ir.types import ControllerState, Sample, Twist
from telerig.registry import DEVICES

TIMEOUT = 5.0
MS = 1_000_000


def test_decodes_letters_case_insensitively_and_named_controls() -> None:
    assert decode_keys(b"wW \r\t\x7f\x03") == ["w", "w", "space", "enter", "tab", "backspace", "ctrl+c"]


def test_decodes_csi_and_ss3_arrows_and_paging() -> None:
    data = b"\x1b[A\x1bOB\x1b[C\x1b[D\x1b[5~\x1b[6~\x1b[1;5A\x1b[H"
    assert decode_keys(data) == ["up", "down", "right", "left", "pageup", "pagedown", "up", "home"]


def test_lone_escape_is_resolved_on_flush_and_alt_prefix() -> None:
    dec = KeyDecoder()
    assert dec.feed(b"\x1b") == []
    assert dec.pending
    assert dec.flush() == ["escape"]
    assert decode_keys(b"\x1bx") == ["alt+x"]


def test_sequence_split_across_reads_is_joined() -> None:
    dec = KeyDecoder()
    assert dec.feed(b"\x1b[") == []
    assert dec.feed(b"5") == []
    assert dec.feed(b"~w") == ["pageup", "w"]


def test_utf8_key_and_unknown_sequence() -> None:
    dec = KeyDecoder()
    assert dec.feed("é".encode()) == ["é"]
    assert dec.feed(b"\x1b[15~") == []  # F5: well-formed, no name
    assert (dec.unknown, dec.malformed) == (1, 0)


@pytest.mark.parametrize("bad", [b"\xff", b"\xc3", b"\x1b[" + b"1" * 40 + b"A", b"\x1b[12"])
def test_malformed_input_raises_wire_error(bad: bytes) -> None:
    with pytest.raises(WireError):
        decode_keys(bad)


def test_press_holds_until_initial_timeout_without_repeat() -> None:
    norm = KeyboardNormalizer("kb", initial_hold_s=0.5, repeat_release_s=0.1)
    norm.press("w", 0)
    assert norm.held(400 * MS) == {"w"}
    assert norm.held(600 * MS) == frozenset()


def test_repeats_keep_the_key_held_and_release_follows_quickly() -> None:
    norm = KeyboardNormalizer("kb", initial_hold_s=0.5, repeat_release_s=0.1)
    norm.press("w", 0)
    for t in range(300, 1000, 33):
        norm.press("w", t * MS)
    last = 993 * MS
    assert norm.held(last + 90 * MS) == {"w"}
    assert norm.held(last + 110 * MS) == frozenset()


def test_held_keys_map_to_operator_frame_twist() -> None:
    norm = KeyboardNormalizer("kb", max_linear=0.2, max_angular=0.5)
    for key in ("w", "up", "a", "q", "f"):
        norm.press(key, 0)
    t = norm.twist(10 * MS)
    np.testing.assert_allclose(t.linear, [0.2, 0.2, -0.2])  # w + up clamps to one key's speed
    np.testing.assert_allclose(t.angular, [0.0, 0.0, 0.5])
    assert (t.frame_id, t.stamp.source_id) == ("operator", "kb")


def test_space_toggles_once_per_press_and_digits_latch_mode() -> None:
    norm = KeyboardNormalizer("kb")
    norm.press("space", 0)
    norm.press("space", 300 * MS)  # auto-repeat of the same press
    norm.press("3", 310 * MS)
    c = norm.controller(320 * MS)
    assert isinstance(c, ControllerState)
    assert (c.trigger, c.buttons, c.stamp.source_id) == (1.0, {"mode3"}, "kb/right")
    assert norm.controller(330 * MS) is None
    norm.press("space", 2000 * MS)
    c2 = norm.controller(2000 * MS)
    assert c2 is not None
    assert c2.trigger == 0.0


def test_same_key_after_another_key_is_a_new_press() -> None:
    norm = KeyboardNormalizer("kb")
    norm.press("space", 0)
    norm.press("w", 10 * MS)
    norm.press("space", 20 * MS)
    assert norm.trigger == 0.0


def test_button_action_is_momentary() -> None:
    norm = KeyboardNormalizer("kb", key_map={"enter": "button:a"}, initial_hold_s=0.5)
    norm.press("enter", 0)
    assert norm.controller(0).buttons == {"a", "mode1"}  # type: ignore[union-attr]
    assert norm.controller(600 * MS).buttons == {"mode1"}  # type: ignore[union-attr]


def test_bad_key_map_names_valid_actions() -> None:
    with pytest.raises(ConfigError, match=r"key_map\['w'\]: unknown action 'forward'; valid"):
        KeyboardNormalizer("kb", key_map={"w": "forward"})


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=64))
def test_fuzz_only_wire_error_escapes_and_twist_is_bounded(data: bytes) -> None:
    try:
        twist, _ = FUZZ_TARGET(data)  # type: ignore[misc]
    except WireError:
        return
    assert isinstance(twist, Twist)
    assert np.all(np.isfinite(twist.linear))
    assert np.all(np.abs(twist.linear) <= 0.1)
    assert np.all(np.abs(twist.angular) <= 0.5)


@settings(max_examples=300, deadline=None)
@given(st.lists(st.binary(max_size=8), max_size=10))
def test_fuzz_incremental_decoder_never_raises(chunks: list[bytes]) -> None:
    dec = KeyDecoder()
    for c in chunks:
        dec.feed(c)
    dec.flush()
    assert not dec.pending


def test_device_implements_protocol() -> None:
    assert isinstance(KeyboardDevice(), Device)


def next_of(q: queue.Queue[Sample], pred: Callable[[Sample], bool]) -> Sample:
    """The first queued sample matching ``pred`` within TIMEOUT overall (the device emits every tick)."""
    deadline = time.monotonic() + TIMEOUT
    while (left := deadline - time.monotonic()) > 0:
        s = q.get(timeout=left)
        if pred(s):
            return s
    raise AssertionError(f"no matching sample within {TIMEOUT} s")


def test_device_reads_a_pty_and_restores_the_terminal() -> None:
    with FakeTerminal() as term:
        before = termios.tcgetattr(term.slave_fd)
        dev = KeyboardDevice("kb", fd=term.slave_fd, rate_hz=100)
        q: queue.Queue[Sample] = queue.Queue()
        dev.start(q.put)
        try:
            assert not termios.tcgetattr(term.slave_fd)[3] & termios.ICANON
            term.type("w")
            t = next_of(q, lambda s: isinstance(s, Twist) and s.linear[0] > 0)
            term.type("space", "2")
            c = next_of(q, lambda s: isinstance(s, ControllerState) and s.trigger == 1.0)
        finally:
            dev.stop()
            dev.stop()
        assert termios.tcgetattr(term.slave_fd) == before
    assert t.linear[0] == pytest.approx(0.1)  # type: ignore[union-attr]
    assert c.buttons in ({"mode1"}, {"mode2"})  # type: ignore[union-attr]
    assert dev.stats["keys"] >= 3


def test_device_escape_key_and_arrow_via_pty() -> None:
    with FakeTerminal() as term:
        dev = KeyboardDevice("kb", fd=term.slave_fd, key_map={"escape": "button:stop", "left": "+linear_y"})
        q: queue.Queue[Sample] = queue.Queue()
        dev.start(q.put)
        try:
            term.type("escape")
            c = next_of(q, lambda s: isinstance(s, ControllerState) and "stop" in s.buttons)
            term.write(typical_payload() + b"\x1b[D")
            t = next_of(q, lambda s: isinstance(s, Twist) and s.linear[1] > 0)
        finally:
            dev.stop()
    assert isinstance(c, ControllerState)
    assert isinstance(t, Twist)
    assert dev.stats["unmapped_key"] >= 1  # "up" is not in this key map


def test_device_holds_while_repeats_come() -> None:
    with FakeTerminal() as term:
        dev = KeyboardDevice("kb", fd=term.slave_fd, rate_hz=200, initial_hold_s=0.3, repeat_release_s=0.1)
        q: queue.Queue[Sample] = queue.Queue()
        dev.start(q.put)
        try:
            term.hold("e", 0.4, repeat_delay_s=0.1, repeat_hz=40)
            next_of(q, lambda s: isinstance(s, Twist) and s.angular[2] < 0)
            term.wait(TIMEOUT)
            next_of(q, lambda s: isinstance(s, Twist) and s.angular[2] == 0)
        finally:
            dev.stop()


def test_start_on_a_non_terminal_names_the_fix() -> None:
    r, w = os.pipe()
    try:
        with pytest.raises(DeviceError, match="not a terminal"):
            KeyboardDevice(fd=r).start(lambda s: None)
    finally:
        os.close(r)
        os.close(w)


def test_config_builds_device_and_validates_key_map() -> None:
    cfg = DEVICES.parse_config(
        {"type": "keyboard", "id": "kb", "key_map": {"i": "+linear_z", "x": "button:x"}, "rate_hz": 20}, "d"
    )
    dev = cfg.build()
    assert isinstance(dev, KeyboardDevice)
    assert (dev.id, dev.rate_hz) == ("kb", 20.0)
    assert cfg.model_validate(cfg.model_dump()) == cfg
    with pytest.raises(ValueError, match="unknown action"):
        DEVICES.parse_config({"type": "keyboard", "id": "kb", "key_map": {"w": "jump"}}, "d")


def test_lone_escape_is_detected_when_ticks_are_shorter_than_the_escape_timeout() -> None:
    with FakeTerminal() as term:
        dev = KeyboardDevice("kb", fd=term.slave_fd, rate_hz=200, key_map={"escape": "button:stop"})
        q: queue.Queue[Sample] = queue.Queue()
        dev.start(q.put)
        try:
            term.type("escape")
            c = next_of(q, lambda s: isinstance(s, ControllerState) and "stop" in s.buttons)
        finally:
            dev.stop()
    assert isinstance(c, ControllerState)
