"""``mqtts://``: a real Mosquitto TLS listener on 127.0.0.1 with a certificate made by the test."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from telerig.bus.base import Message
from telerig.bus.broker import MosquittoBroker
from telerig.bus.mqtt import MqttBus, MqttUrl, TlsOptions
from telerig.errors import BusError, ConfigError

pytestmark = pytest.mark.broker


@pytest.fixture
def pki(tls_pki: tuple[Path, Path, Path]) -> tuple[Path, Path, Path]:
    return tls_pki


@pytest.fixture
def tls_broker(pki: tuple[Path, Path, Path]) -> Iterator[MosquittoBroker]:
    _, cert, key = pki
    with MosquittoBroker(certfile=cert, keyfile=key) as broker:
        yield broker


def test_mqtts_url_parses_with_the_tls_port() -> None:
    url = MqttUrl.parse("mqtts://op:secret@broker.lab")
    assert (url.tls, url.port) == (True, 8883)
    assert str(url) == "mqtts://op:***@broker.lab:8883"


def test_mqtts_with_the_ca_connects_and_keeps_tcp_nodelay(
    tls_broker: MosquittoBroker, pki: tuple[Path, Path, Path]
) -> None:
    ca, _, _ = pki
    assert tls_broker.url.startswith("mqtts://")
    got: list[Message] = []
    arrived = threading.Event()

    def on_message(message: Message) -> None:
        got.append(message)
        arrived.set()

    with MqttBus(tls_broker.url, client_id="tls", tls=TlsOptions(ca_file=ca)) as bus:
        sock = bus._client.socket()
        assert sock is not None
        assert sock.version() is not None  # a TLS socket
        assert sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY) != 0
        bus.subscribe("t/x", on_message, qos=1)
        bus.publish("t/x", b"over tls", qos=1)
        assert arrived.wait(3.0)
    assert got[0].payload == b"over tls"


def test_mqtts_without_the_ca_fails_with_one_line_naming_the_fix(tls_broker: MosquittoBroker) -> None:
    bus = MqttBus(tls_broker.url, client_id="no-ca")
    with pytest.raises(BusError) as raised:
        bus.connect()
    bus.close()
    message = str(raised.value)
    assert "\n" not in message
    assert "TLS handshake" in message
    assert "certificate verify failed" in message
    assert "ca_file" in message
    assert "secret" not in message


def test_tls_options_with_a_plain_url_are_refused(pki: tuple[Path, Path, Path]) -> None:
    with pytest.raises(ConfigError, match="use an mqtts:// URL"):
        MqttBus("mqtt://127.0.0.1:1883", client_id="x", tls=TlsOptions(ca_file=pki[0]))


def test_a_missing_ca_file_is_one_line(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"TLS ca_file '.*nope.pem' does not exist"):
        TlsOptions(ca_file=tmp_path / "nope.pem")


def test_over_tls_two_publishers_and_an_echo_keep_every_message_whole(
    tls_broker: MosquittoBroker, pki: tuple[Path, Path, Path]
) -> None:
    # Two threads publish while the same client receives an echo of each message: every record
    # of the TLS stream stays whole, in both directions.
    ca, _, _ = pki
    tls = TlsOptions(ca_file=ca)
    got: list[Message] = []
    with (
        MqttBus(tls_broker.url, client_id="node", tls=tls) as node,
        MqttBus(tls_broker.url, client_id="echo", tls=tls) as echo,
    ):
        echo.subscribe("t/+/in", lambda m: echo.publish(m.topic.replace("/in", "/out"), m.payload))
        node.subscribe("t/+/out", got.append)
        for bus in (node, echo):  # both subscriptions are in place once each probe is back
            probe = threading.Event()
            bus.subscribe("probe", lambda m, probe=probe: probe.set(), qos=1)
            bus.publish("probe", b"", qos=1)
            assert probe.wait(3.0)

        def publish(writer: int) -> None:
            for i in range(300):
                node.publish(f"t/{writer}/in", f"{i}".encode() * (i % 50 + 1))

        workers = [threading.Thread(target=publish, args=(w,)) for w in range(2)]
        for worker in workers:
            worker.start()
        for worker in workers:
            worker.join()
        deadline = time.monotonic() + 5.0
        while len(got) < 600 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert node.stats.reconnects == 0
    for writer in range(2):
        mine = [m.payload for m in got if m.topic == f"t/{writer}/out"]
        assert mine == [f"{i}".encode() * (i % 50 + 1) for i in range(300)]
