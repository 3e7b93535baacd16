"""The WebXR device: serves the page and its WebSocket on one port, turns page frames into IR samples."""

from __future__ import annotations

import asyncio
import contextlib
import http
import importlib.resources
import logging
import ssl
import threading
from collections import Counter
from collections.abc import Mapping
from pathlib import Path

from telerig.devices.base import SampleSink
from telerig.devices.webxr.protocol import (
    ClockOffset,
    Pong,
    WebXRWireError,
    decode,
    encode_ping,
    frame_samples,
)
from telerig.devices.worker import DeviceWorker
from telerig.errors import DependencyError, DeviceError
from telerig.ir.types import now_ns

__all__ = ["STATIC_FILES", "WS_PATH", "WebXRDevice"]

_log = logging.getLogger(__name__)

#: Path of the WebSocket endpoint; every other path serves a static file or 404.
WS_PATH = "/ws"
#: URL path → (file under ``static/``, content type). Only these are served.
STATIC_FILES: dict[str, tuple[str, str]] = {
    "/": ("index.html", "text/html; charset=utf-8"),
    "/index.html": ("index.html", "text/html; charset=utf-8"),
    "/telerig-xr.js": ("telerig-xr.js", "text/javascript; charset=utf-8"),
}
# Largest message accepted [bytes]: a full frame is 1,744 bytes.
_MAX_MESSAGE = 1 << 14
# Pings whose pong never came are forgotten after this many newer ones.
_MAX_PENDING_PINGS = 64


