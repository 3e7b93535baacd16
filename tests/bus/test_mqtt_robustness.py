"""MqttBus under load and abuse: many writers, big packets, idle links, handlers that publish or
close, and a broker that answers garbage; against a real Mosquitto or a raw TCP peer."""

from __future__ import annotations

import os
import socket
import threading
import time

import pytest

from telerig.bus.base import Inbox, Message
from telerig.bus.broker import MosquittoBroker
from telerig.bus.mqtt import MqttBus

from .test_mqtt import WAIT_S, MakeBus, flush, get, wait_until

#: CONNACK, session not present, accepted (MQTT 3.1.1, 3.2).
CONNACK_OK = bytes([0x20, 0x02, 0x00, 0x00])


def _collect(bus: MqttBus, pattern: str) -> list[Message]:
    got: list[Message] = []
    bus.subscribe(pattern, got.append)
    flush(bus)
    return got


@pytest.mark.broker
def test_a_handler_may_publish_and_its_messages_keep_their_order(make_bus: MakeBus) -> None:
    echo, peer = make_bus("echo"), make_bus("peer")
    echo.subscribe("t/ping", lambda message: echo.publish("t/pong", message.payload + b"!", qos=1))
    flush(echo)
    got = _collect(peer, "t/pong")
    for i in range(50):
        peer.publish("t/ping", str(i).encode())
    wait_until(lambda: len(got) == 50, "50 echoes")
    assert [m.payload for m in got] == [f"{i}!".encode() for i in range(50)]


def _open_fds() -> int:
    return len(os.listdir("/proc/self/fd"))


@pytest.mark.broker
def test_close_from_a_handler_ends_the_network_thread_and_leaks_no_descriptor(
    broker: MosquittoBroker, make_bus: MakeBus
) -> None:
    peer = make_bus("peer")
    before = _open_fds()
    node = MqttBus(broker.url, client_id="node").connect()
    closed = threading.Event()

    def close(message: Message) -> None:
        node.close()
        closed.set()

    node.subscribe("t/close", close)
    flush(node)
    peer.publish("t/close", b"")
    assert closed.wait(WAIT_S)
    wait_until(lambda: not any(t.name.endswith("-node") for t in threading.enumerate()), "its thread to end")
    assert not node.connected
    assert _open_fds() == before  # the client socket and paho's wake-up pair are closed


@pytest.mark.broker
def test_concurrent_publishers_never_interleave_packets(make_bus: MakeBus) -> None:
    node, peer = make_bus("node"), make_bus("peer")
    got = _collect(peer, "t/+")
    # A send buffer this small makes the kernel take big packets in pieces.
    node._client.socket().setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4096)
    threads, per_thread = 4, 200

    def payload(writer: int, i: int) -> bytes:
        return f"{writer}:{i}:".encode() + bytes([writer + i & 0xFF]) * (i * 97 % 40_000)

    def publish(writer: int) -> None:
        for i in range(per_thread):
            node.publish(f"t/{writer}", payload(writer, i))

    workers = [threading.Thread(target=publish, args=(w,)) for w in range(threads)]
    for worker in workers:
        worker.start()
    for worker in workers:
        worker.join()
    wait_until(lambda: len(got) == threads * per_thread, f"{threads * per_thread} messages")
    assert (node.stats.reconnects, node.stats.publish_overflow) == (0, 0)
    for writer in range(threads):
        mine = [m.payload for m in got if m.topic == f"t/{writer}"]
        assert mine == [payload(writer, i) for i in range(per_thread)]  # whole, and in order


@pytest.mark.broker
def test_keepalive_pings_hold_an_idle_connection(make_bus: MakeBus) -> None:
    # Mosquitto drops a client silent for 1.5 x its keep-alive; paho's network thread pings before that.
    node, peer = make_bus("node", keepalive_s=1), make_bus("peer")
    got = _collect(node, "t/x")
    time.sleep(3.2)
    assert node.connected
    assert node.stats.reconnects == 0
    peer.publish("t/x", b"still here")
    wait_until(lambda: len(got) == 1, "a message after 3 idle seconds")


class _RawPeer:
    """A TCP listener on 127.0.0.1 that answers each CONNECT with ``reply``: a hostile broker."""

    def __init__(self, reply: bytes) -> None:
        self.reply = reply
        self.connects = 0
        self._server = socket.create_server(("127.0.0.1", 0))
        self._server.settimeout(0.2)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    @property
    def url(self) -> str:
        return f"mqtt://127.0.0.1:{self._server.getsockname()[1]}"

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._server.accept()
            except TimeoutError:
                continue
            with conn:
                conn.settimeout(WAIT_S)
                try:
                    conn.recv(4096)  # CONNECT
                    self.connects += 1
                    conn.sendall(self.reply)
                    conn.recv(4096)  # until the client drops us
                except OSError:
                    pass

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self._server.close()


@pytest.mark.parametrize(
    "garbage",
    [
        pytest.param(b"\xff" * 100_000, id="reserved packet type"),
        pytest.param(bytes([0x30, 0xFF, 0xFF, 0xFF, 0xFF, 0x7F]), id="remaining length over 4 bytes"),
        pytest.param(bytes([0x30, 0x03, 0xFF, 0xFF, 0x00]), id="topic length past the packet"),
    ],
)
def test_garbage_after_connack_drops_the_connection_and_reconnects(garbage: bytes) -> None:
    peer = _RawPeer(CONNACK_OK + garbage)
    bus = MqttBus(peer.url, client_id="node", reconnect_min_s=0.05, reconnect_max_s=0.1)
    got: list[Message] = []
    try:
        bus.subscribe("t/#", got.append)
        bus.connect()
        wait_until(lambda: peer.connects >= 3, "the client to reconnect after each garbage reply")
        assert bus.stats.reconnects >= 1
        assert got == []
    finally:
        bus.close()
        peer.close()


@pytest.mark.broker
def test_a_slow_handler_delays_but_never_drops_publishes(make_bus: MakeBus) -> None:
    # The network thread is busy reading (a handler at 1 ms per message) while another thread
    # publishes: the publishes still reach the broker, in order, none dropped.
    node, peer = make_bus("node"), make_bus("peer")
    inbox = Inbox(maxlen=10_000)

    def slow(message: Message) -> None:
        time.sleep(0.001)
        inbox(message)

    node.subscribe("t/in", slow)
    flush(node)
    got = _collect(peer, "t/out")
    for i in range(200):
        peer.publish("t/in", b"x")
        node.publish("t/out", str(i).encode())
    wait_until(lambda: len(got) == 200, "200 publishes")
    assert [int(m.payload) for m in got] == list(range(200))
    wait_until(lambda: len(inbox) == 200, "200 deliveries")
    assert get(inbox).topic == "t/in"
