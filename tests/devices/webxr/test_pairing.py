"""WebXR server ownership (issue 11, finding 4): loopback by default; pairing token, origin check and a
generated self-signed TLS certificate when paired; takeovers refused or confirmed by the operator,
each one an alert. Real WebSocket clients over TLS on 127.0.0.1."""

from __future__ import annotations

import io
import json
import queue
import ssl
import stat
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from websockets.exceptions import ConnectionClosed, InvalidStatus

from telerig.bus.broker import MosquittoBroker
from telerig.bus.mqtt import MqttBus
from telerig.bus.topics import Topic
from telerig.cli.main import main
from telerig.devices.base import DeviceAlert, OperatedDevice
from telerig.devices.webxr.config import WebXRConfig
from telerig.devices.webxr.device import WebXRDevice
from telerig.devices.webxr.fake import FakeXRPage, XRControllerInput, encode_frame
from telerig.devices.webxr.pairing import CERT_FILE, KEY_FILE, is_loopback, self_signed_pair
from telerig.errors import DeviceError
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


def _frame(page: FakeXRPage, seq: int) -> bytes:
    return encode_frame(seq, page.now_ms(), right=XRControllerInput())


@pytest.fixture
def paired(tmp_path: Path) -> Iterator[tuple[WebXRDevice, Collector, Alerts, io.StringIO]]:
    out = io.StringIO()
    dev = WebXRDevice(
        "xr0", host="127.0.0.1", port=0, pairing=True, tls_dir=tmp_path / "tls", pairing_output=out,
        takeover="confirm", takeover_timeout_s=3.0, ping_interval_s=0.05,
    )  # fmt: skip
    sink, alerts = Collector(), Alerts()
    dev.set_alert_sink(alerts)
    dev.start(sink)
    yield dev, sink, alerts, out
    dev.stop()


def _trust(tmp_path: Path) -> ssl.SSLContext:
    context = ssl.create_default_context(cafile=tmp_path / "tls" / CERT_FILE)
    return context


def _ws(dev: WebXRDevice, token: str | None) -> str:
    return dev.ws_url + ("" if token is None else f"?token={token}")


def _closed_by_server(page: FakeXRPage) -> bool:
    for seq in range(2, 300):
        try:
            page.send(_frame(page, seq))
        except ConnectionClosed:
            return True
        threading.Event().wait(0.01)
    return False


def _token(dev: WebXRDevice) -> str:
    return dev.pairing_url.split("token=", 1)[1]


def test_default_config_listens_on_loopback_only() -> None:
    cfg = WebXRConfig.model_validate({"type": "webxr", "id": "xr"})
    assert cfg.host == "127.0.0.1"
    dev = cfg.build()
    assert isinstance(dev, WebXRDevice)
    assert not dev.token_required
    assert is_loopback("127.0.0.1")
    assert not is_loopback("0.0.0.0")
    assert not is_loopback("192.168.1.20")


def test_lan_binding_requires_pairing() -> None:
    assert WebXRDevice(host="0.0.0.0").token_required
    with pytest.raises(DeviceError, match="must require pairing"):
        WebXRDevice(host="0.0.0.0", pairing=False)


def test_paired_server_prints_url_and_qr_and_serves_tls_with_a_0600_key(
    paired: tuple[WebXRDevice, Collector, Alerts, io.StringIO], tmp_path: Path
) -> None:
    dev, sink, _, out = paired
    assert dev.pairing_url.startswith(f"https://127.0.0.1:{dev.port}/?token=")
    printed = out.getvalue()
    assert dev.pairing_url in printed
    assert "\u2580" in printed or "\u2584" in printed or "\u2588" in printed  # QR drawn in half blocks
    key = tmp_path / "tls" / KEY_FILE
    assert stat.S_IMODE(key.stat().st_mode) == 0o600
    with FakeXRPage(_ws(dev, _token(dev)), ssl_context=_trust(tmp_path)) as page:
        page.send(_frame(page, 0))
        assert len(sink.wait(1)) == 1


