"""accept_loop: the threaded accept loop the fake glove bridge and the fake UR controller share."""

from __future__ import annotations

import socket
import threading

from telerig.bus.peer_loop import accept_loop


def test_accept_loop_hands_every_connection_over_and_ends_on_stop() -> None:
    listener = socket.create_server(("127.0.0.1", 0))
    listener.settimeout(0.05)
    stop = threading.Event()
    got: list[tuple[str, int]] = []
    both = threading.Event()

    def on_client(conn: socket.socket, address: tuple[str, int]) -> None:
        got.append(address)
        conn.close()
        if len(got) == 2:
            both.set()

    thread = threading.Thread(target=accept_loop, args=(listener, stop, on_client), daemon=True)
    thread.start()
    port = listener.getsockname()[1]
    clients = [socket.create_connection(("127.0.0.1", port)) for _ in range(2)]
    try:
        assert both.wait(5.0)
        assert {a[1] for a in got} == {c.getsockname()[1] for c in clients}
        stop.set()
        thread.join(2.0)
        assert not thread.is_alive()
    finally:
        for c in clients:
            c.close()
        listener.close()


def test_accept_loop_ends_when_its_listener_is_closed() -> None:
    listener = socket.create_server(("127.0.0.1", 0))
    listener.settimeout(0.05)
    thread = threading.Thread(
        target=accept_loop, args=(listener, threading.Event(), lambda c, a: c.close()), daemon=True
    )
    thread.start()
    listener.close()
    thread.join(2.0)
    assert not thread.is_alive()
