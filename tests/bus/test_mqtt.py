"""MqttBus and MosquittoBroker against a real Mosquitto on 127.0.0.1."""

from __future__ import annotations

import os
import socket
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from telerig.bus.base import Bus, Inbox, Message
from telerig.bus.broker import MosquittoBroker, find_mosquitto
from telerig.bus.mqtt import MqttBus, MqttUrl, connect_bus
from telerig.bus.topics import Topic, qos_for
from telerig.errors import BusError, ConfigError, DependencyError

MakeBus = Callable[..., MqttBus]
WAIT_S = 5.0


def flush(bus: Bus) -> None:
    """Wait until the broker has processed everything ``bus`` sent so far.

    Publishes a probe to itself: MQTT keeps a connection's packets in order, so once
    the probe is back, earlier subscriptions and publishes have been handled.
    """
    probe = Inbox()
    topic = f"_probe/{id(bus)}"
    sub = bus.subscribe(topic, probe, qos=1)
    bus.publish(topic, b"probe", qos=1)
    try:
        assert probe.get(timeout=WAIT_S) is not None, "probe did not come back from the broker"
    finally:
        sub.cancel()


def wait_until(condition: Callable[[], bool], what: str) -> None:
    """Poll ``condition`` every 10 ms; fail naming ``what`` after WAIT_S seconds."""
    deadline = time.monotonic() + WAIT_S
    while not condition():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {WAIT_S} s waiting for {what}")
        time.sleep(0.01)


def get(inbox: Inbox) -> Message:
    message = inbox.get(timeout=WAIT_S)
    assert message is not None, "no message within the timeout"
    return message


# URL parsing and missing programs: no broker needed.


def test_url_parses_credentials_and_default_port() -> None:
    url = MqttUrl.parse("mqtt://op%40lab:s3cr%3At@broker.local")
    assert url == MqttUrl("broker.local", 1883, "op@lab", "s3cr:t")
    assert str(url) == "mqtt://op@lab:***@broker.local:1883"


@pytest.mark.parametrize(
    "url", ["tcp://localhost:1883", "localhost:1883", "mqtt://", "mqtt://h:99999", "mqtt://h/x"]
)
def test_url_rejects_other_forms_naming_the_valid_form(url: str) -> None:
    with pytest.raises(ConfigError, match=r"mqtt://\[user:password@\]host\[:port\]"):
        MqttUrl.parse(url)


def test_missing_binary_raises_dependency_error(tmp_path: Path) -> None:
    with pytest.raises(DependencyError, match="apt-get install mosquitto"):
        MosquittoBroker(binary=tmp_path / "mosquitto").start()


def test_find_mosquitto_rejects_non_executable_file(tmp_path: Path) -> None:
    fake = tmp_path / "mosquitto"
    fake.write_text("")
    with pytest.raises(DependencyError, match="not executable"):
        find_mosquitto(fake)


def test_broker_that_exits_raises_bus_error_with_log_tail(tmp_path: Path) -> None:
    fake = tmp_path / "mosquitto"
    # Writes to the log the config names, then fails like a broker with a bad config.
    fake.write_text(
        '#!/bin/sh\nlog=$(sed -n "s/^log_dest file //p" "$2")\necho "Error: boom" >> "$log"\nexit 3\n'
    )
    fake.chmod(0o755)
    broker = MosquittoBroker(port=1, binary=fake)
    with pytest.raises(BusError, match=r"exited with code 3(.|\n)*Error: boom"):
        broker.start()
    assert not broker.running


def test_a_port_another_program_listens_on_fails_with_mosquittos_error() -> None:
    """The other program answers on the port at once; the broker is up only once Mosquitto says so."""
    with socket.socket() as squatter:
        squatter.bind(("127.0.0.1", 0))
        squatter.listen()
        port = squatter.getsockname()[1]
        broker = MosquittoBroker(port=port)
        in_use = rf"^port {port} on 127\.0\.0\.1 is in use by another program: stop it, or give"
        with pytest.raises(BusError, match=in_use):
            broker.start()
        assert not broker.running
        broker.stop()


