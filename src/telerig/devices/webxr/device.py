"""The WebXR device: serves the page and its WebSocket on one port, turns page frames into IR samples."""

from __future__ import annotations

import asyncio
import contextlib
import http
import importlib.resources
import logging
import ssl
import sys
import threading
from collections import Counter
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Literal, TextIO
from urllib.parse import parse_qs

from pydantic import JsonValue

from telerig.devices.base import AlertSink, DeviceAlert, SampleSink
from telerig.devices.webxr.pairing import (
    is_loopback,
    lan_url_host,
    new_token,
    self_signed_pair,
    terminal_qr,
    token_matches,
)
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
#: Where a generated certificate is cached when no ``tls_dir`` is given (the default data root's).
DEFAULT_TLS_DIR = Path("telerig-data") / "tls"
#: WebSocket close codes the page understands.
CLOSE_REPLACED = 4000
CLOSE_REFUSED = 4003

TakeoverPolicy = Literal["refuse", "confirm"]


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

    Who may connect: bound to a loopback address (the default, ``127.0.0.1``) only this host;
    bound to any other address (``0.0.0.0`` or a LAN address) a client must present the pairing
    token generated at :meth:`start` (printed with a QR code of :attr:`pairing_url`), and the
    server serves TLS, with ``certfile``/``keyfile`` or a self-signed pair generated once into
    ``tls_dir``. A browser's ``Origin`` must be this server's own (or one of ``allowed_origins``).

    One page drives the device at a time. While one is connected, another is refused
    (``takeover="refuse"``), or held until the operator answers (``takeover="confirm"``:
    :meth:`command` ``{"takeover": "confirm"}`` or ``"deny"``, within ``takeover_timeout_s``); a
    confirmed page replaces the old one, whose later frames are dropped. Every takeover, refused
    client and request is reported to the alert sink (:meth:`set_alert_sink`; logged without one).
    Bad messages never stop the device; they are dropped and counted in :attr:`stats`
    (``drop_<reason>``, ``refused_<reason>``).
    """

    def __init__(
        self,
        id: str = "xr0",
        *,
        host: str = "127.0.0.1",
        port: int = 8443,
        certfile: Path | str | None = None,
        keyfile: Path | str | None = None,
        frame_id: str = "operator",
        ping_interval_s: float = 0.5,
        tls_dir: Path | str | None = None,
        takeover: TakeoverPolicy = "refuse",
        takeover_timeout_s: float = 30.0,
        allowed_origins: Sequence[str] = (),
        pairing_output: TextIO | None = None,
        pairing: bool | None = None,
    ) -> None:
        """Args:
        id: Device id; source ids are ``"<id>/head"``, ``"<id>/left"``, ``"<id>/right_hand"``, ...
        host: Interface to listen on: ``"127.0.0.1"`` this host only; ``"0.0.0.0"`` or a LAN
            address for a headset on the network (pairing token and TLS then required).
        port: TCP port (0: a free one; read :attr:`port` after ``start``).
        certfile: PEM certificate for HTTPS/WSS; ``None`` serves plain HTTP on loopback and a
            generated self-signed certificate otherwise.
        keyfile: PEM private key matching ``certfile``.
        frame_id: Frame the samples are expressed in.
        ping_interval_s: Clock-sync ping period [s] (> 0).
        tls_dir: Where the generated certificate is cached (``<data root>/tls``); default
            ``telerig-data/tls``.
        takeover: What happens when a second page connects while one is active.
        takeover_timeout_s: How long a takeover waits for the operator's answer [s] (> 0).
        allowed_origins: Browser origins allowed besides the server's own, e.g.
            ``"https://xr.example.org"``.
        pairing_output: Where the pairing URL and QR code are printed (stderr by default).
        pairing: Require the pairing token and TLS; None: exactly when bound beyond loopback
            (False is refused there).
        """
        if (certfile is None) != (keyfile is None):
            raise DeviceError("certfile and keyfile must be given together (or neither, for plain HTTP)")
        if not 0.0 < ping_interval_s <= 60.0:
            raise DeviceError(f"ping_interval_s must be in (0, 60] s, got {ping_interval_s}")
        if takeover not in ("refuse", "confirm"):
            raise DeviceError(f"takeover must be 'refuse' or 'confirm', got {takeover!r}")
        if pairing is False and not is_loopback(host):
            raise DeviceError(
                f"webxr device bound to {host} must require pairing (anyone on the network could drive "
                "it); remove 'pairing: false' or bind host to 127.0.0.1"
            )
        if not takeover_timeout_s > 0.0:
            raise DeviceError(f"takeover_timeout_s must be > 0 s, got {takeover_timeout_s}")
        self._id = id
        self.host = host
        self._requested_port = port
        self._port = port
        self.certfile = None if certfile is None else Path(certfile)
        self.keyfile = None if keyfile is None else Path(keyfile)
        self.frame_id = frame_id
        self.ping_interval_s = float(ping_interval_s)
        self.tls_dir = DEFAULT_TLS_DIR if tls_dir is None else Path(tls_dir)
        self.takeover = takeover
        self.takeover_timeout_s = float(takeover_timeout_s)
        self.allowed_origins = tuple(allowed_origins)
        self._pairing_output = pairing_output
        self._pairing = not is_loopback(host) if pairing is None else pairing
        self._tls: tuple[Path, Path] | None = None
        if self.certfile is not None and self.keyfile is not None:
            self._tls = (self.certfile, self.keyfile)
        self._token: str | None = None
        self._alert_sink: AlertSink | None = None
        self._alerted: set[tuple[str, str]] = set()
        self._takeover_request: tuple[asyncio.Future[bool], str] | None = None
        # Admitted WebSocket connection -> the page it was confirmed to replace (None: none was active).
        self._approved: dict[object, object | None] = {}
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
    def token_required(self) -> bool:
        """Whether clients must present the pairing token (by default: bound beyond loopback)."""
        return self._pairing

    @property
    def url(self) -> str:
        """URL of the page, e.g. ``https://192.168.1.20:8443/`` (without the pairing token)."""
        scheme = "http" if self._tls is None else "https"
        host = lan_url_host(self.host)
        if ":" in host:
            host = f"[{host}]"
        return f"{scheme}://{host}:{self._port}/"

    @property
    def pairing_url(self) -> str:
        """URL to open in the headset: :attr:`url` with the pairing token while one is required."""
        token = self._token
        return self.url if token is None else f"{self.url}?token={token}"

    @property
    def pending_takeover(self) -> str | None:
        """Address of a page waiting for the operator to confirm its takeover, if any."""
        request = self._takeover_request
        return None if request is None else request[1]

    def set_alert_sink(self, sink: AlertSink) -> None:
        """Report alerts (takeovers, refused clients) to ``sink`` instead of the log."""
        self._alert_sink = sink

    def command(self, command: Mapping[str, JsonValue]) -> str:
        """Apply an operator command; returns one line saying what happened.

        ``{"takeover": "confirm"}`` lets the waiting page replace the active one,
        ``{"takeover": "deny"}`` refuses it.
        """
        answer = command.get("takeover")
        if answer not in ("confirm", "deny"):
            return f"{self._id}: unknown command {dict(command)!r}; send {{'takeover': 'confirm' | 'deny'}}"
        with self._lock:
            loop = self._loop
        request = self._takeover_request
        if request is None or loop is None:
            return f"{self._id}: no page is waiting to take over"
        future, remote = request

        def answer_request() -> None:
            if not future.done():
                future.set_result(answer == "confirm")

        with contextlib.suppress(RuntimeError):  # loop closed: the request is gone with it
            loop.call_soon_threadsafe(answer_request)
        return f"{self._id}: takeover by {remote} {'confirmed' if answer == 'confirm' else 'denied'}"

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
        self._token = new_token() if self.token_required else None
        if self.token_required and self._tls is None:
            self._tls = self_signed_pair(self.tls_dir, self.host)
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
        if self._token is not None:
            out = sys.stderr if self._pairing_output is None else self._pairing_output
            out.write(
                f"{self._id}: open this URL in the headset browser (pairing token for this run; accept "
                f"the self-signed certificate once):\n  {self.pairing_url}\n{terminal_qr(self.pairing_url)}"
            )
            out.flush()

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
        if self._tls is None:
            return None
        certfile, keyfile = self._tls
        context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
        try:
            context.load_cert_chain(certfile, keyfile)
        except (OSError, ssl.SSLError) as exc:
            raise DeviceError(
                f"cannot load TLS certificate {certfile} / key {keyfile}: {exc}; "
                "give a valid PEM pair or leave both unset for a generated one"
            ) from exc
        return context

    def _alert(
        self, code: str, reason: str, action: str, severity: Literal["info", "warning", "error"]
    ) -> None:
        alert = DeviceAlert(code, self._id, reason, action, severity, now_ns())
        sink = self._alert_sink
        if sink is None:
            _log.log(
                logging.INFO if severity == "info" else logging.WARNING, "%s: %s: %s", self._id, code, reason
            )
            return
        try:
            sink(alert)
        except Exception:
            _log.exception("%s: the alert sink failed on %s", self._id, code)

    def _refuse_once(self, code: str, reason: str, action: str, *, key: str = "") -> None:
        """Count a refused client; alert on the first of each kind (per ``key``, e.g. a client
        address): a page that retries every second would flood the alerts."""
        self._count(f"refused_{code}")
        if (code, key) not in self._alerted:
            self._alerted.add((code, key))
            self._alert(f"{code}_refused", reason, action, "warning")

    def _origins(self) -> set[str]:
        scheme = "http" if self._tls is None else "https"
        hosts = {self.host, "127.0.0.1", "localhost", "[::1]", lan_url_host(self.host)}
        return {f"{scheme}://{h}:{self._port}" for h in hosts} | set(self.allowed_origins)

    async def _admit(self, remote: str, origin: str | None, query: str) -> tuple[int, str] | None:
        """None to accept a WebSocket client, or the HTTP status and one line to refuse it with."""
        if origin is not None and origin not in self._origins():
            self._refuse_once(
                "origin",
                f"a page from origin {origin} tried to connect (from {remote})",
                "open the page this server serves; add the origin to allowed_origins if it is yours",
            )
            return http.HTTPStatus.FORBIDDEN, f"origin {origin} is not allowed\n"
        if self._token is not None:
            given = parse_qs(query).get("token", [None])[0]
            if not token_matches(given, self._token):
                self._refuse_once(
                    "token",
                    f"a client from {remote} connected without the pairing token",
                    "open the pairing URL printed by telerig (or scan its QR code)",
                )
                return http.HTTPStatus.UNAUTHORIZED, "pairing token missing or wrong\n"
        if self._active is None:
            return None
        if self.takeover == "refuse" or self._takeover_request is not None:
            self._refuse_once(
                "takeover",
                f"a second page from {remote} was refused while another drives {self._id}",
                "close the other page first (takeover: confirm lets the operator hand over)",
                key=remote.rsplit(":", 1)[0],
            )
            return http.HTTPStatus.CONFLICT, "another page is active\n"
        return None if await self._ask_takeover(remote) else (http.HTTPStatus.CONFLICT, "takeover refused\n")

    async def _ask_takeover(self, remote: str) -> bool:
        future: asyncio.Future[bool] = asyncio.get_running_loop().create_future()
        self._takeover_request = (future, remote)
        self._alert(
            "takeover_requested",
            f"a page from {remote} asks to take over {self._id}",
            f"confirm within {self.takeover_timeout_s:g} s if it is the operator's, or deny it",
            "warning",
        )
        try:
            approved = await asyncio.wait_for(future, self.takeover_timeout_s)
        except TimeoutError:
            approved = False
        finally:
            self._takeover_request = None
        if not approved:
            self._count("refused_takeover")
            self._alert(
                "takeover_refused",
                f"the takeover by {remote} was not confirmed",
                "the active page keeps driving",
                "warning",
            )
        return approved

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

        async def process_request(connection: ServerConnection, request: Request) -> Response | None:
            path, _, query = request.path.partition("?")
            if path == WS_PATH:
                refusal = await self._admit(
                    _address(connection.remote_address), request.headers.get("Origin"), query
                )
                if refusal is None:
                    self._approved[connection] = self._active
                    return None
                status, text = refusal
                return connection.respond(status, text)
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
        admitted = connection in self._approved
        replacing = self._approved.pop(connection, None)
        previous = self._active
        remote = _address(connection.remote_address)
        if not admitted or (previous is not None and previous is not replacing):
            # Admitted while no page was active (or to replace another one), but a page got in first.
            self._refuse_once(
                "takeover",
                f"a second page from {remote} was refused while another drives {self._id}",
                "close the other page first",
                key=remote.rsplit(":", 1)[0],
            )
            await connection.close(CLOSE_REFUSED, "another page is active")
            return
        self._active = connection
        if isinstance(previous, ServerConnection):
            self._count("replaced")
            self._alert(
                "takeover",
                f"the page from {remote} took over {self._id} from {_address(previous.remote_address)}",
                "the operator confirmed it; samples now come from the new page only",
                "warning",
            )
            await previous.close(CLOSE_REPLACED, "replaced by a newer page")
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
                if self._active is not connection:
                    self._count("drop_inactive_page")
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


def _address(remote: object) -> str:
    """``host:port`` of a peer address tuple."""
    if isinstance(remote, tuple) and len(remote) >= 2:
        return f"{remote[0]}:{remote[1]}"
    return str(remote)
