"""Stream health monitor: rates, gaps, drops and overflow per stream, live on the bus, alerts on stalls."""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import threading
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Literal

from pydantic import JsonValue

from telerig import priority
from telerig.bus.base import Bus, Message
from telerig.bus.catalogue import ALERTS, HEALTH, PayloadKind, spec_by_name
from telerig.bus.topics import Topic, qos_for
from telerig.errors import ConfigError, WireError
from telerig.ir import wire
from telerig.ir.types import now_ns

__all__ = [
    "ALERTS",
    "HEALTH",
    "AlertCode",
    "Severity",
    "StreamAlert",
    "StreamHealth",
    "StreamHealthMonitor",
]

log = logging.getLogger(__name__)

#: ``stream_stalled``: a stream that was flowing went silent; ``stream_missing``: an expected
#: stream never sent anything after the start-up grace; ``queue_overflow``: a watched bounded
#: queue dropped messages in the last window.
AlertCode = Literal["stream_stalled", "stream_missing", "queue_overflow"]
Severity = Literal["info", "warning", "error"]

_MAX_ALERT_HISTORY = 200
#: An interval longer than this many expected periods is a gap (``HealthMonitor``'s default ``gap_factor``).
GAP_FACTOR = 2.0
_OVERFLOW_STREAM = "queues"


@dataclass(frozen=True, slots=True)
class StreamAlert:
    """An alert raised (``active``) or cleared by the monitor, published as JSON on ``.../alerts``.

    Attributes:
        code: What happened (see :data:`AlertCode`).
        stream: Topic of the stream concerned (``queues`` for overflow alerts).
        reason: One line for a human, with numbers.
        suggested_action: One line saying what the operator or integrator should do.
        since_ns: When the condition began, common clock [ns] (a stall: the last message received).
        severity: ``info``, ``warning`` or ``error``.
        active: True when raised, False in the message that clears it.
        cleared_ns: When it cleared [ns]; ``None`` while active.
    """

    code: AlertCode
    stream: str
    reason: str
    suggested_action: str
    since_ns: int
    severity: Severity
    active: bool = True
    cleared_ns: int | None = None

    def to_json(self) -> dict[str, JsonValue]:
        """The alert as JSON data (every attribute, by name)."""
        return {
            "code": self.code,
            "stream": self.stream,
            "reason": self.reason,
            "suggested_action": self.suggested_action,
            "since_ns": self.since_ns,
            "severity": self.severity,
            "active": self.active,
            "cleared_ns": self.cleared_ns,
        }


@dataclass(frozen=True, slots=True)
class StreamHealth:
    """Health of one stream over the sliding window, as published about once a second.

    Attributes:
        topic: The stream's topic.
        state: ``ok``; ``waiting`` (nothing received yet); ``stalled``; ``degraded`` (rate below
            80 % of expected, or drops/gaps in the window).
        expected_hz: Configured rate [Hz]; 0 when unknown.
        measured_hz: Messages received in the window / window length [Hz].
        messages: Messages received in the window.
        max_gap_ms: Largest capture-time interval between consecutive messages in the window [ms].
        gaps: Intervals in the window longer than ``gap_factor`` expected periods (0 when the rate
            is unknown).
        drops: Messages missing from the sequence numbers in the window.
        silent_ms: Time since the last message was received [ms]; ``None`` before the first.
        latency_ms: Mean time from capture to this node's receipt of the window's messages [ms]
            (``received_ns - capture_ns``, both in the common clock); ``None`` when none.
        max_latency_ms: Largest of them [ms]; ``None`` when none.
    """

    topic: str
    state: str
    expected_hz: float
    measured_hz: float
    messages: int
    max_gap_ms: float
    gaps: int
    drops: int
    silent_ms: float | None
    latency_ms: float | None = None
    max_latency_ms: float | None = None

    def to_json(self) -> dict[str, JsonValue]:
        """JSON data of the window (the topic is the key it is stored under)."""
        return {
            "state": self.state,
            "expected_hz": self.expected_hz,
            "measured_hz": round(self.measured_hz, 3),
            "messages": self.messages,
            "max_gap_ms": round(self.max_gap_ms, 3),
            "gaps": self.gaps,
            "drops": self.drops,
            "silent_ms": None if self.silent_ms is None else round(self.silent_ms, 1),
            "latency_ms": None if self.latency_ms is None else round(self.latency_ms, 3),
            "max_latency_ms": None if self.max_latency_ms is None else round(self.max_latency_ms, 3),
        }


