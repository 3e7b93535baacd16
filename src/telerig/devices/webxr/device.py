"""The WebXR device: the frames of the operator's page, relayed by ``telerig serve``, into IR samples."""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import queue
import threading
import time
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Literal

from pydantic import JsonValue

from telerig.devices.base import AlertSink, DeviceAlert, PageSink, SampleSink
from telerig.devices.webxr.protocol import (
    ClockOffset,
    Pong,
    WebXRWireError,
    decode,
    encode_ping,
    frame_samples,
)
from telerig.devices.webxr.relay import (
    CLOSE,
    MESSAGE,
    OPEN,
    STAMPED,
    close_body,
    decode_event,
    encode_event,
    parse_open,
    parse_stamped,
)
from telerig.devices.worker import DeviceWorker
from telerig.errors import DeviceError
from telerig.ir.types import now_ns

__all__ = ["CLOSE_REFUSED", "CLOSE_REPLACED", "CLOSE_UNKNOWN", "WebXRDevice"]

_log = logging.getLogger(__name__)

#: WebSocket close codes the page understands.
CLOSE_REPLACED = 4000
CLOSE_REFUSED = 4003
#: The device does not know the connection (it restarted): the page connects again.
CLOSE_UNKNOWN = 4004
# Pings whose pong never came are forgotten after this many newer ones.
_MAX_PENDING_PINGS = 64
# Relayed messages waiting for the device thread; beyond, new ones are dropped (drop_overflow).
_QUEUE = 256
# Connections known at once (the driving page, one waiting takeover, pages being refused).
_MAX_CONNECTIONS = 16
#: A relaying server's receive stamp further than this from the device's receipt [ns] is not used:
#: its clock is not the rig's (the relay itself takes milliseconds).
_MAX_RELAY_NS = 1_000_000_000
# A connection that sent nothing for this long is gone (the server died without its close) [s]:
# a page sends a frame per XR frame or desktop tick (60 Hz) and a pong per ping.
IDLE_S = 3.0

TakeoverPolicy = Literal["refuse", "confirm"]


@dataclass(slots=True)
class _Page:
    """One relayed page connection as the device sees it."""

    user: str
    client: str
    last_seen: float  # time.monotonic() [s]
    clock: ClockOffset = field(default_factory=ClockOffset)
    pending: dict[int, int] = field(default_factory=dict)  # ping id -> sent [ns]
    next_ping_id: int = 0
    last_seq: int = -1

    @property
    def who(self) -> str:
        return f"{self.user} ({self.client})"


