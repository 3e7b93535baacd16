"""The control center's link to a running rig: a bus client of its broker, a live state model, commands.

:class:`RigGateway` logs in to the rig's broker as the ``web`` principal (it may publish on
``R/safety/command``, ``R/coordinator/command``, devices' ``command`` and the robots' aid commands;
see :mod:`telerig.bus.acl`) and subscribes to what the dashboard shows, never to the high-rate
sample streams:

==========================  ===================================================================
topic (``R/<node>/...``)    kept as
==========================  ===================================================================
``<recorder>/health``       per-stream state, rate, drops, gaps, silence (retained JSON)
``<device>/health``         per-device rate and drops (retained JSON)
``<robot>/health``          per-robot input-to-actuation latency p50/p99, 2 Hz (retained JSON)
``<robot>/status``          per-robot safety status word (retained text)
``<robot>/latency``         per-robot latency per stage against the rig's budgets, 2 Hz (retained
                            JSON), with the browser stages of :attr:`RigGateway.view` beside it
``*/alerts`` ``*/events``   an alerts ring buffer with each alert's suggested action, and the
                            active alerts of every publisher (retained JSON documents)
``coordinator/session``     the session state (retained :class:`SessionStatus`)
``<station>/session``       each station's start report (retained)
``<station>/clock_ping``    a station's last-seen time (stations ping at ~2 Hz)
``<station>/clock_pong``    the station's clock offset (``t2 - t1`` of the exchanges)
==========================  ===================================================================

Memory is bounded whatever the bus carries: every JSON payload goes through the bounded decoder
(:func:`telerig.bus.jsonpayload.parse_json_object`, at most the catalogue's ``max_bytes`` of the
stream), only the rig's own nodes are kept (a publisher the rig does not have is counted and
dropped), every table has a cap and every text is cut. A payload that is too large, not JSON or not
the expected shape is counted in :attr:`RigGateway.dropped` by reason and dropped; nothing a client
publishes can raise out of a handler.

Lights (``green``/``amber``/``red``/``grey``) are computed when a snapshot is taken, so a station
that stops pinging turns red :data:`STATION_RED_S` after its last ping without any message.
"""

from __future__ import annotations

import json
import logging
import math
import secrets
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Literal

from pydantic import BaseModel, ConfigDict, JsonValue

from telerig.bus.base import Message
from telerig.bus.catalogue import (
    ALERTS,
    CLOCK_PING,
    CLOCK_PONG,
    COORDINATOR,
    EVENTS,
    HEALTH,
    LATENCY,
    LATENCY_VIEW,
    PAGE_IN,
    PAGE_OUT,
    PREVIEW,
    SESSION,
    STATUS,
    NodeRole,
    RigNodes,
    stream_spec,
)
from telerig.bus.jsonpayload import parse_json_object
from telerig.bus.mqtt import MqttBus, TlsOptions
from telerig.bus.topics import Topic
from telerig.config.latency import ROBOT_STAGES, VIDEO_STAGES
from telerig.config.schema import RigConfig
from telerig.errors import BusError, TelerigError, WireError
from telerig.runtime.control_health import DEFAULT_BUDGET_MS, REPORT_TYPE, STAGES_TYPE
from telerig.runtime.session import EpisodeCommand, SessionStatus
from telerig.safety.commands import SafetyCommand, safety_command_topic
from telerig.server.view_latency import ViewLatency

__all__ = [
    "ALERT_HISTORY",
    "STATION_AMBER_S",
    "STATION_RED_S",
    "AlertOut",
    "CameraOut",
    "DeviceOut",
    "GatewayCounters",
    "LatencyOut",
    "LatencyStagesOut",
    "Light",
    "RigGateway",
    "RigSnapshot",
    "RobotOut",
    "SafetyResult",
    "SessionOut",
    "StageOut",
    "StationOut",
    "StreamOut",
]

log = logging.getLogger(__name__)

#: Dashboard colour of a stream, device, robot or station: ``grey`` when nothing current is known.
Light = Literal["green", "amber", "red", "grey"]

#: A station silent this long is amber, and red after :data:`STATION_RED_S` [s] (they ping at 2 Hz).
STATION_AMBER_S = 0.8
STATION_RED_S = 1.5
#: A health report older than this is stale [s] (recorders and devices report every second).
HEALTH_STALE_S = 3.0
#: A robot's latency report older than this is stale [s] (control nodes report at 2 Hz): red while
#: recording (its control node stopped reporting), grey otherwise.
LATENCY_STALE_S = 1.5
#: A camera preview older than this is stale [s] (cameras send ~2 a second).
PREVIEW_STALE_S = 3.0
#: Alerts kept in the ring buffer (newest last).
ALERT_HISTORY = 200
_MAX_SOURCES = 32  # recorders, safety nodes and the broker that may hold active alerts / health
_MAX_STREAMS_PER_SOURCE = 512
_MAX_ACTIVE_PER_SOURCE = 64
_MAX_DROP_REASONS = 16  # of one device's "dropped" counters
_TEXT = 500
_WORD = 64
_PONGS = 16
_PREVIEW_STAMPS = 8  # a page draws a preview within a few seconds of its arrival (they come at 2 Hz)
_STREAM_DOWN = frozenset({"stream_stalled", "stream_missing"})
#: The states a two-step session command ends in (restart: stopped, then armed; end: stopped, then idle).
_FINAL_STATES = {"restart": frozenset({"armed", "recording"}), "end": frozenset({"idle"})}