def test_generated_certificate_is_reused_from_the_tls_dir(tmp_path: Path) -> None:
    cert, key = self_signed_pair(tmp_path, "127.0.0.1")
    first = cert.read_bytes()
    assert self_signed_pair(tmp_path, "127.0.0.1") == (cert, key)
    assert cert.read_bytes() == first
    self_signed_pair(tmp_path, "10.1.2.3")  # a new address needs a new certificate
    assert cert.read_bytes() != first


def test_client_without_the_token_is_refused_with_one_alert(
    paired: tuple[WebXRDevice, Collector, Alerts, io.StringIO], tmp_path: Path
) -> None:
    dev, _, alerts, _ = paired
    for token in (None, "wrong"):
        with pytest.raises(InvalidStatus) as refused:
            FakeXRPage(_ws(dev, token), ssl_context=_trust(tmp_path))
        assert refused.value.response.status_code == 401
    assert dev.stats["refused_token"] == 2
    assert alerts.codes == ["token_refused"]


def test_foreign_origin_is_refused_and_own_origin_accepted(
    paired: tuple[WebXRDevice, Collector, Alerts, io.StringIO], tmp_path: Path
) -> None:
    dev, sink, alerts, _ = paired
    with pytest.raises(InvalidStatus) as refused:
        FakeXRPage(_ws(dev, _token(dev)), ssl_context=_trust(tmp_path), origin="https://evil.example")
    assert refused.value.response.status_code == 403
    assert alerts.wait_for("origin_refused").severity == "warning"
    own = f"https://127.0.0.1:{dev.port}"
    with FakeXRPage(_ws(dev, _token(dev)), ssl_context=_trust(tmp_path), origin=own) as page:
        page.send(_frame(page, 0))
        sink.wait(1)


def test_takeover_needs_the_token_and_the_operators_confirmation(
    paired: tuple[WebXRDevice, Collector, Alerts, io.StringIO], tmp_path: Path
) -> None:
    dev, sink, alerts, _ = paired
    assert isinstance(dev, OperatedDevice)
    context = _trust(tmp_path)
    with FakeXRPage(_ws(dev, _token(dev)), ssl_context=context) as first:
        first.send(_frame(first, 0))
        sink.wait(1)
        with pytest.raises(InvalidStatus):  # no token: refused before the operator is asked
            FakeXRPage(_ws(dev, None), ssl_context=context)
        assert "takeover_requested" not in alerts.codes
        second_page: list[FakeXRPage] = []
        opener = threading.Thread(
            target=lambda: second_page.append(FakeXRPage(_ws(dev, _token(dev)), ssl_context=context))
        )
        opener.start()
        requested = alerts.wait_for("takeover_requested")
        assert dev.pending_takeover is not None
        assert dev.pending_takeover in requested.reason
        first.send(_frame(first, 1))  # the operator's page still drives while the request waits
        sink.wait(2)
        assert "confirmed" in dev.command({"takeover": "confirm"})
        opener.join(TIMEOUT_S)
        (second,) = second_page
        with second:
            assert alerts.wait_for("takeover").severity == "warning"
            assert _closed_by_server(first)  # the old page is closed (4000) ...
            second.send(_frame(second, 0))
            got = sink.wait(3)
    assert len(got) == 3  # ... and none of its later frames became samples
    assert dev.stats["replaced"] == 1


def test_denied_or_unanswered_takeover_is_refused(
    paired: tuple[WebXRDevice, Collector, Alerts, io.StringIO], tmp_path: Path
) -> None:
    dev, sink, alerts, _ = paired
    context = _trust(tmp_path)
    with FakeXRPage(_ws(dev, _token(dev)), ssl_context=context) as first:
        errors: list[BaseException] = []

        def open_second() -> None:
            try:
                FakeXRPage(_ws(dev, _token(dev)), ssl_context=context).close()
            except InvalidStatus as exc:
                errors.append(exc)

        opener = threading.Thread(target=open_second)
        opener.start()
        alerts.wait_for("takeover_requested")
        assert "denied" in dev.command({"takeover": "deny"})
        opener.join(TIMEOUT_S)
        assert len(errors) == 1
        assert "takeover_refused" in alerts.codes
        first.send(_frame(first, 0))
        sink.wait(1)
    assert "replaced" not in dev.stats
    assert "unknown command" in dev.command({"estop": True})
    assert "no page is waiting" in dev.command({"takeover": "confirm"})