class WebXRDevice:
    """Serves the telerig WebXR page and turns what it streams into IR samples.

    One port carries both the page (``GET /``) and its WebSocket (``/ws``). Open
    ``https://<host>:<port>/`` in the headset browser (WebXR needs a secure context: HTTPS
    with ``certfile``/``keyfile``, or ``http://localhost`` e.g. through ``adb reverse``).

    Per frame the page sends, the sink receives (see :func:`~telerig.devices.webxr.protocol.frame_samples`)
    a head :class:`~telerig.ir.types.Pose`, one :class:`~telerig.ir.types.ControllerState` per
    controller and one :class:`~telerig.ir.types.HandPose` per tracked hand, in ``frame_id``
    (x forward, y left, z up, metres). ``device_ns`` is the page clock; ``capture_ns`` maps it to
    the common clock with an offset from a ping/pong exchange every ``ping_interval_s``
    (:class:`~telerig.devices.webxr.protocol.ClockOffset`).

    One page drives the device at a time: a newer connection (e.g. a reload) replaces the older
    one. Bad messages never stop the device; they are dropped and counted in :attr:`stats`
    (``drop_<reason>``).
    """

    def __init__(
        self,
        id: str = "xr0",
        *,
        host: str = "0.0.0.0",
        port: int = 8443,
        certfile: Path | str | None = None,
        keyfile: Path | str | None = None,
        frame_id: str = "operator",
        ping_interval_s: float = 0.5,
    ) -> None:
        """Args:
        id: Device id; source ids are ``"<id>/head"``, ``"<id>/left"``, ``"<id>/right_hand"``, ...
        host: Interface to listen on (``"0.0.0.0"``: every interface, for a headset on the LAN).
        port: TCP port (0: a free one; read :attr:`port` after ``start``).
        certfile: PEM certificate for HTTPS/WSS; ``None`` serves plain HTTP.
        keyfile: PEM private key matching ``certfile``.
        frame_id: Frame the samples are expressed in.
        ping_interval_s: Clock-sync ping period [s] (> 0).
        """
        if (certfile is None) != (keyfile is None):
            raise DeviceError("certfile and keyfile must be given together (or neither, for plain HTTP)")
        if not 0.0 < ping_interval_s <= 60.0:
            raise DeviceError(f"ping_interval_s must be in (0, 60] s, got {ping_interval_s}")
        self._id = id
        self.host = host
        self._requested_port = port
        self._port = port
        self.certfile = None if certfile is None else Path(certfile)
        self.keyfile = None if keyfile is None else Path(keyfile)
        self.frame_id = frame_id
        self.ping_interval_s = float(ping_interval_s)
        self._stats: Counter[str] = Counter()
        self._seqs: Counter[str] = Counter()
        self._lock = threading.Lock()  # guards _stats, _loop and _stop_future
        self._worker = DeviceWorker(id, kind="webxr device", thread_name=f"telerig-webxr-{id}", log=_log)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop_future: asyncio.Future[None] | None = None
        self._active: object | None = None
        self._clock: ClockOffset | None = None
        self._static: dict[str, bytes] = {}

    @property
    def id(self) -> str:
        """Device id."""
        return self._id

    @property
    def port(self) -> int:
        """TCP port the server listens on (the bound one once started)."""
        return self._port

    @property
    def url(self) -> str:
        """URL of the page, e.g. ``https://127.0.0.1:8443/``."""
        scheme = "http" if self.certfile is None else "https"
        host = "127.0.0.1" if self.host in ("0.0.0.0", "") else self.host
        return f"{scheme}://{host}:{self._port}/"

    @property
    def ws_url(self) -> str:
        """URL of the WebSocket endpoint."""
        return self.url.replace("http", "ws", 1).rstrip("/") + WS_PATH

    @property
    def running(self) -> bool:
        """Whether the server thread is running."""
        return self._worker.running

    @property
    def stats(self) -> Mapping[str, int]:
        """Counters (a copy): ``connections``, ``frames``, ``pongs``, ``samples``, ``sink_error`` and
        ``drop_<reason>``."""
        with self._lock:
            stats = dict(self._stats)
        return {**stats, "samples": self._worker.samples, "sink_error": self._worker.sink_errors}

    @property
    def clock_offset_ns(self) -> int | None:
        """Current estimate of common clock - page clock [ns] for the active page, if any."""
        clock = self._clock
        return None if clock is None else clock.offset_ns

    def start(self, sink: SampleSink) -> None:
        """Start serving on a new thread; returns once the port is bound.

        Raises:
            DeviceError: If already running or the port cannot be bound.
            DependencyError: If ``websockets`` is not installed.
        """
        try:
            import websockets  # noqa: F401
        except ImportError:
            raise DependencyError(
                "the webxr device needs 'websockets'; install it with: pip install 'telerig[devices]'"
            ) from None
        ssl_context = self._ssl_context()
        self._load_static()
        ready = threading.Event()
        failure: list[BaseException] = []
        self._worker.start(self._run, sink, ssl_context, ready, failure)
        ready.wait()
        if failure:
            self.stop()
            exc = failure[0]
            raise DeviceError(
                f"webxr device '{self._id}' cannot listen on {self.host}:{self._requested_port}: {exc}; "
                "set port to a free one (0 picks any)"
            ) from exc
        _log.info("%s: open %s in the headset or phone browser", self._id, self.url)

    def stop(self) -> None:
        """Close the server and every connection and join the thread. Idempotent."""
        self._worker.stop(wake=self._finish)

    def _finish(self) -> None:
        # After the stop event is set: _serve either sees it or has published its loop and future here.
        with self._lock:
            loop, future = self._loop, self._stop_future
        if loop is not None and future is not None:

            def finish() -> None:
                if not future.done():
                    future.set_result(None)

            with contextlib.suppress(RuntimeError):  # loop already closed
                loop.call_soon_threadsafe(finish)

    def _count(self, key: str, n: int = 1) -> None:
        with self._lock:
            self._stats[key] += n

    def _next_seq(self, source_id: str) -> int:
        seq = self._seqs[source_id]
        self._seqs[source_id] = seq + 1
        return seq

    def _ssl_context(self) -> ssl.SSLContext | None:
        if self.certfile is None or self.keyfile is None:
            return None
        context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
        try:
            context.load_cert_chain(self.certfile, self.keyfile)
        except (OSError, ssl.SSLError) as exc:
            raise DeviceError(
                f"cannot load TLS certificate {self.certfile} / key {self.keyfile}: {exc}; "
                "create a self-signed pair with openssl (see telerig.devices.webxr.config)"
            ) from exc
        return context

    def _load_static(self) -> None:
        root = importlib.resources.files("telerig.devices.webxr") / "static"
        self._static = {name: (root / name).read_bytes() for name, _ in STATIC_FILES.values()}

    def _run(
        self,
        sink: SampleSink,
        ssl_context: ssl.SSLContext | None,
        ready: threading.Event,
        failure: list[BaseException],
        stop: threading.Event,
    ) -> None:
        loop = asyncio.new_event_loop()
        try:
            loop.run_until_complete(self._serve(sink, ssl_context, ready, stop, loop))
        except BaseException as exc:  # reported to start() or logged; never kills the process
            if not ready.is_set():
                failure.append(exc)
            else:
                _log.exception("%s: server stopped on an error", self._id)
        finally:
            ready.set()
            loop.close()

    async def _serve(
        self,
        sink: SampleSink,
        ssl_context: ssl.SSLContext | None,
        ready: threading.Event,
        stop: threading.Event,
        loop: asyncio.AbstractEventLoop,
    ) -> None:
        from websockets.asyncio.server import ServerConnection, serve
        from websockets.datastructures import Headers
        from websockets.http11 import Request, Response

        def process_request(connection: ServerConnection, request: Request) -> Response | None:
            path = request.path.split("?", 1)[0]
            if path == WS_PATH:
                return None
            entry = STATIC_FILES.get(path)
            if entry is None:
                self._count("http_404")
                return connection.respond(http.HTTPStatus.NOT_FOUND, f"not found: {path}\n")
            name, content_type = entry
            body = self._static[name]
            headers = Headers(
                [
                    ("Content-Type", content_type),
                    ("Content-Length", str(len(body))),
                    ("Cache-Control", "no-store"),
                    ("Connection", "close"),
                ]
            )
            return Response(200, "OK", headers, body)

        async def handler(connection: ServerConnection) -> None:
            await self._handle(connection, sink)

        stop_future: asyncio.Future[None] = loop.create_future()
        with self._lock:
            self._loop, self._stop_future = loop, stop_future
        if stop.is_set():
            return
        async with serve(
            handler,
            self.host,
            self._requested_port,
            process_request=process_request,
            ssl=ssl_context,
            max_size=_MAX_MESSAGE,
            compression=None,
            logger=logging.getLogger(f"{__name__}.ws"),
        ) as server:
            self._port = int(next(iter(server.sockets)).getsockname()[1])
            ready.set()
            await stop_future

    async def _handle(self, connection: object, sink: SampleSink) -> None:
        from websockets.asyncio.server import ServerConnection
        from websockets.exceptions import ConnectionClosed

        assert isinstance(connection, ServerConnection)
        previous, self._active = self._active, connection
        if isinstance(previous, ServerConnection):
            self._count("replaced")
            await previous.close(4000, "replaced by a newer page")
        clock = ClockOffset()
        self._clock = clock
        self._count("connections")
        pending: dict[int, int] = {}
        _log.info("%s: page connected from %s", self._id, connection.remote_address)

        async def pinger() -> None:
            ping_id = 0
            try:
                while True:
                    pending[ping_id] = now_ns()
                    await connection.send(encode_ping(ping_id))
                    if len(pending) > _MAX_PENDING_PINGS:
                        del pending[min(pending)]
                    ping_id = (ping_id + 1) & 0xFFFFFFFF
                    await asyncio.sleep(self.ping_interval_s)
            except ConnectionClosed:
                return

        ping_task = asyncio.create_task(pinger())
        last_seq = -1
        warned: set[str] = set()
        try:
            async for message in connection:
                receive_ns = now_ns()
                if isinstance(message, str):
                    self._count("drop_text")
                    continue
                try:
                    msg = decode(message)
                except WebXRWireError as exc:
                    self._count(f"drop_{exc.reason}")
                    if exc.reason not in warned:
                        warned.add(exc.reason)
                        _log.warning("%s: dropping malformed page message: %s", self._id, exc)
                    continue
                if isinstance(msg, Pong):
                    sent = pending.pop(msg.ping_id, None)
                    if sent is None:
                        self._count("drop_unknown_ping")
                        continue
                    clock.observe_pong(sent, msg.client_ns, receive_ns)
                    self._count("pongs")
                    continue
                if msg.seq <= last_seq:
                    self._count("drop_stale_seq")
                    continue
                last_seq = msg.seq
                clock.observe_frame(msg.client_ns, receive_ns)
                capture_ns = clock.capture_ns(msg.client_ns, receive_ns)
                samples = frame_samples(msg, self._id, capture_ns, self._next_seq, frame_id=self.frame_id)
                self._count("frames")
                for sample in samples:
                    self._worker.deliver(sink, sample)
        except ConnectionClosed:
            pass
        finally:
            ping_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await ping_task
            if self._active is connection:
                self._active = None
            _log.info("%s: page disconnected", self._id)