class _Out(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class StreamOut(_Out):
    """One stream as the rig's recorder last reported it (rates, drops and gaps over its window;
    ``latency_ms``: mean capture-to-recorder time of the window's messages).

    ``light``: green when ``ok``; amber when ``degraded`` or ``waiting``; red when ``stalled``, or
    when the report is stale while the session records; grey when stale otherwise.
    """

    topic: str
    source: str
    state: str
    light: Light
    expected_hz: float
    measured_hz: float
    messages: int
    drops: int
    gaps: int
    max_gap_ms: float
    silent_ms: float | None
    latency_ms: float | None
    max_latency_ms: float | None
    report_age_s: float


class DeviceOut(_Out):
    """A device node's health counters (``dropped`` by reason); ``None`` before its first report.

    ``light``: red when a recorder's active alert says one of its streams stalled or is missing,
    or its report is stale while the session records; amber when it dropped samples or published
    none; green otherwise; grey before its first report or when stale outside a recording.
    """

    id: str
    light: Light
    rate_hz: float | None
    received: int | None
    published: int | None
    dropped: dict[str, int]
    report_age_s: float | None
    #: The device's last operator calibration event (``progress: ...``, ``done: ...``, ``failed: ...``).
    calibration: str | None = None


class LatencyOut(_Out):
    """A robot's live input-to-actuation latency, from its control node's report (2 Hz) [ms].

    ``p50_ms``/``p99_ms``/``max_ms``: device capture -> the command the driver applied, over the
    last ``window_s``; ``state_p50_ms``/``state_p99_ms``: capture -> the first measured state after
    it; ``commands``: applied commands in the window. ``light``: green when p99 is within
    ``budget_ms``, amber within ``hold_ms`` (the input age at which the safety chain holds the
    robot), red beyond it or when the report is stale while the session records; grey when there
    was no input in the window or the report is stale otherwise.
    """

    light: Light
    window_s: float
    budget_ms: float
    hold_ms: float
    commands: int
    p50_ms: float | None
    p99_ms: float | None
    max_ms: float | None
    state_p50_ms: float | None
    state_p99_ms: float | None
    report_age_s: float


class StageOut(_Out):
    """One stage of the operator loop over the last window [ms] (see :mod:`telerig.config.latency`):
    green when its p99 is within ``budget_ms``, amber within twice, red beyond; grey without data."""

    stage: str
    light: Light
    count: int
    p50_ms: float | None
    p99_ms: float | None
    max_ms: float | None
    budget_ms: float


class LatencyStagesOut(_Out):
    """Where a robot's or a camera's latency goes, stage by stage: a robot's from its control node
    (``<robot>/latency``) and the page's ``rendered``; a camera's preview from the camera node and the
    pages. ``end_to_end``: capture to measured state (robots). ``report_age_s``: of the control
    node's report; ``out_of_order``: samples whose stamps went backwards in the window."""

    node: str
    kind: Literal["robot", "camera"]
    stages: list[StageOut]
    end_to_end: StageOut | None
    report_age_s: float | None
    out_of_order: int


class RobotOut(_Out):
    """A robot's safety status word (``ok``, ``limited``, ``holding``, ``stopped``, ``estopped``)
    and its live latency (``None`` before its control node's first report)."""

    id: str
    status: str | None
    light: Light
    status_age_s: float | None
    latency: LatencyOut | None = None


class CameraOut(_Out):
    """A camera's latest JPEG preview (``GET /api/rig/cameras/{id}/preview``): its age and size."""

    id: str
    light: Light
    preview_age_s: float | None
    preview_bytes: int | None


class StationOut(_Out):
    """A station of the rig: when it last pinged the coordinator and its clock offset.

    ``clock_offset_ms``: coordinator minus station clock from the exchanges the gateway sees
    (smallest ``t2 - t1`` of the last 16: high by at most the one-way bus delay).
    """

    id: str
    light: Light
    last_seen_s: float | None
    clock_offset_ms: float | None
    last_start_late_ms: float | None


class AlertOut(_Out):
    """An alert or event of a recorder, the safety supervisor, a device or the broker."""

    t_ns: int
    source: str
    code: str
    severity: str
    subject: str
    reason: str
    suggested_action: str
    active: bool


class SessionOut(_Out):
    """The coordinator's session state (:class:`~telerig.runtime.session.SessionStatus`);
    ``paused_devices``: the input devices paused on their own (their robots hold)."""

    state: str
    session_id: str
    episode_id: str | None
    task: str | None
    operator: str | None
    reason: str | None
    outcome: str | None
    discarded: bool
    ended: bool
    seq: int
    start_at_ns: int | None
    age_s: float
    paused_devices: list[str] = []


class GatewayCounters(_Out):
    """Messages the gateway took, and those it dropped by reason (``oversize``, ``malformed``,
    ``unknown_node``, ``over_cap``), with the last drop's one-line reason."""

    received: int
    dropped: dict[str, int]
    last_drop: str | None


class RigSnapshot(_Out):
    """The whole rig at a glance."""

    rig: str
    connected: bool
    link_error: str | None
    fault_policy: str
    t_ns: int
    session: SessionOut | None
    robots: list[RobotOut]
    stations: list[StationOut]
    cameras: list[CameraOut]
    devices: list[DeviceOut]
    streams: list[StreamOut]
    active_alerts: list[AlertOut]
    alerts: list[AlertOut]
    counters: GatewayCounters
    latency_stages: list[LatencyStagesOut] = []


class RobotConfirmation(_Out):
    """A robot's answer to an e-stop or reset: its status when the wait ended."""

    robot: str
    status: str | None
    confirmed: bool


class SafetyResult(_Out):
    """What an e-stop or reset reached: every targeted robot and whether it confirmed."""

    command: Literal["estop", "reset"]
    robots: list[RobotConfirmation]
    confirmed: bool


@dataclass(frozen=True, slots=True)
class _Stream:
    state: str
    expected_hz: float
    measured_hz: float
    messages: int
    drops: int
    gaps: int
    max_gap_ms: float
    silent_ms: float | None
    latency_ms: float | None
    max_latency_ms: float | None

    @classmethod
    def of(cls, s: Mapping[str, JsonValue]) -> _Stream:
        return cls(
            _text(s.get("state"), _WORD) or "unknown",
            _num(s.get("expected_hz")) or 0.0,
            _num(s.get("measured_hz")) or 0.0,
            _int(s.get("messages")) or 0,
            _int(s.get("drops")) or 0,
            _int(s.get("gaps")) or 0,
            _num(s.get("max_gap_ms")) or 0.0,
            _num(s.get("silent_ms")),
            _num(s.get("latency_ms")),
            _num(s.get("max_latency_ms")),
        )


@dataclass(frozen=True, slots=True)
class _Latency:
    window_s: float
    budget_ms: float
    hold_ms: float
    commands: int
    p50_ms: float | None
    p99_ms: float | None
    max_ms: float | None
    state_p50_ms: float | None
    state_p99_ms: float | None

    @classmethod
    def of(cls, doc: Mapping[str, JsonValue]) -> _Latency:
        """Raises WireError (counted as malformed) unless it is a control node's latency report whose
        numbers are all finite and in range (a NaN, an infinity or 1e300 is a forged report)."""
        command, state = doc.get("input_to_command"), doc.get("input_to_state", {})
        if doc.get("type") != REPORT_TYPE or not isinstance(command, dict) or not isinstance(state, dict):
            raise WireError(f"a robot health report that is not a {REPORT_TYPE!r} document")
        count = command.get("count")
        if not isinstance(count, int) or isinstance(count, bool) or not 0 <= count <= 10**9:
            raise WireError(f"input_to_command.count must be an integer in [0, 1e9], got {str(count)[:40]}")
        budget, hold = _ms_field(doc, "budget_ms"), _ms_field(doc, "hold_ms")
        return cls(
            _ms_field(doc, "window_s") or 0.0,
            budget if budget is not None and budget > 0 else DEFAULT_BUDGET_MS,
            hold if hold is not None and hold > 0 else 100.0,
            count,
            _ms_field(command, "p50_ms"),
            _ms_field(command, "p99_ms"),
            _ms_field(command, "max_ms"),
            _ms_field(state, "p50_ms"),
            _ms_field(state, "p99_ms"),
        )


@dataclass(frozen=True, slots=True)
class _Stage:
    count: int
    p50_ms: float | None
    p99_ms: float | None
    max_ms: float | None
    budget_ms: float

    @classmethod
    def of(cls, doc: JsonValue) -> _Stage:
        """Raises WireError unless ``doc`` is a stage's figures (finite, in range)."""
        if not isinstance(doc, dict):
            raise WireError("a latency stage that is not an object")
        count, budget = doc.get("count"), _ms_field(doc, "budget_ms")
        if not isinstance(count, int) or isinstance(count, bool) or not 0 <= count <= 10**9:
            raise WireError(f"a stage's count must be an integer in [0, 1e9], got {str(count)[:40]}")
        if budget is None or budget <= 0:
            raise WireError("a stage's budget_ms must be a number > 0")
        return cls(
            count, _ms_field(doc, "p50_ms"), _ms_field(doc, "p99_ms"), _ms_field(doc, "max_ms"), budget
        )

    def out(self, stage: str, stale: bool) -> StageOut:
        light: Light = "grey"
        if not stale and self.count > 0 and self.p99_ms is not None:
            budget = self.budget_ms
            light = "green" if self.p99_ms <= budget else "amber" if self.p99_ms <= 2 * budget else "red"
        return StageOut(
            stage=stage,
            light=light,
            count=self.count,
            p50_ms=self.p50_ms,
            p99_ms=self.p99_ms,
            max_ms=self.max_ms,
            budget_ms=self.budget_ms,
        )


@dataclass(frozen=True, slots=True)
class _Stages:
    """A control node's ``latency_stages`` report, validated."""

    stages: dict[str, _Stage]
    end_to_end: _Stage
    out_of_order: int

    @classmethod
    def of(cls, doc: Mapping[str, JsonValue]) -> _Stages:
        stages, out_of_order = doc.get("stages"), _int(doc.get("out_of_order"))
        if doc.get("type") != STAGES_TYPE or not isinstance(stages, dict):
            raise WireError(f"a robot latency report that is not a {STAGES_TYPE!r} document")
        if set(stages) != set(ROBOT_STAGES):
            raise WireError(f"a robot latency report must have the stages {', '.join(ROBOT_STAGES)}")
        if out_of_order is None or not 0 <= out_of_order <= 10**9:
            raise WireError("out_of_order must be an integer in [0, 1e9]")
        return cls(
            {s: _Stage.of(stages[s]) for s in ROBOT_STAGES}, _Stage.of(doc.get("end_to_end")), out_of_order
        )


@dataclass(slots=True)
class _Health:
    received_mono: int
    streams: dict[str, _Stream]


@dataclass(slots=True)
class _Device:
    received_mono: int | None = None
    rate_hz: float | None = None
    received: int | None = None
    published: int | None = None
    dropped: dict[str, int] = field(default_factory=dict)


@dataclass(slots=True)
class _Station:
    last_ping_mono: int | None = None
    offsets: deque[int] = field(default_factory=lambda: deque(maxlen=_PONGS))
    late_ns: int | None = None


class RigGateway:
    """A live view of one running rig and the operator commands to it (see the module docs).

    Thread-safe: the bus handlers run on the bus client's thread; :meth:`snapshot` and the commands
    are called from web requests.

    Args:
        rig: The rig's configuration (its robots, devices, stations and fault policy).
        url: The broker URL with the ``web`` principal's login.
        tls: TLS options of an ``mqtts://`` broker (with ``url``).
        login: Instead of ``url``: returns the URL and TLS options now (``telerig serve`` reads the
            running rig's login file, as ``telerig safety`` does); called again when the gateway is
            not connected (see :meth:`start`).
        client_id: MQTT client id; ``web-<random>`` by default (several servers may watch a rig).
        retry_s: With ``login``: how often to try again while not connected [s].
    """

    def __init__(
        self,
        rig: RigConfig,
        url: str | None = None,
        *,
        tls: TlsOptions | None = None,
        login: Callable[[], tuple[str, TlsOptions | None]] | None = None,
        client_id: str | None = None,
        retry_s: float = 1.0,
    ) -> None:
        if (url is None) == (login is None):
            raise ValueError("give the gateway a broker url or a login function, not both")
        self.rig = rig
        self.name = rig.name
        self._url = url
        self._tls = tls
        self._login = login
        self._retry_s = retry_s
        self._client_id = client_id or f"web-{secrets.token_hex(3)}"
        self._nodes = RigNodes.of(
            devices=[d.id for d in rig.devices],
            robots=[r.id for r in rig.robots],
            cameras=[c.id for c in rig.cameras],
            stations=[s.id for s in rig.stations],
        )
        self._robot_ids = tuple(r.id for r in rig.robots)
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)
        self._bus: MqttBus | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._down_since: float | None = None
        #: Why the gateway is not connected (the login function's or the broker's one line).
        self.link_error: str | None = None
        self._alerts: deque[AlertOut] = deque(maxlen=ALERT_HISTORY)
        self.received = 0
        #: Messages dropped, by reason.
        self.dropped: dict[str, int] = {}
        self.last_drop: str | None = None
        self._page_listener: Callable[[str, bytes], None] | None = None
        #: Extra subscriptions (``R/+/<stream>``, handler) of other server parts (the operator scene),
        #: made again on every (re)connection.
        self._listeners: list[tuple[str, Callable[[Message], None]]] = []
        self._clear()
        #: The browser stages its pages report (``/api/latency``), published on ``latency_view``.
        self.view = ViewLatency(self)

    def _clear(self) -> None:
        """Forget the rig's state (a new run of the rig refills it from its retained topics)."""
        self._health: dict[str, _Health] = {}
        self._devices = {d.id: _Device() for d in self.rig.devices}
        self._robots: dict[str, tuple[str, int]] = {}  # id -> (status, received monotonic ns)
        self._latency: dict[str, tuple[_Latency, int]] = {}  # id -> (report, received monotonic ns)
        self._stages: dict[str, tuple[_Stages, int]] = {}  # robot -> (stage report, received monotonic ns)
        # camera -> (capture, encoded, received) [ns] of its last previews that carried stamps
        self._preview_stamps: dict[str, deque[tuple[int, int, int]]] = {}
        self._stations = {s.id: _Station() for s in self.rig.stations}
        self._session: tuple[SessionStatus, int] | None = None
        self._active: dict[str, list[AlertOut]] = {}
        self._replies: dict[str, tuple[int, str]] = {}  # device -> (replies seen, last reply)
        self._calibrations: dict[str, str] = {}  # device -> its last calibration event
        self._previews: dict[str, tuple[bytes, int]] = {}  # camera -> (JPEG, received monotonic ns)

    # --- lifecycle -------------------------------------------------------------------------------

    def start(self) -> RigGateway:
        """Connect to the broker and subscribe. Returns ``self``.

        With a ``login`` function the gateway does not fail when the rig is not running: it keeps
        trying every ``retry_s`` (``link_error`` says why it is not connected), and logs in again
        when the connection is lost for longer (a new run of the rig has new bus passwords and may
        have a new port).

        Raises:
            BusError: With a fixed ``url``: the broker is unreachable or refuses the login.
        """
        if self._bus is not None or self._thread is not None:
            return self
        self.view.start()
        if self._login is None:
            assert self._url is not None
            self._connect(self._url, self._tls)
            return self
        self._stop.clear()
        self._relogin()
        self._thread = threading.Thread(target=self._watch, name=f"gateway-{self.name}", daemon=True)
        self._thread.start()
        return self

    def _connect(self, url: str, tls: TlsOptions | None) -> None:
        bus = MqttBus(url, client_id=self._client_id, tls=tls).connect()
        handlers: Mapping[str, Callable[[Message], None]] = {
            HEALTH: self._on_health,
            STATUS: self._on_status,
            ALERTS: self._on_alerts,
            EVENTS: self._on_event,
            SESSION: self._on_session,
            CLOCK_PING: self._on_ping,
            CLOCK_PONG: self._on_pong,
            PREVIEW: self._on_preview,
            PAGE_OUT: self._on_page_out,
            LATENCY: self._on_latency,
        }
        with self._changed:
            old, self._bus = self._bus, bus
            if old is not None:
                self._clear()
            self._url, self._tls, self.link_error, self._down_since = url, tls, None, None
            listeners = list(self._listeners)
        for stream, handler in handlers.items():
            bus.subscribe(Topic.pattern(self.name, "+", stream), self._guard(handler), qos=1)
        for stream, listener in listeners:
            bus.subscribe(Topic.pattern(self.name, "+", stream), self._guard(listener), qos=0)
        if old is not None:
            old.close()

    def _relogin(self) -> None:
        assert self._login is not None
        try:
            url, tls = self._login()
            if url != self._url or tls != self._tls or self._bus is None:
                self._connect(url, tls)
        except (TelerigError, OSError) as exc:
            self.link_error = str(exc).splitlines()[0][:_TEXT] if str(exc) else type(exc).__name__

    def _watch(self) -> None:
        while not self._stop.wait(self._retry_s):
            bus = self._bus
            if bus is not None and bus.connected:
                self._down_since = None
                continue
            now = time.monotonic()
            if self._down_since is None:
                self._down_since = now
            if bus is None or now - self._down_since >= 2 * self._retry_s:
                self._relogin()

    def close(self) -> None:
        """Disconnect. Idempotent."""
        self.view.stop()
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=10.0)
            self._thread = None
        bus, self._bus = self._bus, None
        if bus is not None:
            bus.close()

    def __enter__(self) -> RigGateway:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def connected(self) -> bool:
        """Whether the broker has acknowledged the current connection."""
        return self._bus is not None and self._bus.connected

    @property
    def robots(self) -> tuple[str, ...]:
        """The rig's robot ids."""
        return self._robot_ids

    # --- commands --------------------------------------------------------------------------------

    def send_session(self, command: EpisodeCommand, *, timeout_s: float = 3.0) -> SessionStatus | None:
        """Publish an episode command to the coordinator (as ``telerig session`` does) and wait for the
        session state to change; returns the new state, ``None`` when it did not change in time (the
        coordinator refused the command in its state, or is not running). ``restart`` and ``end``
        change it twice in a row (stopped, then armed or idle): the reply is the second.

        Raises:
            BusError: Not connected to the broker.
        """
        bus = self._connected_bus()
        with self._lock:
            before = None if self._session is None else self._session[0]
        bus.publish(str(Topic(self.name, COORDINATOR, "command")), command.model_dump_json().encode(), qos=1)
        deadline = time.monotonic() + timeout_s
        final = _FINAL_STATES.get(command.command)
        with self._changed:
            seen = before
            changed = False
            while True:
                now = None if self._session is None else self._session[0]
                if now is not None and (
                    seen is None or (now.session_id, now.seq) != (seen.session_id, seen.seq)
                ):
                    seen, changed = now, True
                if changed and (final is None or (seen is not None and seen.state.value in final)):
                    return seen
                left = deadline - time.monotonic()
                if left <= 0:
                    return seen if changed else None
                self._changed.wait(left)

    def send_safety(self, command: SafetyCommand, *, timeout_s: float = 3.0) -> SafetyResult:
        """Publish an e-stop or reset (as ``telerig safety`` does) and wait until every targeted
        robot's status confirms it (``estopped`` after an e-stop, anything else after a reset).

        Raises:
            BusError: Not connected to the broker.
        """
        bus = self._connected_bus()
        targets = list(self._robot_ids) if command.robot is None else [command.robot]
        bus.publish(safety_command_topic(self.name), command.model_dump_json().encode(), qos=1)

        def confirmed(robot: str) -> bool:
            state = self._robots.get(robot, (None, 0))[0]
            return state == "estopped" if command.command == "estop" else state not in (None, "estopped")

        deadline = time.monotonic() + timeout_s
        with self._changed:
            while not all(confirmed(r) for r in targets):
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._changed.wait(left)
            robots = [
                RobotConfirmation(robot=r, status=self._robots.get(r, (None, 0))[0], confirmed=confirmed(r))
                for r in targets
            ]
        return SafetyResult(
            command=command.command, robots=robots, confirmed=all(r.confirmed for r in robots)
        )

    def send_device_command(
        self, device: str, command: Mapping[str, JsonValue], *, timeout_s: float = 3.0
    ) -> str | None:
        """Publish an operator command to a device (e.g. ``{"takeover": "confirm"}``, as ``telerig
        device takeover`` does) and wait for its ``command_reply`` event; returns the reply's one
        line, ``None`` when none came in time.

        Raises:
            BusError: Not connected to the broker.
            ValueError: ``device`` is not a device of the rig.
        """
        if device not in self._devices:
            raise ValueError(f"no device {device!r} in rig {self.name!r}")
        bus = self._connected_bus()
        with self._lock:
            before = self._replies.get(device, (0, ""))[0]
        bus.publish(str(Topic(self.name, device, "command")), json.dumps(command).encode(), qos=1)
        deadline = time.monotonic() + timeout_s
        with self._changed:
            while self._replies.get(device, (0, ""))[0] == before:
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._changed.wait(left)
            return self._replies[device][1]

    def publish(self, topic: str, payload: bytes, *, qos: int = 1, retain: bool = False) -> None:
        """Publish an operator command as the ``web`` principal (the voice endpoint's grammar commands,
        :mod:`telerig.voice.dispatch`); the broker's ACL drops what that principal may not send.

        Raises:
            BusError: Not connected to the broker.
        """
        self._connected_bus().publish(topic, payload, qos=qos, retain=retain)

    @property
    def devices(self) -> tuple[str, ...]:
        """The rig's device ids."""
        return tuple(self._devices)

    def send_page(self, device: str, envelope: bytes) -> None:
        """Relay a logged-in operator page's message (a relay envelope, see
        :mod:`telerig.devices.webxr.relay`) to ``device`` on its ``page_in`` topic (QoS 0: a late
        pose is worth nothing).

        Raises:
            BusError: Not connected to the broker.
        """
        self._connected_bus().publish(str(Topic(self.name, device, PAGE_IN)), envelope)

    def set_page_listener(self, listener: Callable[[str, bytes], None] | None) -> None:
        """Call ``listener(device, envelope)`` (from the bus thread) for what a device sends its
        relayed pages on its ``page_out`` topic (clock pings, closes)."""
        self._page_listener = listener

    def add_listener(self, stream: str, handler: Callable[[Message], None]) -> None:
        """Also deliver every node's ``R/+/<stream>`` to ``handler`` (QoS 0, on the bus thread: it must
        be quick), now and after every reconnection. What it raises as malformed input is counted in
        :attr:`dropped`."""
        with self._lock:
            self._listeners.append((stream, handler))
            bus = self._bus
        if bus is not None:
            bus.subscribe(Topic.pattern(self.name, "+", stream), self._guard(handler), qos=0)

    def send_latency_view(self, node: str, payload: bytes) -> None:
        """Publish a robot's or camera's ``latency_view`` report (retained; the recorder records it).

        Raises:
            BusError: Not connected.
        """
        self._connected_bus().publish(str(Topic(self.name, node, LATENCY_VIEW)), payload, qos=1, retain=True)

    def _on_page_out(self, message: Message) -> None:
        listener = self._page_listener
        topic = Topic.try_parse(message.topic)
        if listener is not None and topic is not None and topic.node in self._devices:
            listener(topic.node, message.payload)

    def _connected_bus(self) -> MqttBus:
        bus = self._bus
        if bus is None or not bus.connected:
            raise BusError(f"the control center is not connected to rig {self.name!r}'s broker")
        return bus

    # --- snapshot --------------------------------------------------------------------------------

    def snapshot(self, *, alerts: int = 50) -> RigSnapshot:
        """The rig now: session, robots, stations, devices, streams, alerts (the newest ``alerts``)."""
        mono = time.monotonic_ns()
        with self._lock:
            session = self._session_out(mono)
            recording = session is not None and session.state == "recording"
            robots = [self._robot_out(r, mono, recording) for r in self._robot_ids]
            stations = self._stations_out(mono)
            down = self._down_nodes()
            devices = [
                self._device_out(d, v, mono, recording, d in down).model_copy(
                    update={"calibration": self._calibrations.get(d)}
                )
                for d, v in self._devices.items()
            ]
            cameras = [self._camera_out(c.id, mono) for c in self.rig.cameras]
            streams = self._streams_out(mono, recording)
            active = [a for source in sorted(self._active) for a in self._active[source]]
            history = list(self._alerts)[-alerts:][::-1] if alerts > 0 else []
            counters = GatewayCounters(
                received=self.received, dropped=dict(self.dropped), last_drop=self.last_drop
            )
            stages = [self._stages_out(r, mono) for r in self._robot_ids]
        stages += [self._camera_stages_out(c.id) for c in self.rig.cameras]
        return RigSnapshot(
            rig=self.name,
            connected=self.connected,
            link_error=None if self.connected else self.link_error or "not connected to the rig's broker",
            fault_policy=self.rig.safety.policy,
            t_ns=time.time_ns(),
            session=session,
            robots=robots,
            stations=stations,
            cameras=cameras,
            devices=devices,
            streams=streams,
            active_alerts=active,
            alerts=history,
            counters=counters,
            latency_stages=stages,
        )

    def _stages_out(self, robot: str, mono: int) -> LatencyStagesOut:
        """A robot's stages: its control node's report and the pages' ``rendered``."""
        got = self._stages.get(robot)
        age = None if got is None else _age(mono, got[1])
        stale = age is None or age > LATENCY_STALE_S
        out = [] if got is None else [got[0].stages[s].out(s, stale) for s in ROBOT_STAGES]
        view = self.view.report(robot)
        if view is not None and isinstance(view["stages"], dict):
            out.append(_Stage.of(view["stages"]["rendered"]).out("rendered", False))
        return LatencyStagesOut(
            node=robot,
            kind="robot",
            stages=out,
            end_to_end=None if got is None else got[0].end_to_end.out("end_to_end", stale),
            report_age_s=age,
            out_of_order=0 if got is None else got[0].out_of_order,
        )

    def _camera_stages_out(self, camera: str) -> LatencyStagesOut:
        view = self.view.report(camera)
        stages = view["stages"] if view is not None else {}
        out = [_Stage.of(stages[s]).out(s, False) for s in VIDEO_STAGES] if isinstance(stages, dict) else []
        ooo = view["out_of_order"] if view is not None else 0
        return LatencyStagesOut(
            node=camera,
            kind="camera",
            stages=out,
            end_to_end=None,
            report_age_s=None,
            out_of_order=ooo if isinstance(ooo, int) else 0,
        )

    def _session_out(self, mono: int) -> SessionOut | None:
        if self._session is None:
            return None
        s, at = self._session
        return SessionOut(
            state=s.state.value,
            session_id=s.session_id,
            episode_id=s.episode_id,
            task=s.task,
            operator=s.operator,
            reason=s.reason,
            outcome=s.outcome,
            discarded=s.discarded,
            ended=s.ended,
            seq=s.seq,
            start_at_ns=s.start_at_ns,
            age_s=_age(mono, at),
            paused_devices=list(s.paused_devices),
        )

    def _robot_out(self, robot: str, mono: int, recording: bool) -> RobotOut:
        status, at = self._robots.get(robot, (None, None))
        light: Light = "grey"
        if status in ("ok",):
            light = "green"
        elif status in ("limited", "holding"):
            light = "amber"
        elif status is not None:
            light = "red"  # stopped (watchdog), estopped, or a word this version does not know
        return RobotOut(
            id=robot,
            status=status,
            light=light,
            status_age_s=None if at is None else _age(mono, at),
            latency=self._latency_out(robot, mono, recording),
        )

    def _latency_out(self, robot: str, mono: int, recording: bool) -> LatencyOut | None:
        got = self._latency.get(robot)
        if got is None:
            return None
        lat, at = got
        age = _age(mono, at)
        light: Light
        if age > LATENCY_STALE_S:
            light = "red" if recording else "grey"
        elif lat.p99_ms is None or lat.commands == 0:
            light = "grey"  # no input in the window: nothing to say about latency
        elif lat.p99_ms <= lat.budget_ms:
            light = "green"
        else:
            light = "amber" if lat.p99_ms <= lat.hold_ms else "red"
        return LatencyOut(
            light=light,
            window_s=lat.window_s,
            budget_ms=lat.budget_ms,
            hold_ms=lat.hold_ms,
            commands=lat.commands,
            p50_ms=lat.p50_ms,
            p99_ms=lat.p99_ms,
            max_ms=lat.max_ms,
            state_p50_ms=lat.state_p50_ms,
            state_p99_ms=lat.state_p99_ms,
            report_age_s=age,
        )

    def _camera_out(self, camera: str, mono: int) -> CameraOut:
        got = self._previews.get(camera)
        if got is None:
            return CameraOut(id=camera, light="grey", preview_age_s=None, preview_bytes=None)
        age = _age(mono, got[1])
        light: Light = "green" if age < PREVIEW_STALE_S else "grey"
        return CameraOut(id=camera, light=light, preview_age_s=age, preview_bytes=len(got[0]))

    def preview_stamps(self, camera: str, capture_ns: int) -> tuple[int, int, int] | None:
        """``(capture, encoded, received)`` [ns] of one of ``camera``'s last previews, by its capture
        stamp (within 2 us: a browser's numbers carry 53 bits); ``None`` when none matches."""
        with self._lock:
            recent = tuple(self._preview_stamps.get(camera, ()))
        return next((s for s in recent if abs(s[0] - capture_ns) <= 2_000), None)

    def preview_capture_ns(self, camera: str) -> int | None:
        """Capture time [ns] of ``camera``'s latest preview, when the camera node stamped it."""
        with self._lock:
            recent = self._preview_stamps.get(camera)
            return recent[-1][0] if recent else None

    def preview(self, camera: str) -> tuple[bytes, float] | None:
        """The latest JPEG preview of ``camera`` and its age [s]; ``None`` before the first."""
        with self._lock:
            got = self._previews.get(camera)
        return None if got is None else (got[0], _age(time.monotonic_ns(), got[1]))

    @property
    def cameras(self) -> tuple[str, ...]:
        """The rig's camera ids."""
        return tuple(c.id for c in self.rig.cameras)

    def _stations_out(self, mono: int) -> list[StationOut]:
        first = self.rig.stations[0].id
        first_alive = _silent_s(mono, self._stations[first].last_ping_mono) < STATION_RED_S
        out = []
        for sid, st in self._stations.items():
            silent = _silent_s(mono, st.last_ping_mono)
            light: Light
            if st.last_ping_mono is None:
                light = "red" if first_alive and sid != first else "grey"
            else:
                light = "green" if silent < STATION_AMBER_S else "amber" if silent < STATION_RED_S else "red"
            out.append(
                StationOut(
                    id=sid,
                    light=light,
                    last_seen_s=None if st.last_ping_mono is None else round(silent, 3),
                    clock_offset_ms=None if not st.offsets else min(st.offsets) / 1e6,
                    last_start_late_ms=None if st.late_ns is None else st.late_ns / 1e6,
                )
            )
        return out

    def _down_nodes(self) -> set[str]:
        """Nodes with a stream a recorder's active alert says is stalled or missing."""
        return {
            parts[3]
            for alerts in self._active.values()
            for a in alerts
            if a.code in _STREAM_DOWN and len(parts := a.subject.split("/")) > 3
        }

    @staticmethod
    def _device_out(device: str, d: _Device, mono: int, recording: bool, down: bool) -> DeviceOut:
        age = None if d.received_mono is None else _age(mono, d.received_mono)
        light: Light
        if down:
            light = "red"  # a recorder's stall alert on its stream: at once, not at its next report
        elif age is None:
            light = "grey"  # its node has not reported yet (it starts with the episode)
        elif age > HEALTH_STALE_S:
            light = "red" if recording else "grey"
        elif sum(d.dropped.values()) > 0 or not d.rate_hz:
            light = "amber"
        else:
            light = "green"
        return DeviceOut(
            id=device,
            light=light,
            rate_hz=d.rate_hz,
            received=d.received,
            published=d.published,
            dropped=dict(d.dropped),
            report_age_s=age,
        )

    def _streams_out(self, mono: int, recording: bool) -> list[StreamOut]:
        by_topic: dict[str, StreamOut] = {}
        # A recorder's stall alert goes out at once, its health report once a second: a stream it
        # names is stalled now, whatever the last report said.
        stalled = {
            (source, a.subject)
            for source, alerts in self._active.items()
            for a in alerts
            if a.code in _STREAM_DOWN
        }
        for source, health in sorted(self._health.items(), key=lambda kv: kv[1].received_mono):
            age = _age(mono, health.received_mono)
            stale = age > HEALTH_STALE_S
            for topic, s in health.streams.items():
                light: Light
                state = "stalled" if (source, topic) in stalled else s.state
                if stale:
                    light = "red" if recording else "grey"
                else:
                    light = "green" if state == "ok" else "red" if state == "stalled" else "amber"
                by_topic[topic] = StreamOut(
                    topic=topic,
                    source=source,
                    state=state,
                    light=light,
                    expected_hz=s.expected_hz,
                    measured_hz=s.measured_hz,
                    messages=s.messages,
                    drops=s.drops,
                    gaps=s.gaps,
                    max_gap_ms=s.max_gap_ms,
                    silent_ms=s.silent_ms,
                    latency_ms=s.latency_ms,
                    max_latency_ms=s.max_latency_ms,
                    report_age_s=age,
                )
        return [by_topic[t] for t in sorted(by_topic)]

    # --- bus handlers (on the bus thread) --------------------------------------------------------

    def _guard(self, handler: Callable[[Message], None]) -> Callable[[Message], None]:
        def guarded(message: Message) -> None:
            try:
                handler(message)
            except (WireError, ValueError, TypeError, KeyError, TelerigError) as exc:
                self._drop("malformed", message, str(exc))

        return guarded

    def _drop(self, reason: str, message: Message, why: str) -> None:
        with self._lock:
            if reason in self.dropped or len(self.dropped) < _MAX_DROP_REASONS:
                self.dropped[reason] = self.dropped.get(reason, 0) + 1
            self.last_drop = f"{message.topic[:200]}: {reason}: {why[:200]}"
        log.debug("dropped %s: %s: %s", message.topic, reason, why)

    def _json(self, message: Message, roles: tuple[NodeRole, ...]) -> tuple[str, dict[str, JsonValue]] | None:
        """The node and the JSON object of ``message`` from a node of one of ``roles``; ``None``
        (counted) when the node is not the rig's, the payload too large or not a JSON object."""
        _, _, _, node, stream = message.topic.split("/")
        spec = next((stream_spec(r, stream) for r in self._nodes.roles(node) if r in roles), None)
        if spec is None:
            self._drop("unknown_node", message, f"no {'/'.join(roles)} node {node!r} in rig {self.name!r}")
            return None
        if len(message.payload) > spec.max_bytes:
            self._drop("oversize", message, f"{len(message.payload)} bytes, over {spec.max_bytes}")
            return None
        with self._lock:
            self.received += 1
        return node, parse_json_object(message.payload, max_bytes=spec.max_bytes)

    def _on_health(self, message: Message) -> None:
        got = self._json(message, (NodeRole.RECORDER, NodeRole.DEVICE, NodeRole.ROBOT))
        if got is None:
            return
        node, doc = got
        if not _all_finite(doc):  # JSON has no NaN or Infinity; Python's parser lets them through
            raise WireError("a health report with a NaN or infinite number")
        mono = time.monotonic_ns()
        if node in self._robot_ids:
            latency = _Latency.of(doc)
            with self._changed:
                self._latency[node] = (latency, mono)
                self._changed.notify_all()
            return
        if node in self._devices:
            dropped = doc.get("dropped")
            drops: dict[str, int] = {}
            if isinstance(dropped, dict):
                for reason, n in list(dropped.items())[:_MAX_DROP_REASONS]:
                    if (count := _int(n)) is not None:
                        drops[reason[:_WORD]] = count
            with self._changed:
                d = self._devices[node]
                d.received_mono = mono
                d.rate_hz = _num(doc.get("rate_hz"))
                d.received = _int(doc.get("received"))
                d.published = _int(doc.get("published"))
                d.dropped = drops
                self._changed.notify_all()
            return
        streams = doc.get("streams")
        if not isinstance(streams, dict):
            raise WireError("a recorder health report without a 'streams' object")
        kept = {
            topic[:300]: _Stream.of(s)
            for topic, s in list(streams.items())[:_MAX_STREAMS_PER_SOURCE]
            if isinstance(s, dict) and topic.startswith(f"telerig/v1/{self.name}/")
        }
        with self._changed:
            if node not in self._health and len(self._health) >= _MAX_SOURCES:
                self._drop_locked("over_cap", message, f"more than {_MAX_SOURCES} health sources")
                return
            self._health[node] = _Health(mono, kept)
            self._changed.notify_all()
        if len(streams) > _MAX_STREAMS_PER_SOURCE:
            self._drop("over_cap", message, f"{len(streams)} streams, kept {_MAX_STREAMS_PER_SOURCE}")

    def _drop_locked(self, reason: str, message: Message, why: str) -> None:
        if reason in self.dropped or len(self.dropped) < _MAX_DROP_REASONS:
            self.dropped[reason] = self.dropped.get(reason, 0) + 1
        self.last_drop = f"{message.topic[:200]}: {reason}: {why[:200]}"

    def _on_status(self, message: Message) -> None:
        node = message.topic.split("/")[3]
        if node not in self._robot_ids:
            self._drop("unknown_node", message, f"no robot {node!r} in rig {self.name!r}")
            return
        if len(message.payload) > _WORD:
            self._drop("oversize", message, f"a status word of {len(message.payload)} bytes")
            return
        word = message.payload.decode("utf-8", errors="replace").strip()
        with self._changed:
            self.received += 1
            self._robots[node] = (word, time.monotonic_ns())
            self._changed.notify_all()

    def _on_latency(self, message: Message) -> None:
        got = self._json(message, (NodeRole.ROBOT,))
        if got is None:
            return
        node, doc = got
        if not _all_finite(doc):
            raise WireError("a latency report with a NaN or infinite number")
        stages = _Stages.of(doc)
        with self._changed:
            self._stages[node] = (stages, time.monotonic_ns())
            self._changed.notify_all()

    def _on_alerts(self, message: Message) -> None:
        got = self._json(message, (NodeRole.RECORDER, NodeRole.SAFETY, NodeRole.BROKER, NodeRole.ROBOT))
        if got is None:
            return
        node, doc = got
        now = time.time_ns()
        raw = doc.get("active_alerts")
        active: list[AlertOut] = []
        if isinstance(raw, list):
            active = [_alert(node, a, now) for a in raw[:_MAX_ACTIVE_PER_SOURCE] if isinstance(a, dict)]
            if len(active) < min(len(raw), _MAX_ACTIVE_PER_SOURCE):
                self._drop("malformed", message, "active_alerts holds entries that are not objects")
        event = None if doc.get("type") == "safety_alerts" else _alert(node, doc, now)
        with self._changed:
            if node not in self._active and len(self._active) >= _MAX_SOURCES:
                self._drop_locked("over_cap", message, f"more than {_MAX_SOURCES} alert sources")
                return
            if event is not None and event.code != "unknown":
                self._alerts.append(event)
                if not isinstance(raw, list):  # the broker's alerts: the document is the alert
                    active = [event] if event.active else []
            self._active[node] = [a for a in active if a.active]
            if not self._active[node]:
                del self._active[node]
            self._changed.notify_all()

    def _on_event(self, message: Message) -> None:
        got = self._json(message, (NodeRole.SAFETY, NodeRole.DEVICE))
        if got is None:
            return
        node, doc = got
        event = _alert(node, doc, time.time_ns())
        with self._changed:
            self._alerts.append(event)
            if event.code == "command_reply" and node in self._devices:
                count = self._replies.get(node, (0, ""))[0]
                self._replies[node] = (count + 1, event.reason)
            if event.code.startswith("calibration_") and node in self._devices:
                self._calibrations[node] = f"{event.code.removeprefix('calibration_')}: {event.reason}"
            self._changed.notify_all()

    def _on_session(self, message: Message) -> None:
        node = message.topic.split("/")[3]
        if node == COORDINATOR:
            got = self._json(message, (NodeRole.COORDINATOR,))
            if got is None:
                return
            status = SessionStatus.model_validate_json(message.payload)  # strict: enums from JSON text
            with self._changed:
                old = self._session
                if old is not None and old[0].session_id == status.session_id and status.seq < old[0].seq:
                    return  # an older copy (a retained one after a reconnect)
                self._session = (status, time.monotonic_ns())
                self._changed.notify_all()
            return
        got = self._json(message, (NodeRole.STATION,))
        if got is None:
            return
        late = _int(got[1].get("late_ns"))
        with self._changed:
            self._stations[got[0]].late_ns = late

    def _on_preview(self, message: Message) -> None:
        node = message.topic.split("/")[3]
        spec = (
            stream_spec(NodeRole.CAMERA, PREVIEW) if NodeRole.CAMERA in set(self._nodes.roles(node)) else None
        )
        if spec is None:
            self._drop("unknown_node", message, f"no camera {node!r} in rig {self.name!r}")
            return
        if len(message.payload) > spec.max_bytes:
            self._drop("oversize", message, f"{len(message.payload)} bytes, over {spec.max_bytes}")
            return
        if not message.payload.startswith(b"\xff\xd8\xff"):
            raise WireError("a preview that is not a JPEG")
        stamps = jpeg_stamps(message.payload)
        with self._changed:
            self.received += 1
            self._previews[node] = (message.payload, time.monotonic_ns())
            recent = self._preview_stamps.setdefault(node, deque(maxlen=_PREVIEW_STAMPS))
            if stamps is None:
                recent.clear()  # the latest preview has no stamps: nothing to measure it by
            else:
                recent.append((*stamps, time.time_ns()))

    def _on_ping(self, message: Message) -> None:
        got = self._json(message, (NodeRole.STATION,))
        if got is None:
            return
        with self._changed:
            self._stations[got[0]].last_ping_mono = time.monotonic_ns()
            self._changed.notify_all()

    def _on_pong(self, message: Message) -> None:
        got = self._json(message, (NodeRole.STATION,))
        if got is None:
            return
        t1, t2 = _int(got[1].get("t1")), _int(got[1].get("t2"))
        if t1 is None or t2 is None:
            raise WireError("a clock reply without integer t1 and t2")
        with self._changed:
            self._stations[got[0]].offsets.append(t2 - t1)


