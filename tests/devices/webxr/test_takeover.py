"""One page drives a WebXR device (issue 11, finding 4): a second page is refused, or held until the
operator confirms or denies the takeover, each one an alert; over a real Mosquitto the pages' relay
envelopes and the operator's answer travel on the device's topics. Also the server's generated
certificate (``pairing.self_signed_pair``, the TLS of ``telerig serve``)."""

from __future__ import annotations

import json
import queue
import stat
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from telerig.bus.broker import MosquittoBroker
from telerig.bus.catalogue import PAGE_IN, PAGE_OUT
from telerig.bus.mqtt import MqttBus
from telerig.bus.topics import Topic
from telerig.cli.main import main
from telerig.devices.base import DeviceAlert
from telerig.devices.webxr.device import CLOSE_REFUSED, CLOSE_REPLACED, WebXRDevice
from telerig.devices.webxr.fake import LocalPage, LocalRelay, XRControllerInput, encode_frame
from telerig.devices.webxr.pairing import KEY_FILE, self_signed_pair
from telerig.devices.webxr.relay import (
    CLOSE,
    MESSAGE,
    OPEN,
    decode_event,
    encode_event,
    open_body,
    parse_close,
)
from telerig.ir.types import Sample
from telerig.runtime.device_node import DeviceNode

TIMEOUT_S = 5.0


class Collector:
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


class Alerts:
    def __init__(self) -> None:
        self.alerts: list[DeviceAlert] = []
        self._cond = threading.Condition()

    def __call__(self, alert: DeviceAlert) -> None:
        with self._cond:
            self.alerts.append(alert)
            self._cond.notify_all()

    def wait_for(self, code: str) -> DeviceAlert:
        with self._cond:
            assert self._cond.wait_for(lambda: any(a.code == code for a in self.alerts), TIMEOUT_S), (
                self.alerts
            )
            return next(a for a in self.alerts if a.code == code)

    @property
    def codes(self) -> list[str]:
        with self._cond:
            return [a.code for a in self.alerts]


def wait_for(predicate: Callable[[], object], what: str) -> None:
    deadline = time.monotonic() + TIMEOUT_S
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(0.01)
    raise AssertionError(f"timed out waiting for {what}")


def _frame(relay: LocalRelay, seq: int) -> bytes:
    return encode_frame(seq, relay.now_ms(), right=XRControllerInput())


@pytest.fixture
def confirm() -> Iterator[tuple[WebXRDevice, LocalRelay, Collector, Alerts]]:
    dev = WebXRDevice("xr0", takeover="confirm", takeover_timeout_s=1.0, ping_interval_s=0.05)
    relay = LocalRelay(dev)
    sink, alerts = Collector(), Alerts()
    dev.set_alert_sink(alerts)
    dev.start(sink)
    yield dev, relay, sink, alerts
    dev.stop()


def _closed(page: LocalPage) -> int:
    wait_for(lambda: page.close_code is not None, f"page {page.conn} to be closed")
    code = page.close_code
    assert code is not None
    return code


def test_a_second_page_is_refused_while_one_drives_and_alerts_once_per_user() -> None:
    dev = WebXRDevice("xr0")
    relay, sink, alerts = LocalRelay(dev), Collector(), Alerts()
    dev.set_alert_sink(alerts)
    dev.start(sink)
    try:
        first = relay.open("otto")
        first.send(_frame(relay, 0))
        sink.wait(1)
        seconds = [relay.open("eve") for _ in range(3)]  # a page retrying must not flood the alerts
        assert [_closed(p) for p in seconds] == [CLOSE_REFUSED] * 3
        for page in seconds:
            page.send(_frame(relay, 1))
        first.send(_frame(relay, 1))
        got = sink.wait(2)
    finally:
        dev.stop()
    assert [s.stamp.seq for s in got] == [0, 1]
    assert dev.stats["refused_takeover"] == 3
    assert alerts.codes == ["takeover_refused"]
    assert "eve" in alerts.alerts[0].reason
    assert "otto" in alerts.alerts[0].reason


def test_a_confirmed_takeover_closes_the_old_page(
    confirm: tuple[WebXRDevice, LocalRelay, Collector, Alerts],
) -> None:
    dev, relay, sink, alerts = confirm
    first = relay.open("otto")
    first.send(_frame(relay, 0))
    sink.wait(1)
    second = relay.open("ada")
    requested = alerts.wait_for("takeover_requested")
    assert dev.pending_takeover == "ada (127.0.0.1)"
    assert "ada" in requested.reason
    second.send(_frame(relay, 0))  # held: not driving yet
    first.send(_frame(relay, 1))  # the operator's page still drives while the request waits
    sink.wait(2)
    assert "confirmed" in dev.command({"takeover": "confirm"})
    assert alerts.wait_for("takeover").severity == "warning"
    assert _closed(first) == CLOSE_REPLACED
    first.send(_frame(relay, 2))
    second.send(_frame(relay, 1))
    got = sink.wait(3)
    wait_for(lambda: dev.stats.get("drop_unknown_page") == 1, "the old page's frame dropped")
    assert len(got) == 3
    assert dev.stats["replaced"] == 1
    assert dev.stats["drop_inactive_page"] == 1
    assert dev.active_user == "ada (127.0.0.1)"


