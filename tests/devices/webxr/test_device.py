"""WebXR device against the fake page on 127.0.0.1: samples, drops, clock offset, HTTP, lifecycle, config."""

from __future__ import annotations

import socket
import threading
import urllib.error
import urllib.request
from collections.abc import Iterator

import pytest
from websockets.exceptions import InvalidStatus

from telerig.devices.base import Device
from telerig.devices.webxr.config import WebXRConfig
from telerig.devices.webxr.device import WebXRDevice
from telerig.devices.webxr.fake import FakeXRPage, XRControllerInput, encode_frame, typical_payload
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


def wait_for(predicate: object, what: str) -> None:
    event = threading.Event()
    for _ in range(int(TIMEOUT_S / 0.01)):
        if predicate():  # type: ignore[operator]
            return
        event.wait(0.01)
    raise AssertionError(f"timed out waiting for {what}")


@pytest.fixture
def device() -> Iterator[tuple[WebXRDevice, Collector]]:
    dev = WebXRDevice("xr0", host="127.0.0.1", port=0, ping_interval_s=0.05)
    sink = Collector()
    dev.start(sink)
    yield dev, sink
    dev.stop()


def test_implements_device_protocol() -> None:
    assert isinstance(WebXRDevice(), Device)


def test_fake_page_frames_become_samples_with_increasing_seq(device: tuple[WebXRDevice, Collector]) -> None:
    dev, sink = device
    with FakeXRPage(dev.ws_url) as page:
        for seq in range(3):
            page.send(encode_frame(seq, page.now_ms(), right=XRControllerInput(trigger=0.5)))
        got = sink.wait(3)
    assert all(isinstance(s, ControllerState) and s.trigger == 0.5 for s in got)
    assert [s.stamp.seq for s in got] == [0, 1, 2]
    assert {s.stamp.source_id for s in got} == {"xr0/right"}


def test_typical_frame_yields_five_samples(device: tuple[WebXRDevice, Collector]) -> None:
    dev, sink = device
    with FakeXRPage(dev.ws_url) as page:
        page.send(typical_payload())
        assert len(sink.wait(5)) == 5


def test_bad_messages_are_dropped_and_counted(device: tuple[WebXRDevice, Collector]) -> None:
    dev, sink = device
    with FakeXRPage(dev.ws_url) as page:
        page.send(b"garbage!")
        page.send("text")
        page.send(encode_frame(5, page.now_ms(), right=XRControllerInput(trigger=3.0)))
        page.send(encode_frame(5, page.now_ms(), right=XRControllerInput()))
        page.send(encode_frame(5, page.now_ms(), right=XRControllerInput()))  # repeated seq
        sink.wait(1)
        wait_for(lambda: dev.stats.get("drop_stale_seq") == 1, "the stale frame to be counted")
    stats = dev.stats
    assert (stats["drop_magic"], stats["drop_text"], stats["drop_analog"], stats["frames"]) == (1, 1, 1, 1)


def test_clock_offset_tracks_the_page_clock_skew(device: tuple[WebXRDevice, Collector]) -> None:
    dev, sink = device
    with FakeXRPage(dev.ws_url, clock_skew_ms=-3_000.0) as page:
        wait_for(lambda: page.pings_answered >= 3, "three pongs")
        wait_for(lambda: dev.stats.get("pongs", 0) >= 3, "the server to read three pongs")
        client_ms = page.now_ms()
        page.send(encode_frame(0, client_ms, right=XRControllerInput()))
        (sample,) = sink.wait(1)
    offset = dev.clock_offset_ns
    assert offset is not None
    assert abs(offset - 3_000_000_000) < 50_000_000  # within 50 ms on localhost
    assert sample.stamp.device_ns == round(client_ms * 1e6)
    assert sample.stamp.capture_ns == min(sample.stamp.device_ns + offset, sample.stamp.capture_ns)


def test_a_second_page_is_refused_while_one_drives(device: tuple[WebXRDevice, Collector]) -> None:
    # Issue 11 finding 4: a second page used to replace the operator's silently.
    dev, sink = device
    with FakeXRPage(dev.ws_url) as first:
        first.send(encode_frame(0, first.now_ms(), right=XRControllerInput()))
        sink.wait(1)
        with pytest.raises(InvalidStatus) as refused:
            FakeXRPage(dev.ws_url)
        assert refused.value.response.status_code == 409
        first.send(encode_frame(1, first.now_ms(), right=XRControllerInput()))
        got = sink.wait(2)
    assert [s.stamp.seq for s in got] == [0, 1]
    assert dev.stats.get("refused_takeover") == 1
    assert "replaced" not in dev.stats


def test_page_and_module_are_served_and_unknown_paths_404(device: tuple[WebXRDevice, Collector]) -> None:
    dev, _ = device
    with urllib.request.urlopen(dev.url, timeout=TIMEOUT_S) as r:
        assert r.headers["Content-Type"].startswith("text/html")
        assert b'src="/telerig-xr.js"' in r.read()
    with urllib.request.urlopen(dev.url + "telerig-xr.js", timeout=TIMEOUT_S) as r:
        assert r.headers["Content-Type"].startswith("text/javascript")
    with pytest.raises(urllib.error.HTTPError) as info:
        urllib.request.urlopen(dev.url + "fake-xr.js", timeout=TIMEOUT_S)
    assert info.value.code == 404
    info.value.close()


def test_busy_port_raises_device_error() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        dev = WebXRDevice(host="127.0.0.1", port=s.getsockname()[1])
        with pytest.raises(DeviceError, match="cannot listen"):
            dev.start(lambda _s: None)
    assert not dev.running


def test_stop_is_idempotent_and_restart_works() -> None:
    dev = WebXRDevice(host="127.0.0.1", port=0)
    dev.stop()
    dev.start(lambda _s: None)
    with pytest.raises(DeviceError, match="already running"):
        dev.start(lambda _s: None)
    dev.stop()
    dev.stop()
    assert not dev.running
    dev.start(lambda _s: None)
    dev.stop()


def test_half_a_tls_pair_is_rejected() -> None:
    with pytest.raises(DeviceError, match="together"):
        WebXRDevice(certfile="cert.pem")
    with pytest.raises(ValueError, match="together"):
        WebXRConfig(id="xr0", certfile="cert.pem")  # type: ignore[arg-type]


def test_config_builds_the_device() -> None:
    cfg = WebXRConfig.model_validate({"type": "webxr", "id": "quest", "host": "127.0.0.1", "port": 0})
    dev = cfg.build()
    assert isinstance(dev, WebXRDevice)
    assert (dev.id, dev.host, dev.port, dev.certfile) == ("quest", "127.0.0.1", 0, None)