class _Stream:
    """Per-stream counters: a window of (received_ns, capture interval ns, drops) and episode totals."""

    __slots__ = (
        "alert",
        "drops",
        "expected_hz",
        "first_capture_ns",
        "gaps",
        "last_capture_ns",
        "last_received_ns",
        "last_seq",
        "max_gap_ns",
        "messages",
        "stall_ns",
        "stalls",
        "window",
    )

    def __init__(self, expected_hz: float) -> None:
        self.expected_hz = expected_hz
        self.window: deque[tuple[int, int, int, int]] = deque()  # received, interval, drops, latency
        self.messages = 0
        self.drops = 0
        self.gaps = 0
        self.max_gap_ns = 0
        self.stalls = 0
        self.stall_ns = 0
        self.first_capture_ns = 0
        self.last_capture_ns = 0
        self.last_received_ns: int | None = None
        self.last_seq: int | None = None
        self.alert: StreamAlert | None = None

    def view(self) -> _View:
        """What the stream's health is computed from (a copy: hold the monitor's lock to take it)."""
        return _View(self.expected_hz, self.last_received_ns, self.alert is not None, tuple(self.window))


@dataclass(frozen=True, slots=True)
class _View:
    """A stream's window and state as of one moment; its health is computed from it outside the lock.

    The recorder takes the monitor's lock for every message it counts: summing every window of a
    busy rig under the lock (a fleet holds ~20 000 messages in 5 s) kept it waiting (when it still
    recorded on the bus delivery thread, at the robots' real-time priority, for a monitor thread
    the real-time threads did not let run). Copying a window is one C loop.
    """

    expected_hz: float
    last_received_ns: int | None
    stalled: bool
    window: tuple[tuple[int, int, int, int], ...]


@dataclass(frozen=True, slots=True)
class _Report:
    """A health report's inputs, taken under the lock; :meth:`StreamHealthMonitor._health_json` writes it."""

    now: int
    started_ns: int
    streams: dict[str, _View]
    overflow: dict[str, JsonValue]
    active: list[str]