def test_denied_or_unanswered_takeover_is_refused(
    confirm: tuple[WebXRDevice, LocalRelay, Collector, Alerts],
) -> None:
    dev, relay, sink, alerts = confirm
    first = relay.open("otto")
    denied = relay.open("ada")
    alerts.wait_for("takeover_requested")
    assert "denied" in dev.command({"takeover": "deny"})
    assert _closed(denied) == CLOSE_REFUSED
    unanswered = relay.open("bob")  # takeover_timeout_s = 1 s
    assert _closed(unanswered) == CLOSE_REFUSED
    assert alerts.codes.count("takeover_refused") == 2
    first.send(_frame(relay, 0))
    sink.wait(1)
    assert "replaced" not in dev.stats
    assert "unknown command" in dev.command({"estop": True})
    assert "no page is waiting" in dev.command({"takeover": "confirm"})


@pytest.mark.broker
def test_relayed_pages_and_the_takeover_travel_over_the_bus(
    broker: MosquittoBroker, make_bus: Callable[..., MqttBus], capsys: pytest.CaptureFixture[str]
) -> None:
    # The shipped webxr rig names its device "browser"; the server's side is played by a bus client.
    dev = WebXRDevice("browser", takeover="confirm", ping_interval_s=0.05)
    node = DeviceNode("webxr", dev, make_bus("xr-node"), health_period_s=None)
    server = make_bus("web")
    page_in = str(Topic("webxr", "browser", PAGE_IN))
    out: queue.Queue[tuple[int, int, bytes]] = queue.Queue()
    server.subscribe(
        str(Topic("webxr", "browser", PAGE_OUT)),
        lambda m: out.put((e.event, e.conn, e.body)) if (e := decode_event(m.payload)) else None,
    )
    events: queue.Queue[dict[str, object]] = queue.Queue()
    server.subscribe(
        str(Topic("webxr", "browser", "events")), lambda m: events.put(json.loads(m.payload)), qos=1
    )

    def next_event(code: str) -> dict[str, object]:
        while True:
            event = events.get(timeout=TIMEOUT_S)
            if event["code"] == code:
                return event

    def next_out(event: int, conn: int) -> bytes:
        while True:
            got = out.get(timeout=TIMEOUT_S)
            if got[:2] == (event, conn):
                return got[2]

    argv = ["device", "takeover", "confirm", "--rig", "webxr", "--device", "browser", "--broker", broker.url]
    node.start()
    try:
        assert main(argv) == 1  # nothing is waiting
        assert "no page is waiting" in capsys.readouterr().out
        server.publish(page_in, encode_event(OPEN, 1, open_body("otto", "10.0.0.5")), qos=1)
        assert len(next_out(MESSAGE, 1)) == 8  # the device pings its page through the server
        server.publish(page_in, encode_event(MESSAGE, 1, encode_frame(0, time.time_ns() / 1e6)), qos=1)
        wait_for(lambda: dev.stats.get("frames") == 1, "the relayed frame")
        server.publish(page_in, encode_event(OPEN, 2, open_body("ada", "10.0.0.6")), qos=1)
        assert "ada" in str(next_event("takeover_requested")["reason"])
        assert main(argv) == 0
        assert "confirmed" in capsys.readouterr().out
        assert next_event("takeover")["severity"] == "warning"
        assert parse_close(next_out(CLOSE, 1))[0] == CLOSE_REPLACED
        assert dev.stats["replaced"] == 1
    finally:
        node.stop()


def test_generated_certificate_is_reused_from_the_tls_dir_with_a_0600_key(tmp_path: Path) -> None:
    cert, key = self_signed_pair(tmp_path, "127.0.0.1")
    assert key == tmp_path / KEY_FILE
    assert stat.S_IMODE(key.stat().st_mode) == 0o600
    first = cert.read_bytes()
    assert self_signed_pair(tmp_path, "127.0.0.1") == (cert, key)
    assert cert.read_bytes() == first
    self_signed_pair(tmp_path, "10.1.2.3")  # a new address needs a new certificate
    assert cert.read_bytes() != first