def jpeg_stamps(jpeg: bytes) -> tuple[int, int] | None:
    """``(capture_ns, encoded_ns)`` from a preview's comment segment (written by the camera node's
    :func:`telerig.cameras.preview.stamp_jpeg`), ``None`` when it has none or a malformed one."""
    if jpeg[2:4] != b"\xff\xfe" or len(jpeg) < 6:
        return None
    size = int.from_bytes(jpeg[4:6], "big")
    text = jpeg[6 : 4 + size]
    if not text.startswith(_STAMP_PREFIX) or len(text) > 80:
        return None
    fields = text[len(_STAMP_PREFIX) :].split(b" ")
    if len(fields) != 2 or not all(f.isdigit() and len(f) <= 19 for f in fields):
        return None
    capture, encoded = int(fields[0]), int(fields[1])
    return (capture, encoded) if 0 < capture <= encoded else None


_STAMP_PREFIX = b"telerig-stamps "


def _age(mono: int, at: int) -> float:
    return round((mono - at) / 1e9, 3)


def _silent_s(mono: int, at: int | None) -> float:
    return float("inf") if at is None else (mono - at) / 1e9


def _num(value: JsonValue) -> float | None:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return float(value) if abs(value) < 1e18 else None


def _all_finite(doc: JsonValue) -> bool:
    """Whether every number in ``doc`` is finite (walked without recursion; the parser bounded it)."""
    stack = [doc]
    while stack:
        value = stack.pop()
        if isinstance(value, float) and not math.isfinite(value):
            return False
        if isinstance(value, dict):
            stack.extend(value.values())
        elif isinstance(value, list):
            stack.extend(value)
    return True