def test_any_port_picks_another_when_the_free_one_is_taken_before_mosquitto_binds_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import telerig.bus.broker as broker_module

    with socket.socket() as squatter:
        squatter.bind(("127.0.0.1", 0))
        squatter.listen()
        taken = squatter.getsockname()[1]
        picked: list[int] = []
        free_port = broker_module._free_port

        def pick() -> int:
            picked.append(taken if not picked else free_port())
            return picked[-1]

        monkeypatch.setattr(broker_module, "_free_port", pick)
        with MosquittoBroker() as broker:
            assert picked[0] == taken
            assert broker.port == picked[1] != taken
            assert "Address already in use" in broker.log_path.read_text()  # type: ignore[union-attr]
            with MqttBus(broker.url, client_id="after-retry") as bus:
                inbox = Inbox()
                bus.subscribe("t/retry", inbox, qos=1)
                bus.publish("t/retry", b"x", qos=1)
                received = inbox.get(timeout=5.0)
                assert received is not None
                assert received.payload == b"x"


def test_connect_to_closed_port_names_url_and_fix() -> None:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    bus = MqttBus(f"mqtt://127.0.0.1:{port}", client_id="lonely", connect_timeout_s=1.0)
    with pytest.raises(BusError, match=rf"mqtt://127\.0\.0\.1:{port}.*start a broker there") as err:
        bus.connect()
    bus.close()
    # The URL was required here: the hint must not suggest leaving it out (issue 11, finding 13).
    assert "no URL" not in str(err.value)


# Against a real broker.


@pytest.mark.broker
def test_publish_subscribe_round_trip(make_bus: MakeBus) -> None:
    pub, sub = make_bus("pub"), make_bus("sub")
    inbox = Inbox()
    sub.subscribe("telerig/v1/demo/vr0/pose", inbox)
    flush(sub)
    pub.publish("telerig/v1/demo/vr0/pose", b"\x00\x01payload")
    message = get(inbox)
    assert (message.topic, message.payload) == ("telerig/v1/demo/vr0/pose", b"\x00\x01payload")
    assert message.received_ns > 0
    assert isinstance(pub, Bus)
    assert (pub.stats.published, sub.stats.delivered) == (1, 2)  # sub also got its flush probe


@pytest.mark.broker
def test_wildcard_subscriptions_match_plus_and_hash(make_bus: MakeBus) -> None:
    pub, sub = make_bus("pub"), make_bus("sub")
    plus, hash_, exact = Inbox(), Inbox(), Inbox()
    sub.subscribe(Topic.pattern("demo", stream="session"), plus)
    sub.subscribe("telerig/v1/demo/#", hash_)
    sub.subscribe("telerig/v1/demo/vr0/session", exact)
    flush(sub)
    for topic in ("telerig/v1/demo/vr0/session", "telerig/v1/demo/arm/state", "telerig/v1/other/vr0/session"):
        pub.publish(topic, b"x")
    flush(pub)
    pub.publish("telerig/v1/demo/end/session", b"end")  # ordered after the others
    assert [get(plus).topic for _ in range(2)] == [
        "telerig/v1/demo/vr0/session",
        "telerig/v1/demo/end/session",
    ]
    assert [get(hash_).topic for _ in range(3)] == [
        "telerig/v1/demo/vr0/session",
        "telerig/v1/demo/arm/state",
        "telerig/v1/demo/end/session",
    ]
    assert get(exact).topic == "telerig/v1/demo/vr0/session"
    assert len(exact) == 0  # overlapping subscriptions deliver once per handler


@pytest.mark.broker
def test_retained_state_reaches_late_subscriber_with_qos1(make_bus: MakeBus) -> None:
    coordinator = make_bus("coordinator")
    topic = str(Topic("demo", "coordinator", "session"))
    qos, retain = qos_for("session")
    coordinator.publish(topic, b"recording", qos=qos, retain=retain)
    flush(coordinator)
    late = make_bus("late")
    inbox = Inbox()
    late.subscribe(Topic.pattern("demo", stream="session"), inbox, qos=1)
    message = get(inbox)
    assert (message.topic, message.payload) == (topic, b"recording")


