"""What a fake peer (robot controller, hand tracker) serves on: an asyncio main on a thread, or a
threaded accept loop."""

from __future__ import annotations

import asyncio
import contextlib
import socket
import threading
from collections.abc import Awaitable, Callable

from telerig.errors import TelerigError

__all__ = ["PeerLoop", "PeerMain", "accept_loop"]

#: A peer's server coroutine: ``main(ready, done)`` calls ``ready()`` once it listens, then serves
#: until ``done`` is set, and closes what it opened.
PeerMain = Callable[[Callable[[], None], asyncio.Event], Awaitable[None]]


class PeerLoop:
    """Runs a fake peer's server coroutine on its own thread, started and stopped from the caller's.

    Args:
        main: The server coroutine (see :data:`PeerMain`).
        what: The peer, for errors, e.g. ``"fake Dobot"``.
        thread_name: Name of the loop's thread.
        error: What :meth:`start` and :meth:`call` raise, e.g. ``RobotError`` for a robot's peer.
    """

    def __init__(
        self, main: PeerMain, *, what: str, thread_name: str, error: type[TelerigError] = TelerigError
    ) -> None:
        self._main = main
        self._errtype = error
        self._what = what
        self._thread_name = thread_name
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._done: asyncio.Event | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None

    @property
    def running(self) -> bool:
        """Whether the server is up (between :meth:`start` and :meth:`stop`)."""
        return self._thread is not None and self._loop is not None

    def start(self, timeout_s: float = 10.0) -> None:
        """Start the loop thread; returns once the peer listens. Idempotent.

        Raises:
            TelerigError: (the ``error`` given) the server failed to start (e.g. its port is taken).
        """
        if self._thread is not None:
            return
        self._ready.clear()
        self._error = None
        self._thread = threading.Thread(target=self._run, name=self._thread_name, daemon=True)
        self._thread.start()
        self._ready.wait(timeout_s)
        if self._error is not None:
            self._thread.join()
            self._thread = None
            raise self._errtype(f"{self._what} failed to start: {self._error}")

    def stop(self) -> None:
        """Stop serving and join the thread. Idempotent."""
        thread, self._thread = self._thread, None
        loop, done = self._loop, self._done
        if thread is None:
            return
        if loop is not None and done is not None:
            with contextlib.suppress(RuntimeError):  # the loop already finished
                loop.call_soon_threadsafe(done.set)
        thread.join()

    def call(self, fn: Callable[[], object], timeout_s: float = 5.0) -> None:
        """Run ``fn`` on the loop's thread and wait for it (fault injection from a test's thread).

        Raises:
            TelerigError: (the ``error`` given) the peer is not running.
        """
        loop = self._loop
        if loop is None or self._thread is None:
            raise self._errtype(f"the {self._what} is not running; call start() first")
        finished = threading.Event()

        def wrapped() -> None:
            try:
                fn()
            finally:
                finished.set()

        loop.call_soon_threadsafe(wrapped)
        finished.wait(timeout_s)

    def _run(self) -> None:
        try:
            asyncio.run(self._serve())
        except BaseException as exc:  # surfaced by start()
            self._error = exc
            self._ready.set()

    async def _serve(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._done = asyncio.Event()
        try:
            await self._main(self._ready.set, self._done)
        finally:
            self._loop = None


def accept_loop(
    listener: socket.socket,
    stop: threading.Event,
    on_client: Callable[[socket.socket, tuple[str, int]], None],
) -> None:
    """Accept connections until ``stop`` is set or ``listener`` is closed (a threaded fake peer's loop).

    Args:
        listener: A listening socket with a timeout [s], the longest ``stop`` goes unnoticed.
        stop: Ends the loop.
        on_client: Called with each accepted connection and its ``(host, port)``; it owns the socket.
    """
    while not stop.is_set():
        try:
            conn, address = listener.accept()
        except TimeoutError:
            continue
        except OSError:  # the listener was closed
            return
        on_client(conn, address)
