"""The latency stages only the operator's browser sees, measured by the control center from its pages.

The control node measures the robot's stages up to the measured state (``<robot>/latency``,
:mod:`telerig.runtime.control_health`); what happens after is the page's: it draws a joint state,
or a camera's preview, and reports which one it drew and when (``/api/latency``,
:mod:`telerig.server.routes_latency`). This module turns those reports into two more figures, in
the same rolling windows (:class:`~telerig.runtime.metrics.LatencyWindow`), judged against the
rig's budgets (``latency.budgets_ms``) and published by the ``web`` principal at
:data:`PERIOD_S` on each node's retained, recorded ``latency_view`` stream:

* per robot, ``rendered``: the joint state's stamp (the driver's measurement time) → the frame the
  page drew with it, in the server's clock (the page's clock is mapped through the NTP-style
  exchange of its connection, see :class:`ClockMap`);
* per camera, ``video_encode`` → ``video_deliver`` → ``video_display``: a preview frame's capture
  → its JPEG encoded (both stamped by the camera node into the JPEG's comment segment,
  :func:`telerig.cameras.preview.stamp_jpeg`) → received by this server → drawn by the page.

The server's clock is taken as the rig's common clock: ``telerig serve`` runs on a station's host
(a control center on another host adds its clock offset to these stages).
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from typing import Protocol

from telerig.config.latency import VIDEO_STAGES, StageName
from telerig.config.schema import RigConfig
from telerig.runtime.metrics import LatencyWindow, WindowSummary

__all__ = ["MAX_AGE_NS", "PERIOD_S", "VIEW_TYPE", "ClockMap", "Link", "ViewLatency", "finite_ms"]

log = logging.getLogger("telerig.server")

#: Report period [s] of every ``latency_view`` stream (2 Hz, as the control nodes').
PERIOD_S = 0.5
#: The ``type`` of a ``latency_view`` document.
VIEW_TYPE = "latency_view"
#: A reported stamp older than this [ns] is dropped (``stale``): no draw takes 10 s, a replayed or
#: forged report does.
MAX_AGE_NS = 10_000_000_000
#: A drawn time this far [ns] after the server's now is dropped (``future``): the clock map's error
#: is half a round trip, far below it.
_MAX_AHEAD_NS = 1_000_000_000
#: Clock exchanges a connection keeps; the one with the shortest round trip maps the page's clock.
_EXCHANGES = 8


class Link(Protocol):
    """What :class:`ViewLatency` needs of the rig's gateway (:class:`telerig.server.gateway.RigGateway`)."""

    @property
    def rig(self) -> RigConfig: ...

    @property
    def connected(self) -> bool: ...

    def preview_stamps(self, camera: str, capture_ns: int) -> tuple[int, int, int] | None: ...

    def send_latency_view(self, node: str, payload: bytes) -> None: ...


class ClockMap:
    """The page's clock → the server's, from NTP-style exchanges on one connection.

    The server sends its time ``t1`` [ns]; the page answers with its own time ``p`` [ms,
    ``performance.timeOrigin + performance.now()``]; the server reads its time ``t2`` on receipt.
    Assuming a symmetric path, the page read ``p`` at ``(t1 + t2) / 2``, so ``offset = p - (t1 + t2)
    / 2`` with an error of at most half the round trip; of the last :data:`_EXCHANGES`, the one with
    the shortest round trip is used.
    """

    def __init__(self) -> None:
        self._exchanges: deque[tuple[int, float]] = deque(maxlen=_EXCHANGES)  # (rtt ns, offset ns)

    def add(self, t1_ns: int, page_ms: float, t2_ns: int) -> None:
        """One exchange: sent at ``t1_ns``, answered with ``page_ms``, received at ``t2_ns``."""
        self._exchanges.append((t2_ns - t1_ns, page_ms * 1e6 - (t1_ns + t2_ns) / 2))

    @property
    def synced(self) -> bool:
        return bool(self._exchanges)

    @property
    def rtt_ms(self) -> float | None:
        """Round trip of the exchange in use [ms]; ``None`` before the first."""
        return min(self._exchanges)[0] / 1e6 if self._exchanges else None

    def to_server_ns(self, page_ms: float) -> int:
        """A page time [ms] in the server's clock [ns].

        Raises:
            ValueError: No exchange yet.
        """
        if not self._exchanges:
            raise ValueError("no clock exchange with the page yet")
        return round(page_ms * 1e6 - min(self._exchanges)[1])