class StreamHealthMonitor:
    """Watches every stream a node receives; publishes health at ~1 Hz and alerts on stalls.

    Feed it every IR message (:meth:`observe` from a handler that already decoded the sample, or
    :meth:`observe_message`); it keeps a sliding window per topic of receive times, capture
    intervals and sequence gaps. :meth:`tick` checks for stalls and publishes; a background thread
    calls it every ``check_interval_s``, or the caller drives it (``check_interval_s=None``, tests).

    Stall rule: a stream that has sent at least one message is stalled when nothing has been
    received for ``max(stall_periods / expected_hz, min_stall_s)`` (3 periods, 0.2 s floor by
    default: a few lost samples or a scheduler hiccup on a 100 Hz stream do not alert). The alert
    goes out at the first tick past that, so within threshold + ``check_interval_s`` of the last
    message: under 1 s for every stream of 3.5 Hz and up. A stream with no expected rate uses the
    rate measured in the window, or 1 s before it has one. It clears (a message with
    ``active: false``) at the first tick after data resumes.

    Topics: health JSON on ``telerig/v1/<rig>/<node>/health`` and alerts on
    ``telerig/v1/<rig>/<node>/alerts``, both retained. Because a retained topic keeps only the
    last message, every alert message also lists ``active_alerts``, all alerts still active, so a
    dashboard joining late sees the full picture from one message.

    Args:
        rig: Rig name.
        node: Node name the reports are published under, e.g. ``recorder``.
        bus: Bus to publish on.
        expected_rates: Expected rate [Hz] per topic (0 = unknown). These are reported (and
            ``stream_missing`` is raised for them) even before their first message.
        window_s: Sliding window for rates, gaps and drops [s] (> 0).
        gap_factor: An interval longer than this many expected periods is a gap (> 1).
        stall_periods: Silent periods before a stream is stalled (> 0).
        min_stall_s: Floor of the stall threshold [s] (> 0).
        startup_grace_s: After :meth:`start`, how long an expected stream may be silent before
            ``stream_missing`` [s] (> 0).
        publish_interval_s: Health report period [s] (> 0).
        check_interval_s: Period of the background thread calling :meth:`tick` [s] (> 0); ``None``
            runs no thread and the caller calls :meth:`tick`.
        clock: Common-clock time [ns]; injected by tests.
    """

    def __init__(
        self,
        rig: str,
        node: str,
        bus: Bus,
        expected_rates: Mapping[str, float] | None = None,
        *,
        window_s: float = 5.0,
        gap_factor: float = GAP_FACTOR,
        stall_periods: float = 3.0,
        min_stall_s: float = 0.2,
        startup_grace_s: float = 2.0,
        publish_interval_s: float = 1.0,
        check_interval_s: float | None = 0.05,
        clock: Callable[[], int] = now_ns,
    ) -> None:
        for name, value in (
            ("window_s", window_s),
            ("stall_periods", stall_periods),
            ("min_stall_s", min_stall_s),
            ("startup_grace_s", startup_grace_s),
            ("publish_interval_s", publish_interval_s),
        ):
            if not value > 0:
                raise ConfigError(f"{name} must be > 0, got {value}")
        if not gap_factor > 1:
            raise ConfigError(f"gap_factor must be > 1 period, got {gap_factor}")
        if check_interval_s is not None and not check_interval_s > 0:
            raise ConfigError(f"check_interval_s must be > 0 s or None, got {check_interval_s}")
        for topic, hz in (expected_rates or {}).items():
            if not hz >= 0 or not math.isfinite(hz):
                raise ConfigError(f"expected rate of {topic} must be >= 0 Hz (0 = unknown), got {hz}")
        self.rig = rig
        self.node = node
        self._bus = bus
        self._expected = dict(expected_rates or {})
        self._window_ns = round(window_s * 1e9)
        self._gap_factor = gap_factor
        self._stall_periods = stall_periods
        self._min_stall_ns = round(min_stall_s * 1e9)
        self._grace_ns = round(startup_grace_s * 1e9)
        self._publish_ns = round(publish_interval_s * 1e9)
        self._check_interval_s = check_interval_s
        self._clock = clock
        self._health_topic = str(Topic(rig, node, HEALTH))
        self._alerts_topic = str(Topic(rig, node, ALERTS))
        self._lock = threading.Lock()
        self._streams: dict[str, _Stream] = {}
        self._counters: dict[str, Callable[[], int]] = {}
        self._oldest_unobserved: Callable[[], int | None] = lambda: None  # see watch_backlog
        self._counter_base: dict[str, int] = {}
        self._overflow_window: dict[str, deque[tuple[int, int]]] = {}
        self._overflow_alert: StreamAlert | None = None
        self._overflow_final: dict[str, int] = {}
        self._history: list[StreamAlert] = []
        self._started_ns = 0
        self._last_publish_ns: int | None = None
        self._running = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._reset(clock())

    @property
    def health_topic(self) -> str:
        """``telerig/v1/<rig>/<node>/health``."""
        return self._health_topic

    @property
    def alerts_topic(self) -> str:
        """``telerig/v1/<rig>/<node>/alerts``."""
        return self._alerts_topic

    def watch_counter(self, name: str, read: Callable[[], int]) -> None:
        """Track a cumulative drop counter, e.g. ``lambda: bus.stats.inbox_overflow``.

        It is read at every tick; increases in the window are reported under ``overflow`` and
        raise ``queue_overflow``. Counts before :meth:`start` are not attributed to the episode.
        """
        with self._lock:
            self._counters[name] = read
            self._counter_base[name] = int(read())
            self._overflow_window[name] = deque()

    def watch_backlog(self, oldest_ns: Callable[[], int | None]) -> None:
        """Let a feeder that runs behind its bus delivery (the recorder's writer thread) say how far
        behind: ``oldest_ns()`` is the receive time [ns, this monitor's clock] of the oldest message
        received and not yet observed, ``None`` when there is none. Streams are then checked for
        stalls up to that time, not up to now: a message the feeder still holds is not silence."""
        self._oldest_unobserved = oldest_ns

    # --- lifecycle -------------------------------------------------------------------------------

    def start(self) -> None:
        """Reset the counters for a new episode and start the background thread (if any); idempotent."""
        with self._lock:
            if self._running:
                return
            self._running = True
            self._reset(self._clock())
        if self._check_interval_s is not None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._loop, name=f"health-{self.node}", daemon=True)
            self._thread.start()

    def stop(self) -> None:
        """Stop the thread, clear every active alert (published) and publish a last report; idempotent.

        :meth:`summary` keeps describing the episode until the next :meth:`start`.
        """
        with self._lock:
            if not self._running:
                return
            self._running = False
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5.0)
        self._thread = None
        now = self._clock()
        with self._lock:
            cleared = [self._clear(s.alert, now, s) for s in self._streams.values() if s.alert is not None]
            for s in self._streams.values():
                s.alert = None
            if self._overflow_alert is not None:
                cleared.append(self._clear(self._overflow_alert, now, None))
                self._overflow_alert = None
            report = self._report(now)
            self._overflow_final = self._overflow_totals()
        self._publish_alerts(cleared)
        self._publish(self._health_topic, self._health_json(report))

    def close(self) -> None:
        """Same as :meth:`stop`. Idempotent."""
        self.stop()

    def __enter__(self) -> StreamHealthMonitor:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # --- input -----------------------------------------------------------------------------------

    def observe(self, topic: str, *, capture_ns: int, seq: int | None, received_ns: int) -> None:
        """Count one message (cheap: called for every message the recorder writes).

        Args:
            topic: The message's topic.
            capture_ns: The sample's capture time, common clock [ns].
            seq: The sample's sequence number; ``None`` when it has none.
            received_ns: When this node received it, in the monitor's clock [ns].
        """
        with self._lock:
            if not self._running:
                return
            s = self._streams.get(topic)
            if s is None:
                s = self._streams[topic] = _Stream(self._expected.get(topic, 0.0))
            interval = 0
            if s.messages == 0:
                s.first_capture_ns = capture_ns
            elif capture_ns > s.last_capture_ns:
                interval = capture_ns - s.last_capture_ns
                s.max_gap_ns = max(s.max_gap_ns, interval)
                if s.expected_hz > 0 and interval * s.expected_hz > self._gap_factor * 1e9:
                    s.gaps += 1
            drops = 0
            if seq is not None:
                if s.last_seq is not None and seq > s.last_seq + 1:
                    drops = seq - s.last_seq - 1
                    s.drops += drops
                s.last_seq = seq  # a lower seq is a restarted source: count from there
            s.last_capture_ns = max(s.last_capture_ns, capture_ns)
            s.last_received_ns = received_ns
            s.messages += 1
            window = s.window
            window.append((received_ns, interval, drops, received_ns - capture_ns))
            horizon = received_ns - self._window_ns
            while window and window[0][0] <= horizon:
                window.popleft()

    def observe_message(self, message: Message) -> None:
        """Decode a message of an IR stream (by the catalogue) and :meth:`observe` it; others are ignored."""
        spec = spec_by_name(message.topic.rsplit("/", 1)[-1])
        if spec is None or spec.kind is not PayloadKind.IR:
            return
        try:
            sample = wire.decode(message.payload)
        except WireError:
            return
        stamp = sample.stamp
        seq = spec.loss_seq(stamp.seq)
        self.observe(message.topic, capture_ns=stamp.capture_ns, seq=seq, received_ns=message.received_ns)

    # --- evaluation ------------------------------------------------------------------------------

    def tick(self, now_ns: int | None = None) -> list[StreamAlert]:
        """Check for stalls, recoveries and overflow; publish health when it is due.

        Args:
            now_ns: Current time [ns]; the clock's when ``None``.

        Returns:
            The alerts raised or cleared by this tick (already published).
        """
        now = self._clock() if now_ns is None else now_ns
        backlog = self._oldest_unobserved()
        observed = now if backlog is None else min(now, backlog)
        with self._lock:
            if not self._running:
                return []
            changes = self._check_streams(observed) + self._check_overflow(now)
            report = None
            if self._last_publish_ns is None or now - self._last_publish_ns >= self._publish_ns:
                self._last_publish_ns = now
                report = self._report(now)
        self._publish_alerts(changes)
        if report is not None:
            self._publish(self._health_topic, self._health_json(report))
        return changes

    def health(self, now_ns: int | None = None) -> dict[str, StreamHealth]:
        """Current window of every stream, by topic."""
        now = self._clock() if now_ns is None else now_ns
        with self._lock:
            views, started = {t: s.view() for t, s in sorted(self._streams.items())}, self._started_ns
        return {t: self._window(t, view, now, started) for t, view in views.items()}

    def active_alerts(self) -> list[StreamAlert]:
        """Alerts raised and not cleared."""
        with self._lock:
            return self._active()

    def summary(self) -> dict[str, JsonValue]:
        """Episode totals for the manifest (JSON data).

        Returns:
            ``{"window_s", "stall_rule", "streams": {topic: {"expected_hz", "measured_hz",
            "messages", "drops", "gaps", "max_gap_ms", "stalls", "stalled_s"}}, "overflow":
            {counter: n}, "alerts": [alert, ...]}``. ``measured_hz`` is over the capture span of
            the episode; ``stalled_s`` the time spent stalled (ongoing stalls up to the end).
        """
        with self._lock:
            now = self._clock()
            streams: dict[str, JsonValue] = {}
            for topic, s in sorted(self._streams.items()):
                span = (s.last_capture_ns - s.first_capture_ns) / 1e9
                ongoing = s.alert is not None and s.alert.code == "stream_stalled"
                stalled_ns = s.stall_ns + (now - s.alert.since_ns if ongoing and s.alert else 0)
                streams[topic] = {
                    "expected_hz": s.expected_hz,
                    "measured_hz": round((s.messages - 1) / span, 3) if s.messages > 1 and span > 0 else 0.0,
                    "messages": s.messages,
                    "drops": s.drops,
                    "gaps": s.gaps,
                    "max_gap_ms": round(s.max_gap_ns / 1e6, 3),
                    "stalls": s.stalls,
                    "stalled_s": round(stalled_ns / 1e9, 3),
                }
            totals = self._overflow_totals() if self._running else self._overflow_final
            overflow: dict[str, JsonValue] = dict(totals)
            return {
                "window_s": self._window_ns / 1e9,
                "stall_rule": (
                    f"no message for max({self._stall_periods:g} periods, {self._min_stall_ns / 1e9:g} s)"
                ),
                "streams": streams,
                "overflow": overflow,
                "alerts": [a.to_json() for a in self._history],
            }

    # --- internals (hold self._lock) -------------------------------------------------------------

    def _reset(self, now: int) -> None:
        self._streams = {t: _Stream(hz) for t, hz in self._expected.items()}
        self._counter_base = {name: self._safe_read(name) for name in self._counters}
        self._overflow_window = {name: deque() for name in self._counters}
        self._overflow_alert = None
        self._overflow_final = {}
        self._history = []
        self._started_ns = now
        self._last_publish_ns = None

    def _overflow_totals(self) -> dict[str, int]:
        return {name: self._safe_read(name) - base for name, base in self._counter_base.items()}

    def _safe_read(self, name: str) -> int:
        try:
            return int(self._counters[name]())
        except Exception:
            log.exception("reading counter %s failed", name)
            return self._counter_base.get(name, 0)

    def _stall_threshold_ns(self, s: _Stream, now: int) -> int:
        hz = s.expected_hz
        if hz <= 0:
            # The window is pruned on arrival, so after a stall it still holds the rate before it.
            if len(s.window) < 2:
                return max(self._min_stall_ns, 1_000_000_000)
            hz = len(s.window) / (self._window_ns / 1e9)
        return max(self._min_stall_ns, round(self._stall_periods / hz * 1e9))

    def _window_counts(self, s: _View, now: int) -> tuple[int, int, int, int, int, int | None]:
        """(messages, max interval ns, gaps, drops, latency sum ns, max latency ns) received in
        (now - window, now]. Needs no lock (a view is a copy)."""
        horizon = now - self._window_ns
        messages = max_gap = gaps = drops = latency = 0
        max_latency: int | None = None
        gap_ns = self._gap_factor * 1e9 / s.expected_hz if s.expected_hz > 0 else math.inf
        for received, interval, dropped, delay in s.window:
            if received <= horizon or received > now:
                continue
            messages += 1
            drops += dropped
            max_gap = max(max_gap, interval)
            latency += delay
            max_latency = delay if max_latency is None else max(max_latency, delay)
            if interval > gap_ns:
                gaps += 1
        return messages, max_gap, gaps, drops, latency, max_latency

    def _window(self, topic: str, s: _View, now: int, started_ns: int) -> StreamHealth:
        messages, max_gap, gaps, drops, latency, max_latency = self._window_counts(s, now)
        span_ns = min(self._window_ns, now - started_ns)
        rate = messages / (span_ns / 1e9) if span_ns > 0 else 0.0
        silent = None if s.last_received_ns is None else (now - s.last_received_ns) / 1e6
        if s.last_received_ns is None:
            state = "waiting"
        elif s.stalled:
            state = "stalled"
        elif (
            drops or gaps or (s.expected_hz > 0 and span_ns >= self._window_ns and rate < 0.8 * s.expected_hz)
        ):
            state = "degraded"
        else:
            state = "ok"
        mean_ms = latency / messages / 1e6 if messages else None
        max_ms = None if max_latency is None else max_latency / 1e6
        return StreamHealth(
            topic, state, s.expected_hz, rate, messages, max_gap / 1e6, gaps, drops, silent, mean_ms, max_ms
        )

    def _check_streams(self, now: int) -> list[StreamAlert]:
        changes: list[StreamAlert] = []
        for topic, s in self._streams.items():
            if s.last_received_ns is None:
                if s.alert is None and s.expected_hz > 0 and now - self._started_ns > self._grace_ns:
                    s.alert = self._raise(
                        "stream_missing",
                        topic,
                        f"no message on {topic} {(now - self._started_ns) / 1e9:.1f} s after the start "
                        f"(expected {s.expected_hz:g} Hz)",
                        self._started_ns,
                    )
                    changes.append(s.alert)
                continue
            silent = now - s.last_received_ns
            threshold = self._stall_threshold_ns(s, now)
            if s.alert is None and silent > threshold:
                s.stalls += 1
                s.alert = self._raise(
                    "stream_stalled",
                    topic,
                    f"no message on {topic} for {silent / 1e6:.0f} ms (threshold {threshold / 1e6:.0f} ms"
                    + (f", expected {s.expected_hz:g} Hz)" if s.expected_hz > 0 else ")"),
                    s.last_received_ns,
                )
                changes.append(s.alert)
            elif s.alert is not None and silent <= threshold:
                changes.append(self._clear(s.alert, s.last_received_ns, s))
                s.alert = None
        return changes

    def _check_overflow(self, now: int) -> list[StreamAlert]:
        for name, window in self._overflow_window.items():
            total = self._safe_read(name) - self._counter_base[name]
            if not window or total != window[-1][1]:
                window.append((now, total))
        overflowing = {n: v for n in self._overflow_window if (v := self._overflow_in_window(n, now)) > 0}
        if overflowing and self._overflow_alert is None:
            what = ", ".join(f"{n} +{v}" for n, v in sorted(overflowing.items()))
            self._overflow_alert = self._raise(
                "queue_overflow",
                _OVERFLOW_STREAM,
                f"bounded queues dropped messages in the last {self._window_ns / 1e9:g} s: {what}",
                now,
                severity="warning",
            )
            return [self._overflow_alert]
        if not overflowing and self._overflow_alert is not None:
            cleared = self._clear(self._overflow_alert, now, None)
            self._overflow_alert = None
            return [cleared]
        return []

    def _overflow_in_window(self, name: str, now: int) -> int:
        """Increase of a watched counter over (now - window, now], from the totals sampled at ticks."""
        window = self._overflow_window[name]
        horizon = now - self._window_ns
        while len(window) > 1 and window[1][0] <= horizon:
            window.popleft()  # window[0] stays the last total at or before the horizon
        if not window:
            return 0
        baseline = window[0][1] if window[0][0] <= horizon else 0
        return window[-1][1] - baseline

    def _raise(
        self, code: AlertCode, stream: str, reason: str, since_ns: int, *, severity: Severity = "error"
    ) -> StreamAlert:
        alert = StreamAlert(code, stream, reason, _suggested_action(code, stream), since_ns, severity)
        log.warning("%s: %s", code, reason)
        self._remember(alert)
        return alert

    def _clear(self, alert: StreamAlert, at_ns: int, s: _Stream | None) -> StreamAlert:
        if s is not None and alert.code == "stream_stalled":
            s.stall_ns += max(0, at_ns - alert.since_ns)
        cleared = dataclasses.replace(alert, active=False, cleared_ns=at_ns)
        log.info("%s cleared on %s", alert.code, alert.stream)
        self._remember(cleared)
        return cleared

    def _remember(self, alert: StreamAlert) -> None:
        if len(self._history) < _MAX_ALERT_HISTORY:
            self._history.append(alert)

    def _active(self) -> list[StreamAlert]:
        active = [s.alert for s in self._streams.values() if s.alert is not None]
        if self._overflow_alert is not None:
            active.append(self._overflow_alert)
        return active

    def _report(self, now: int) -> _Report:
        overflow: dict[str, JsonValue] = {}
        for name in self._overflow_window:
            total = self._safe_read(name) - self._counter_base[name]
            overflow[name] = {"total": total, "window": self._overflow_in_window(name, now)}
        streams = {t: s.view() for t, s in sorted(self._streams.items())}
        active = [f"{a.code}:{a.stream}" for a in self._active()]
        return _Report(now, self._started_ns, streams, overflow, active)

    def _health_json(self, report: _Report) -> bytes:
        now = report.now
        streams: dict[str, JsonValue] = {
            t: self._window(t, view, now, report.started_ns).to_json() for t, view in report.streams.items()
        }
        doc: dict[str, JsonValue] = {
            "type": "stream_health",
            "time_ns": now,
            "window_s": self._window_ns / 1e9,
            "streams": streams,
            "overflow": report.overflow,
            "active_alerts": list(report.active),
        }
        return json.dumps(doc, separators=(",", ":")).encode()

    # --- publishing (without the lock) -----------------------------------------------------------

    def _publish_alerts(self, changes: list[StreamAlert]) -> None:
        if not changes:
            return
        with self._lock:
            active = [a.to_json() for a in self._active()]
            now = self._clock()
        for alert in changes:
            doc = alert.to_json()
            doc.update({"node": self.node, "time_ns": now, "active_alerts": list(active)})
            self._publish(self._alerts_topic, json.dumps(doc, separators=(",", ":")).encode())

    def _publish(self, topic: str, payload: bytes) -> None:
        qos, retain = qos_for(topic.rsplit("/", 1)[-1])
        try:
            self._bus.publish(topic, payload, qos=qos, retain=retain)
        except Exception:
            log.exception("publishing %s failed", topic)

    def _loop(self) -> None:
        assert self._check_interval_s is not None
        priority.enter("work")  # below the control loop
        while not self._stop.wait(self._check_interval_s):
            try:
                self.tick()
            except Exception:
                log.exception("health check of %s failed", self.node)


def _suggested_action(code: AlertCode, stream: str) -> str:
    try:
        node = Topic.parse(stream).node
    except ValueError:
        node = stream
    if code == "stream_stalled":
        return (
            f"check that node {node!r} is running and connected (see its health topic); "
            "the episode has a gap here: discard it or trim the gap at export"
        )
    if code == "stream_missing":
        return f"start node {node!r} or remove this stream from the rig's expected streams"
    return "the station is overloaded: reduce camera resolution or stream rates, or record on a faster disk"