@pytest.mark.broker
@pytest.mark.parametrize("nodelay", [True, False])
def test_tcp_nodelay_option_is_applied_to_the_socket(make_bus: MakeBus, nodelay: bool) -> None:
    bus = make_bus("node", tcp_nodelay=nodelay)
    sock = bus._client.socket()
    assert bool(sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY)) is nodelay


@pytest.mark.broker
def test_publish_overflow_counted_when_outgoing_queue_full(
    broker: MosquittoBroker, make_bus: MakeBus
) -> None:
    bus = make_bus("node", max_queued_messages=8)
    broker.stop()
    wait_until(lambda: not bus.connected, "the client to notice the broker is gone")
    for _ in range(20):
        bus.publish("telerig/v1/demo/node/status", b"x", qos=1)  # queued until reconnect, 8 fit
    bus.publish("telerig/v1/demo/node/pose", b"x", qos=0)  # QoS 0 while disconnected is dropped
    assert (bus.stats.published, bus.stats.publish_overflow) == (8, 13)


@pytest.mark.broker
def test_reconnects_after_broker_restart_and_keeps_subscriptions(
    broker: MosquittoBroker, make_bus: MakeBus
) -> None:
    pub, sub = make_bus("pub"), make_bus("sub")
    inbox = Inbox()
    sub.subscribe("telerig/v1/demo/+/pose", inbox)
    flush(sub)
    broker.restart()
    wait_until(lambda: sub.stats.reconnects == 1 and sub.connected, "sub to reconnect")
    wait_until(lambda: pub.stats.reconnects == 1 and pub.connected, "pub to reconnect")
    flush(sub)
    pub.publish("telerig/v1/demo/vr0/pose", b"after restart")
    assert get(inbox).payload == b"after restart"


@pytest.mark.broker
def test_raising_handler_is_counted_and_delivery_goes_on(make_bus: MakeBus) -> None:
    pub, sub = make_bus("pub"), make_bus("sub")

    def broken(message: Message) -> None:
        raise RuntimeError("handler bug")

    inbox = Inbox()
    sub.subscribe("t/x", broken)
    sub.subscribe("t/x", inbox)
    flush(sub)
    pub.publish("t/x", b"1")
    pub.publish("t/x", b"2")
    assert [get(inbox).payload for _ in range(2)] == [b"1", b"2"]
    assert sub.stats.handler_errors == 2


@pytest.mark.broker
def test_cancelled_subscription_gets_nothing_more(make_bus: MakeBus) -> None:
    pub, sub = make_bus("pub"), make_bus("sub")
    cancelled, kept = Inbox(), Inbox()
    subscription = sub.subscribe("t/a", cancelled)
    sub.subscribe("t/b", kept)
    flush(sub)
    subscription.cancel()
    subscription.cancel()
    pub.publish("t/a", b"late")
    pub.publish("t/b", b"marker")  # same publisher, so it arrives after t/a would have
    assert get(kept).payload == b"marker"
    assert len(cancelled) == 0


@pytest.mark.broker
def test_close_is_idempotent_and_later_publish_is_ignored(make_bus: MakeBus) -> None:
    bus = make_bus("node")
    bus.close()
    bus.close()
    bus.publish("t/x", b"after close")
    assert not bus.connected
    assert bus.stats.published == 0


@pytest.mark.broker
def test_broker_with_password_refuses_wrong_one() -> None:
    with MosquittoBroker(username="op", password="right") as broker:
        good = MqttBus(broker.url, client_id="good").connect()
        good.close()
        bad = MqttBus(f"mqtt://op:wrong@127.0.0.1:{broker.port}", client_id="bad")
        with pytest.raises(BusError, match=r"refused client 'bad'.*user and password"):
            bad.connect()
        bad.close()


@pytest.mark.broker
def test_connect_bus_without_url_owns_an_embedded_broker() -> None:
    bus = connect_bus(None, client_id="solo")
    broker = bus.broker
    assert broker is not None
    assert broker.running
    other = connect_bus(broker.url, client_id="other")
    assert other.broker is None
    other.close()
    bus.close()
    assert not broker.running


@pytest.mark.broker
def test_broker_stop_is_idempotent_and_leaves_no_process() -> None:
    broker = MosquittoBroker().start()
    pid = broker._proc.pid if broker._proc else -1
    broker.stop()
    broker.stop()
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)