def _ms_field(doc: Mapping[str, JsonValue], key: str) -> float | None:
    """A latency [ms] or window [s] of a report: absent or null is unknown; anything but a finite
    number within +-1e6 raises WireError (the report is counted and dropped)."""
    value = doc.get(key)
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float) or not abs(value) <= 1e6:
        raise WireError(f"{key} must be a finite number within +-1e6, got {str(value)[:40]}")
    return float(value)


def _int(value: JsonValue) -> int | None:
    return value if isinstance(value, int) and not isinstance(value, bool) else None


def _text(value: JsonValue, limit: int = _TEXT) -> str:
    if value is None:
        return ""
    return (value if isinstance(value, str) else str(value))[:limit]


def _alert(source: str, doc: Mapping[str, JsonValue], now_ns: int) -> AlertOut:
    """An alert from any publisher's JSON: the subject is its robot, stream or device."""
    subject = doc.get("robot") or doc.get("stream") or doc.get("device") or ""
    t = _int(doc.get("time_ns")) or _int(doc.get("since_ns")) or _int(doc.get("up_ns")) or now_ns
    active = doc.get("active")
    return AlertOut(
        t_ns=t,
        source=source,
        code=_text(doc.get("code"), _WORD) or "unknown",
        severity=_text(doc.get("severity"), _WORD) or "info",
        subject=_text(subject, 300),
        reason=_text(doc.get("reason")),
        suggested_action=_text(doc.get("suggested_action")),
        active=active if isinstance(active, bool) else True,
    )
