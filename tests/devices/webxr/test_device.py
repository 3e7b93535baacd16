"""WebXR device fed by relayed pages (telerig serve's relay played in-process by LocalRelay): samples,
drops, clock offset, idle pages, lifecycle, config."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator

import pytest

from telerig.devices.base import Device, OperatedDevice, RelayedDevice
from telerig.devices.webxr.config import WebXRConfig
from telerig.devices.webxr.device import CLOSE_UNKNOWN, IDLE_S, WebXRDevice
from telerig.devices.webxr.fake import LocalRelay, XRControllerInput, encode_frame, typical_payload
from telerig.devices.webxr.relay import MESSAGE, encode_event
from telerig.errors import DeviceError
from telerig.ir.types import ControllerState, Sample

TIMEOUT_S = 5.0


class Collector:
    """A sink that records samples and signals when ``n`` have arrived."""

    def __init__(self) -> None:
        self.samples: list[Sample] = []
        self._cond = threading.Condition()

    def __call__(self, sample: Sample) -> None:
        with self._cond:
            self.samples.append(sample)
            self._cond.notify_all()

    def wait(self, n: int) -> list[Sample]:
        with self._cond:
            assert self._cond.wait_for(lambda: len(self.samples) >= n, TIMEOUT_S), (
                f"{len(self.samples)} < {n}"
            )
            return list(self.samples)


def wait_for(predicate: Callable[[], object], what: str, timeout_s: float = TIMEOUT_S) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(0.01)
    raise AssertionError(f"timed out waiting for {what}")


@pytest.fixture
def device() -> Iterator[tuple[WebXRDevice, LocalRelay, Collector]]:
    dev = WebXRDevice("xr0", ping_interval_s=0.05)
    relay = LocalRelay(dev)
    sink = Collector()
    dev.start(sink)
    yield dev, relay, sink
    dev.stop()


def test_implements_the_device_protocols() -> None:
    dev = WebXRDevice()
    assert isinstance(dev, Device)
    assert isinstance(dev, OperatedDevice)
    assert isinstance(dev, RelayedDevice)


def test_relayed_frames_become_samples_with_increasing_seq(
    device: tuple[WebXRDevice, LocalRelay, Collector],
) -> None:
    dev, relay, sink = device
    page = relay.open()
    for seq in range(3):
        page.send(encode_frame(seq, relay.now_ms(), right=XRControllerInput(trigger=0.5)))
    got = sink.wait(3)
    assert all(isinstance(s, ControllerState) and s.trigger == 0.5 for s in got)
    assert [s.stamp.seq for s in got] == [0, 1, 2]
    assert {s.stamp.source_id for s in got} == {"xr0/right"}
    assert dev.active_user == "otto (127.0.0.1)"


def test_typical_frame_yields_five_samples(device: tuple[WebXRDevice, LocalRelay, Collector]) -> None:
    _, relay, sink = device
    relay.open().send(typical_payload())
    assert len(sink.wait(5)) == 5


def test_bad_messages_and_envelopes_are_dropped_and_counted(
    device: tuple[WebXRDevice, LocalRelay, Collector],
) -> None:
    dev, relay, sink = device
    page = relay.open()
    page.send(b"garbage!")
    page.send(encode_frame(5, relay.now_ms(), right=XRControllerInput(trigger=3.0)))
    page.send(encode_frame(5, relay.now_ms(), right=XRControllerInput(position=(1e30, 0.0, 0.0))))
    page.send(encode_frame(5, relay.now_ms(), right=XRControllerInput()))
    page.send(encode_frame(5, relay.now_ms(), right=XRControllerInput()))  # repeated seq
    dev.page_message(b"\x00" * 40)  # not an envelope
    dev.page_message(b"TR\x01\x02" + b"\x00" * 8 + b"\x00" * (1 << 15))  # oversized
    sink.wait(1)
    wait_for(lambda: dev.stats.get("drop_relay") == 2, "the bad envelopes to be counted")
    stats = dev.stats
    assert (stats["drop_magic"], stats["drop_analog"], stats["drop_position"]) == (1, 1, 1)
    assert (stats["drop_stale_seq"], stats["frames"]) == (1, 1)
    assert len(sink.samples) == 1


def test_a_message_of_an_unknown_page_gets_a_close_that_makes_it_reconnect(
    device: tuple[WebXRDevice, LocalRelay, Collector],
) -> None:
    dev, relay, sink = device
    frame = encode_frame(0, relay.now_ms(), right=XRControllerInput())
    for _ in range(3):  # e.g. the station restarted while the page stayed connected to the server
        dev.page_message(encode_event(MESSAGE, 99, frame))
    wait_for(lambda: dev.stats.get("drop_unknown_page") == 3, "the unknown page's frames dropped")
    assert relay.closed[99][0] == CLOSE_UNKNOWN  # once
    assert sink.samples == []


def test_clock_offset_tracks_the_page_clock_skew() -> None:
    dev = WebXRDevice("xr0", ping_interval_s=0.05)
    relay = LocalRelay(dev, clock_skew_ms=-3_000.0)
    sink = Collector()
    dev.start(sink)
    try:
        page = relay.open()
        wait_for(lambda: dev.stats.get("pongs", 0) >= 3, "three pongs")
        client_ms = relay.now_ms()
        page.send(encode_frame(0, client_ms, right=XRControllerInput()))
        (sample,) = sink.wait(1)
    finally:
        dev.stop()
    offset = dev.clock_offset_ns
    assert offset is None  # the page is closed with the device
    assert sample.stamp.device_ns == round(client_ms * 1e6)
    # capture = page time + offset (~ +3 s), never after the arrival
    assert abs(sample.stamp.capture_ns - (sample.stamp.device_ns + 3_000_000_000)) < 50_000_000


def test_a_silent_page_is_forgotten_so_another_may_drive(
    device: tuple[WebXRDevice, LocalRelay, Collector],
) -> None:
    dev, _, sink = device
    silent = LocalRelay(dev)  # a relay that never answers pings: the server died
    silent._from_device = lambda payload: None  # type: ignore[method-assign]
    dev.set_page_sink(silent._from_device)
    silent.open("gone")
    wait_for(lambda: dev.active_user is not None, "the first page to drive")
    wait_for(lambda: dev.stats.get("expired") == 1, "the silent page to expire", IDLE_S + 2.0)
    relay = LocalRelay(dev)
    page = relay.open("otto")
    page.send(encode_frame(0, relay.now_ms(), right=XRControllerInput()))
    sink.wait(1)
    assert dev.active_user == "otto (127.0.0.1)"


def test_stop_is_idempotent_restart_works_and_closes_the_pages() -> None:
    dev = WebXRDevice("xr0", ping_interval_s=0.05)
    relay = LocalRelay(dev)
    sink = Collector()
    dev.start(sink)
    with pytest.raises(DeviceError, match="already running"):
        dev.start(sink)
    page = relay.open()
    wait_for(lambda: dev.active_user is not None, "the page to drive")
    dev.stop()
    dev.stop()
    assert page.close_code == 1001
    dev.page_message(encode_event(MESSAGE, page.conn, b"x"))
    assert dev.stats["drop_stopped"] == 1
    dev.start(sink)
    try:
        page = relay.open()
        page.send(encode_frame(0, relay.now_ms(), right=XRControllerInput()))
        sink.wait(1)
    finally:
        dev.stop()


def test_config_builds_the_device() -> None:
    dev = WebXRConfig(id="xr9", ping_interval_s=0.2, takeover="confirm").build()
    assert isinstance(dev, WebXRDevice)
    assert (dev.id, dev.ping_interval_s, dev.takeover) == ("xr9", 0.2, "confirm")
    with pytest.raises(ValueError, match="host"):
        WebXRConfig.model_validate({"id": "xr0", "host": "0.0.0.0"})  # the page is telerig serve's now