class ViewLatency:
    """The browser stages of one watched rig (see the module docs).

    Thread-safe: :meth:`rendered` and :meth:`displayed` are called from the pages' WebSocket
    handlers, :meth:`snapshot` from requests, the publisher from its own thread.

    Args:
        gateway: The rig's gateway: its cameras' preview stamps, and the bus it publishes on.
        window_s: Rolling window of the percentiles [s].
        clock: The server's clock [ns] (the common clock, see the module docs).
    """

    def __init__(
        self, gateway: Link, *, window_s: float = 2.0, clock: Callable[[], int] = time.time_ns
    ) -> None:
        self.gateway = gateway
        rig = gateway.rig
        self.budgets_ms = rig.latency.budgets()
        self._clock = clock
        self.robots = {r.id: LatencyWindow(window_s, 1024) for r in rig.robots}
        self.cameras = {c.id: LatencyWindow(window_s, 256, stages=VIDEO_STAGES) for c in rig.cameras}
        #: Reports taken (``rendered``, ``displayed``, ``sync``) and dropped (``drop_<reason>``).
        self.counters: Counter[str] = Counter()
        self._lock = threading.Lock()
        self._last: dict[str, int] = {}  # node -> the last stamp reported drawn (a page reports once)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._sent_empty: set[str] = set()
        #: Reports published.
        self.published = 0

    def count(self, key: str) -> None:
        with self._lock:
            self.counters[key] += 1

    def counts(self) -> dict[str, int]:
        """A copy of :attr:`counters`."""
        with self._lock:
            return dict(self.counters)

    def now_ns(self) -> int:
        return self._clock()

    # --- reports ---------------------------------------------------------------------------------

    def _plausible(self, stamp_ns: int, drawn_ns: int) -> str | None:
        now = self._clock()
        if drawn_ns > now + _MAX_AHEAD_NS:
            return "future"
        if stamp_ns < now - MAX_AGE_NS or drawn_ns < now - MAX_AGE_NS:
            return "stale"
        if drawn_ns < stamp_ns:
            return "order"  # drawn before the state was measured: a wrong stamp or clock map
        return None

    def rendered(self, robot: str, state_ns: int, drawn_ns: int) -> str | None:
        """A page drew robot ``robot``'s joint state stamped ``state_ns`` at ``drawn_ns`` [ns, server
        clock]. Returns the drop reason, or ``None`` when it was taken (counted either way)."""
        window = self.robots.get(robot)
        reason = "node" if window is None else self._plausible(state_ns, drawn_ns)
        if reason is None and self._last.get(robot) == state_ns:
            reason = "repeat"
        if reason is not None or window is None:
            self.count(f"drop_{reason}")
            return reason
        self._last[robot] = state_ns
        window.add(drawn_ns - state_ns, drawn_ns)
        self.count("rendered")
        return None

    def displayed(self, camera: str, capture_ns: int, drawn_ns: int) -> str | None:
        """A page drew camera ``camera``'s preview of the frame captured at ``capture_ns`` at
        ``drawn_ns`` [ns, server clock]. The preview must be one this server received (its encode
        and delivery stamps are looked up); returns the drop reason or ``None``."""
        window = self.cameras.get(camera)
        reason = "node" if window is None else self._plausible(capture_ns, drawn_ns)
        stamps = None
        if reason is None:
            stamps = self.gateway.preview_stamps(camera, capture_ns)
            if stamps is None:
                reason = "unknown_frame"
            elif self._last.get(camera) == stamps[0]:
                reason = "repeat"
            elif drawn_ns < stamps[2]:
                reason = "order"
        if reason is not None or window is None or stamps is None:
            self.count(f"drop_{reason}")
            return reason
        capture, encoded, delivered = stamps
        self._last[camera] = capture
        window.add_stamps(drawn_ns, capture, encoded, delivered, drawn_ns)
        self.count("displayed")
        return None

    # --- reporting -------------------------------------------------------------------------------

    def _judged(self, stage: StageName, w: WindowSummary) -> dict[str, object]:
        budget = self.budgets_ms[stage]
        return {**w.to_json(), "budget_ms": budget, "over": w.count > 0 and w.p99_ms > budget}

    def report(self, node: str, now: int | None = None) -> dict[str, object] | None:
        """The ``latency_view`` document of a robot or camera; ``None`` for another node."""
        t = self._clock() if now is None else now
        window: LatencyWindow | None = self.robots.get(node)
        if window is not None:
            stages = {"rendered": self._judged("rendered", window.summary(t))}
            out_of_order = 0
        elif (window := self.cameras.get(node)) is not None:
            summary = window.stage_summary(t)
            stages = {s: self._judged(s, summary.stages[s]) for s in VIDEO_STAGES}
            out_of_order = summary.out_of_order
        else:
            return None
        return {
            "type": VIEW_TYPE,
            "node": node,
            "time_ns": t,
            "window_s": window.window_ns / 1e9,
            "stages": stages,
            "out_of_order": out_of_order,
        }

    def publish(self) -> None:
        """Publish every node's report that has figures (and one empty report after the last)."""
        t = self._clock()
        for node in (*self.robots, *self.cameras):
            doc = self.report(node, t)
            if doc is None:
                continue
            stages = doc["stages"]
            empty = isinstance(stages, dict) and all(
                isinstance(s, dict) and s.get("count") == 0 for s in stages.values()
            )
            if empty and node in self._sent_empty:
                continue
            self.gateway.send_latency_view(node, json.dumps(doc, separators=(",", ":")).encode())
            self.published += 1
            if empty:
                self._sent_empty.add(node)
            else:
                self._sent_empty.discard(node)

    def start(self) -> ViewLatency:
        """Start publishing every :data:`PERIOD_S`; idempotent. Returns ``self``."""
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._loop, name="view-latency", daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        """Stop publishing; idempotent."""
        thread, self._thread = self._thread, None
        if thread is not None:
            self._stop.set()
            thread.join(timeout=5.0)

    def _loop(self) -> None:
        while not self._stop.wait(PERIOD_S):
            if not self.gateway.connected:
                continue
            try:
                self.publish()
            except Exception as exc:  # a lost link: the next period tries again
                log.debug("latency_view not published: %s", exc)


def finite_ms(value: object) -> float | None:
    """A page time [ms] as a float, or ``None`` unless it is a finite JSON number in a sane range."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    v = float(value)
    return v if math.isfinite(v) and 0 < v < 1e14 else None