class WebXRDevice:
    """Turns what the telerig WebXR page streams into IR samples.

    The page is served by ``telerig serve`` at ``/xr`` behind its login and TLS: only an operator
    (or admin) may stream, from the server's own origin. The server checks each message against
    the wire format (:mod:`~telerig.devices.webxr.protocol`; malformed ones are counted and
    dropped there) and relays it on the device's ``page_in`` topic (:mod:`~telerig.devices.webxr.relay`
    envelope); the device node hands it to :meth:`page_message`. The device decodes it again (the
    bus is an input too), and its pings and closes go back through :meth:`set_page_sink`.

    Per frame the page sends, the sink receives (see :func:`~telerig.devices.webxr.protocol.frame_samples`)
    a head :class:`~telerig.ir.types.Pose`, one :class:`~telerig.ir.types.ControllerState` per
    controller and one :class:`~telerig.ir.types.HandPose` per tracked hand, in ``frame_id``
    (x forward, y left, z up, metres). ``device_ns`` is the page clock; ``capture_ns`` maps it to
    the common clock with an offset from a ping/pong exchange every ``ping_interval_s``
    (:class:`~telerig.devices.webxr.protocol.ClockOffset`; the relay's hops are inside the round
    trip, so they bound the error).

    One page drives the device at a time. While one is connected, another is refused
    (``takeover="refuse"``), or held until the operator answers (``takeover="confirm"``:
    :meth:`command` ``{"takeover": "confirm"}`` or ``"deny"``, within ``takeover_timeout_s``); a
    confirmed page replaces the old one, which is closed. A page silent for :data:`IDLE_S` is gone.
    Every takeover, refused page and request is reported to the alert sink (:meth:`set_alert_sink`;
    logged without one). Bad messages never stop the device; they are dropped and counted in
    :attr:`stats` (``drop_<reason>``, ``refused_<reason>``).
    """

    def __init__(
        self,
        id: str = "xr0",
        *,
        frame_id: str = "operator",
        ping_interval_s: float = 0.5,
        takeover: TakeoverPolicy = "refuse",
        takeover_timeout_s: float = 30.0,
    ) -> None:
        """Args:
        id: Device id; source ids are ``"<id>/head"``, ``"<id>/left"``, ``"<id>/right_hand"``, ...
        frame_id: Frame the samples are expressed in.
        ping_interval_s: Clock-sync ping period [s] (> 0).
        takeover: What happens when a second page connects while one is active.
        takeover_timeout_s: How long a takeover waits for the operator's answer [s] (> 0).
        """
        if not 0.0 < ping_interval_s <= 60.0:
            raise DeviceError(f"ping_interval_s must be in (0, 60] s, got {ping_interval_s}")
        if takeover not in ("refuse", "confirm"):
            raise DeviceError(f"takeover must be 'refuse' or 'confirm', got {takeover!r}")
        if not takeover_timeout_s > 0.0:
            raise DeviceError(f"takeover_timeout_s must be > 0 s, got {takeover_timeout_s}")
        self._id = id
        self.frame_id = frame_id
        self.ping_interval_s = float(ping_interval_s)
        self.takeover = takeover
        self.takeover_timeout_s = float(takeover_timeout_s)
        self._alert_sink: AlertSink | None = None
        self._page_sink: PageSink | None = None
        self._alerted: set[tuple[str, str]] = set()
        self._stats: Counter[str] = Counter()
        self._seqs: Counter[str] = Counter()
        self._lock = threading.Lock()  # guards _stats
        self._inbox: queue.Queue[bytes | tuple[str, bool] | None] = queue.Queue(_QUEUE)
        self._worker = DeviceWorker(id, kind="webxr device", thread_name=f"telerig-webxr-{id}", log=_log)
        # Owned by the device thread:
        self._pages: dict[int, _Page] = {}
        self._active: int | None = None
        self._request: tuple[int, float] | None = None  # waiting takeover: (conn, deadline monotonic)
        self._told_unknown: set[int] = set()

    @property
    def id(self) -> str:
        """Device id."""
        return self._id

    @property
    def running(self) -> bool:
        """Whether the device thread is running."""
        return self._worker.running

    @property
    def stats(self) -> Mapping[str, int]:
        """Counters (a copy): ``connections``, ``frames``, ``pongs``, ``replaced``, ``expired``,
        ``samples``, ``sink_error``, ``drop_<reason>`` and ``refused_<reason>``."""
        with self._lock:
            stats = dict(self._stats)
        return {**stats, "samples": self._worker.samples, "sink_error": self._worker.sink_errors}

    @property
    def clock_offset_ns(self) -> int | None:
        """Current estimate of common clock - page clock [ns] for the active page, if any."""
        page = self._pages.get(self._active) if self._active is not None else None
        return None if page is None else page.clock.offset_ns

    @property
    def active_user(self) -> str | None:
        """Who drives the device now (``user (client)``), if a page does."""
        page = self._pages.get(self._active) if self._active is not None else None
        return None if page is None else page.who

    @property
    def pending_takeover(self) -> str | None:
        """Who waits for the operator to confirm a takeover, if anyone."""
        request = self._request
        page = None if request is None else self._pages.get(request[0])
        return None if page is None else page.who

    def set_alert_sink(self, sink: AlertSink) -> None:
        """Report alerts (takeovers, refused pages) to ``sink`` instead of the log."""
        self._alert_sink = sink

    def set_page_sink(self, sink: PageSink) -> None:
        """Where the device's answers to its pages go (relay envelopes for ``page_out``)."""
        self._page_sink = sink

    def page_message(self, payload: bytes) -> None:
        """A relay envelope from ``page_in``; queued for the device thread (never blocks)."""
        if not self._worker.running:
            self._count("drop_stopped")
            return
        try:
            self._inbox.put_nowait(bytes(payload))
        except queue.Full:
            self._count("drop_overflow")

    def command(self, command: Mapping[str, JsonValue]) -> str:
        """Apply an operator command; returns one line saying what happened.

        ``{"takeover": "confirm"}`` lets the waiting page replace the active one,
        ``{"takeover": "deny"}`` refuses it.
        """
        answer = command.get("takeover")
        if answer not in ("confirm", "deny"):
            return f"{self._id}: unknown command {dict(command)!r}; send {{'takeover': 'confirm' | 'deny'}}"
        who = self.pending_takeover
        if who is None or not self._worker.running:
            return f"{self._id}: no page is waiting to take over"
        with contextlib.suppress(queue.Full):
            self._inbox.put_nowait(("takeover", answer == "confirm"))
        return f"{self._id}: takeover by {who} {'confirmed' if answer == 'confirm' else 'denied'}"

    def start(self, sink: SampleSink) -> None:
        """Start the device thread (it waits for relayed pages).

        Raises:
            DeviceError: If already running.
        """
        while not self._inbox.empty():
            self._inbox.get_nowait()
        self._pages.clear()
        self._active = self._request = None
        self._worker.start(self._run, sink)

    def stop(self) -> None:
        """Close every page and join the thread. Idempotent."""
        self._worker.stop(wake=self._wake)

    def _wake(self) -> None:
        with contextlib.suppress(queue.Full):
            self._inbox.put_nowait(None)

    def _count(self, key: str, n: int = 1) -> None:
        with self._lock:
            self._stats[key] += n

    def _next_seq(self, source_id: str) -> int:
        seq = self._seqs[source_id]
        self._seqs[source_id] = seq + 1
        return seq

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
        """Count a refused page; alert on the first of each kind (per ``key``, e.g. a user): a page
        that retries every few seconds would flood the alerts."""
        self._count(f"refused_{code}")
        if (code, key) not in self._alerted:
            self._alerted.add((code, key))
            self._alert(f"{code}_refused", reason, action, "warning")

    def _send(self, event: int, conn: int, body: bytes) -> None:
        sink = self._page_sink
        if sink is None:
            self._count("drop_no_page_sink")
            return
        try:
            sink(encode_event(event, conn, body))
        except Exception:
            self._count("page_sink_error")
            _log.exception("%s: sending to the page failed", self._id)

    def _close(self, conn: int, code: int, reason: str) -> None:
        self._send(CLOSE, conn, close_body(code, reason))
        self._forget(conn)
        self._closed_once(conn)  # its messages still in flight are dropped without another close

    def _closed_once(self, conn: int) -> bool:
        """Whether ``conn`` was closed already; remembers it (bounded)."""
        if conn in self._told_unknown:
            return True
        if len(self._told_unknown) > 1024:
            self._told_unknown.clear()
        self._told_unknown.add(conn)
        return False

    def _forget(self, conn: int) -> None:
        self._pages.pop(conn, None)
        if self._active == conn:
            self._active = None
        if self._request is not None and self._request[0] == conn:
            self._request = None

    # --- the device thread ------------------------------------------------------------------------

    def _run(self, sink: SampleSink, stop: threading.Event) -> None:
        next_ping = time.monotonic()
        while not stop.is_set():
            now = time.monotonic()
            if now >= next_ping:
                next_ping = now + self.ping_interval_s
                self._tick(now)
            try:
                item = self._inbox.get(timeout=max(0.0, next_ping - time.monotonic()))
            except queue.Empty:
                continue
            if item is None:
                continue
            try:
                if isinstance(item, tuple):
                    self._answer_takeover(item[1])
                else:
                    self._on_event(item, sink)
            except Exception:  # a bug must not end the device: count, log once per kind
                self._count("drop_internal")
                _log.exception("%s: handling a page message failed", self._id)
        for conn in list(self._pages):
            self._close(conn, 1001, "the device stopped")

    def _tick(self, now: float) -> None:
        """Ping every page; forget silent ones; refuse a takeover nobody answered in time."""
        for conn, page in list(self._pages.items()):
            if now - page.last_seen > IDLE_S:
                self._count("expired")
                _log.info("%s: page of %s went silent; forgetting it", self._id, page.who)
                self._forget(conn)
                continue
            page.pending[page.next_ping_id] = now_ns()
            self._send(MESSAGE, conn, encode_ping(page.next_ping_id))
            if len(page.pending) > _MAX_PENDING_PINGS:
                del page.pending[min(page.pending)]
            page.next_ping_id = (page.next_ping_id + 1) & 0xFFFFFFFF
        if self._request is not None and now >= self._request[1]:
            self._answer_takeover(False)

    def _on_event(self, payload: bytes, sink: SampleSink) -> None:
        receive_ns = now_ns()
        try:
            event = decode_event(payload)
        except WebXRWireError as exc:
            self._count(f"drop_{exc.reason}")
            return
        conn = event.conn
        if event.event == CLOSE:
            if conn in self._pages:
                _log.info("%s: page of %s disconnected", self._id, self._pages[conn].who)
            self._forget(conn)
            return
        if event.event == OPEN:
            try:
                user, client = parse_open(event.body)
            except WebXRWireError as exc:
                self._count(f"drop_{exc.reason}")
                return
            self._admit(conn, _Page(user, client, time.monotonic()))
            return
        page = self._pages.get(conn)
        if page is None:
            self._count("drop_unknown_page")
            if not self._closed_once(conn):  # once: the page reconnects (and opens) on this close
                self._send(CLOSE, conn, close_body(CLOSE_UNKNOWN, "the device does not know this page"))
            return
        page.last_seen = time.monotonic()
        try:
            server_ns, body = parse_stamped(event.body) if event.event == STAMPED else (0, event.body)
            msg = decode(body)
        except WebXRWireError as exc:
            self._count(f"drop_{exc.reason}")
            return
        if isinstance(msg, Pong):
            sent = page.pending.pop(msg.ping_id, None)
            if sent is None:
                self._count("drop_unknown_ping")
                return
            page.clock.observe_pong(sent, msg.client_ns, receive_ns)
            self._count("pongs")
            return
        if self._active != conn:
            self._count("drop_inactive_page")
            return
        if msg.seq <= page.last_seq:
            self._count("drop_stale_seq")
            return
        page.last_seq = msg.seq
        page.clock.observe_frame(msg.client_ns, receive_ns)
        capture_ns = page.clock.capture_ns(msg.client_ns, receive_ns)
        samples = frame_samples(msg, self._id, capture_ns, self._next_seq, frame_id=self.frame_id)
        if receive_ns - _MAX_RELAY_NS <= server_ns <= receive_ns + _MAX_RELAY_NS:
            # The frame reached telerig at the server that relayed it (its ``receive`` stage ends
            # there); a stamp from a server whose clock is far off is not used (arrival stays 0
            # and the device node stamps its own).
            samples = [
                dataclasses.replace(s, stamp=dataclasses.replace(s.stamp, arrival_ns=server_ns))
                for s in samples
            ]
        self._count("frames")
        for sample in samples:
            self._worker.deliver(sink, sample)

    def _admit(self, conn: int, page: _Page) -> None:
        if conn in self._pages:
            self._count("drop_duplicate_open")
            return
        if len(self._pages) >= _MAX_CONNECTIONS:
            self._refuse_once("crowd", f"too many pages connect to {self._id}", "close the other pages")
            self._close(conn, CLOSE_REFUSED, "too many pages")
            return
        active = None if self._active is None else self._pages.get(self._active)
        if active is None:
            self._pages[conn] = page
            self._active = conn
            self._count("connections")
            _log.info("%s: page of %s drives the device", self._id, page.who)
            return
        if self.takeover == "refuse" or self._request is not None:
            self._refuse_once(
                "takeover",
                f"a second page of {page.who} was refused while {active.who} drives {self._id}",
                "close the other page first (takeover: confirm lets the operator hand over)",
                key=page.user,
            )
            self._close(conn, CLOSE_REFUSED, "another page is active")
            return
        self._pages[conn] = page
        self._request = (conn, time.monotonic() + self.takeover_timeout_s)
        self._alert(
            "takeover_requested",
            f"the page of {page.who} asks to take over {self._id} from {active.who}",
            f"confirm within {self.takeover_timeout_s:g} s if it is the operator's, or deny it",
            "warning",
        )

    def _answer_takeover(self, approved: bool) -> None:
        request, self._request = self._request, None
        if request is None:
            return
        conn = request[0]
        page = self._pages.get(conn)
        if page is None:
            return
        if not approved:
            self._count("refused_takeover")
            self._alert(
                "takeover_refused",
                f"the takeover by {page.who} was not confirmed",
                "the active page keeps driving",
                "warning",
            )
            self._close(conn, CLOSE_REFUSED, "takeover refused")
            return
        previous = self._active
        old = None if previous is None else self._pages.get(previous)
        self._active = conn
        self._count("connections")
        if previous is not None and old is not None:
            self._count("replaced")
            self._alert(
                "takeover",
                f"the page of {page.who} took over {self._id} from {old.who}",
                "the operator confirmed it; samples now come from the new page only",
                "warning",
            )
            self._close(previous, CLOSE_REPLACED, "replaced by a newer page")