@pytest.mark.broker
def test_takeover_alerts_and_confirmation_travel_over_the_bus(
    make_bus: Callable[..., MqttBus], tmp_path: Path
) -> None:
    dev = WebXRDevice(
        "xr0", host="127.0.0.1", port=0, pairing=True, tls_dir=tmp_path / "tls", pairing_output=io.StringIO(),
        takeover="confirm",
    )  # fmt: skip
    node = DeviceNode("rig1", dev, make_bus("xr-node"), health_period_s=None)
    operator = make_bus("operator")
    events: queue.Queue[dict[str, object]] = queue.Queue()
    operator.subscribe(
        str(Topic("rig1", "xr0", "events")), lambda m: events.put(json.loads(m.payload)), qos=1
    )

    def next_event(code: str) -> dict[str, object]:
        while True:
            event = events.get(timeout=TIMEOUT_S)
            if event["code"] == code:
                return event

    node.start()
    try:
        context = _trust(tmp_path)
        with FakeXRPage(_ws(dev, _token(dev)), ssl_context=context):
            second_page: list[FakeXRPage] = []
            opener = threading.Thread(
                target=lambda: second_page.append(FakeXRPage(_ws(dev, _token(dev)), ssl_context=context))
            )
            opener.start()
            assert next_event("takeover_requested")["device"] == "xr0"
            operator.publish(str(Topic("rig1", "xr0", "command")), b'{"takeover": "confirm"}', qos=1)
            assert next_event("takeover")["severity"] == "warning"
            opener.join(TIMEOUT_S)
            second_page[0].close()
    finally:
        node.stop()


def test_refused_second_pages_alert_once_per_address() -> None:
    dev = WebXRDevice("xr0", host="127.0.0.1", port=0)
    sink, alerts = Collector(), Alerts()
    dev.set_alert_sink(alerts)
    dev.start(sink)
    try:
        with FakeXRPage(dev.ws_url) as first:
            for _ in range(3):  # a page retrying every second must not flood the alerts
                with pytest.raises(InvalidStatus):
                    FakeXRPage(dev.ws_url)
            first.send(_frame(first, 0))
            sink.wait(1)
    finally:
        dev.stop()
    assert dev.stats["refused_takeover"] == 3
    assert alerts.codes == ["takeover_refused"]
    assert "127.0.0.1:" in alerts.alerts[0].reason


@pytest.mark.broker
def test_telerig_device_takeover_confirms_over_the_bus(
    broker: MosquittoBroker, make_bus: Callable[..., MqttBus], capsys: pytest.CaptureFixture[str]
) -> None:
    # The shipped webxr rig names its device "browser".
    dev = WebXRDevice("browser", host="127.0.0.1", port=0, takeover="confirm")
    node = DeviceNode("webxr", dev, make_bus("xr-node"), health_period_s=None)
    node.start()
    argv = ["device", "takeover", "confirm", "--rig", "webxr", "--device", "browser", "--broker", broker.url]
    try:
        assert main(argv) == 1  # nothing is waiting
        assert "no page is waiting" in capsys.readouterr().out
        with FakeXRPage(dev.ws_url):
            second_page: list[FakeXRPage] = []
            opener = threading.Thread(target=lambda: second_page.append(FakeXRPage(dev.ws_url)))
            opener.start()
            for _ in range(500):
                if dev.pending_takeover is not None:
                    break
                threading.Event().wait(0.01)
            assert main(argv) == 0
            assert "confirmed" in capsys.readouterr().out
            opener.join(TIMEOUT_S)
            second_page[0].close()
        assert dev.stats["replaced"] == 1
    finally:
        node.stop()
