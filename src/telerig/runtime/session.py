"""Session coordinator (state machine, synchronized start broadcast, episode commands) and station agents."""

from __future__ import annotations

import argparse
import json
import logging
import re
import secrets
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from enum import StrEnum
from types import TracebackType
from typing import TYPE_CHECKING, Literal, Self

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from telerig.bus.base import Bus, Inbox, Message, Subscription
from telerig.bus.catalogue import COMMAND, COORDINATOR, SESSION
from telerig.bus.topics import Topic, qos_for
from telerig.errors import BusError, SessionError, TelerigError
from telerig.ir.types import now_ns

if TYPE_CHECKING:
    from telerig.bus.mqtt import TlsOptions
from telerig.runtime.clock_sync import (
    Clock,
    ClockEstimate,
    ClockSyncClient,
    ClockSyncServer,
    offset_clock,
)
from telerig.safety.commands import parse_payload

__all__ = [
    "COMMAND",
    "COMMANDS",
    "COORDINATOR",
    "DEVICE_COMMANDS",
    "SESSION",
    "TRANSITIONS",
    "Coordinator",
    "CoordinatorStats",
    "EpisodeCommand",
    "SessionError",
    "SessionState",
    "SessionStatus",
    "StartReport",
    "StationAgent",
    "send_command",
    "wait_until",
]

log = logging.getLogger(__name__)

# From the catalogue: the coordinator's node name (COORDINATOR); its session state stream (SESSION,
# QoS 1, retained: .../coordinator/session; stations ack on .../<id>/session) and episode command
# stream (COMMAND: telerig/v1/<rig>/coordinator/command, JSON EpisodeCommand).

_NAME = r"^[A-Za-z0-9_.\-]+$"


class SessionState(StrEnum):
    """Where the session is.

    Attributes:
        IDLE: No episode; nothing records.
        ARMED: An episode is announced and starts at ``start_at_ns`` on every station.
        RECORDING: The episode records.
        PAUSED: The episode is open but nothing records.
        STOPPED: The episode ended (kept, or discarded when ``discarded``); the next may be armed.
    """

    IDLE = "idle"
    ARMED = "armed"
    RECORDING = "recording"
    PAUSED = "paused"
    STOPPED = "stopped"


S = SessionState
#: Allowed next states of every state; anything else raises :class:`SessionError`.
TRANSITIONS: Mapping[SessionState, frozenset[SessionState]] = {
    S.IDLE: frozenset({S.ARMED}),
    S.ARMED: frozenset({S.RECORDING, S.STOPPED}),
    S.RECORDING: frozenset({S.PAUSED, S.STOPPED}),
    S.PAUSED: frozenset({S.RECORDING, S.STOPPED}),
    S.STOPPED: frozenset({S.ARMED, S.IDLE}),
}

Outcome = Literal["success", "failure"]


class SessionStatus(BaseModel):
    """What the coordinator publishes (retained) on ``telerig/v1/<rig>/coordinator/session``.

    Attributes:
        rig: Rig name.
        state: Current state.
        session_id: Id of the session, ``ses-YYYYMMDD-HHMMSS-xxxx``.
        episode_id: Current (or last) episode, ``ep-YYYYMMDD-HHMMSS-xxxx`` (its start); ``None`` before one.
        task: Task label of the episode.
        operator: Operator id of the episode.
        start_at_ns: When the episode starts (armed) or started, coordinator clock [ns].
        reason: Why the state changed (the command, or e.g. ``"restart"``).
        outcome: Success/failure mark of the episode, if any.
        discarded: The episode that ended here must be thrown away (discard, restart).
        ended: The session ends with this stop (``end``): no episode follows.
        seq: Increases by one per publication in the session.
        stamp_ns: Coordinator clock when published [ns].
        paused_devices: Input devices paused on their own (seed 000: pause the affected device while
            the others go on; ``pause`` pauses the whole episode). Their robots hold their pose and
            re-anchor on resume (:class:`~telerig.runtime.control_node.ControlNode`); kept across
            episodes until ``resume_device``.
    """

    model_config = ConfigDict(frozen=True, extra="forbid", strict=True)

    rig: str
    state: SessionState
    session_id: str
    episode_id: str | None = None
    task: str | None = None
    operator: str | None = None
    start_at_ns: int | None = None
    reason: str | None = None
    outcome: Outcome | None = None
    discarded: bool = False
    ended: bool = False
    seq: int = 0
    stamp_ns: int = 0
    paused_devices: tuple[str, ...] = ()


#: The commands that pause or resume one input device (they need ``device``).
DEVICE_COMMANDS = frozenset({"pause_device", "resume_device"})


class EpisodeCommand(BaseModel):
    """A lifecycle command, as JSON on ``telerig/v1/<rig>/coordinator/command`` (CLI, web UI, controller).

    Examples: ``{"command": "start", "task": "pick cube", "operator": "op7"}``,
    ``{"command": "mark", "outcome": "success"}``, ``{"command": "discard", "reason": "dropped it"}``.

    Attributes:
        command: ``start`` (arm the next episode), ``stop`` (end it, kept), ``pause``, ``resume``,
            ``restart`` (discard the current episode and arm a new one), ``discard`` (end it, thrown away),
            ``mark`` (label the current or last episode with ``outcome``), ``end`` (stop and go idle),
            ``pause_device``/``resume_device`` (stop or restart one input device driving its robots;
            the rest of the rig goes on), in any state.
        device: The device of ``pause_device``/``resume_device`` (required there, allowed nowhere else).
        task: Task label (start, restart, mark); the previous one when omitted.
        operator: Operator id (start, restart, mark); the previous one when omitted.
        outcome: ``success`` or ``failure``; required by ``mark`` and only allowed there.
        reason: Free text kept in the session status.
        lead_s: Start lead for ``start``/``restart`` [s]; the coordinator's default when omitted.
        source: Who sent it, e.g. ``cli``, ``web``, ``controller`` (logged).
    """

    model_config = ConfigDict(frozen=True, extra="forbid", strict=True)

    command: Literal[
        "start",
        "stop",
        "pause",
        "resume",
        "restart",
        "discard",
        "mark",
        "end",
        "pause_device",
        "resume_device",
    ]
    device: str | None = Field(default=None, pattern=_NAME, max_length=64)
    task: str | None = Field(default=None, min_length=1, max_length=200)
    operator: str | None = Field(default=None, pattern=_NAME, max_length=64)
    outcome: Outcome | None = None
    reason: str | None = Field(default=None, max_length=500)
    lead_s: float | None = Field(default=None, ge=0, le=60)
    source: str | None = Field(default=None, max_length=64)

    @model_validator(mode="after")
    def _outcome_with_mark(self) -> Self:
        if (self.command == "mark") != (self.outcome is not None):
            raise ValueError("'outcome' (success or failure) is required by 'mark' and only allowed there")
        if (self.command in DEVICE_COMMANDS) != (self.device is not None):
            raise ValueError("'device' is required by pause_device/resume_device and only allowed there")
        return self


#: What each episode command does, as ``telerig session COMMAND --help`` says it.
COMMANDS: Mapping[str, str] = {
    "start": "arm the next episode (`telerig run` arms its episodes itself)",
    "stop": "end the running episode and keep it; the run goes on with the next episode",
    "discard": "end the running episode and throw it away (to incomplete/); the run goes on with the "
    "next episode, which takes its place in --episodes",
    "restart": "throw the running episode away and record it again at once",
    "pause": "pause the running episode",
    "resume": "resume a paused episode",
    "mark": "label the running (or last) episode a success or failure (--outcome)",
    "end": "end the session: the running episode is kept and `telerig run` ends the session and exits",
    "pause_device": "pause one input device (--device): its robots hold their pose, the rest goes on",
    "resume_device": "resume a paused input device (--device): its robots re-anchor where they are",
}


@dataclass(slots=True)
class CoordinatorStats:
    """Command counters: ``accepted``, ``malformed`` (dropped: not a valid :class:`EpisodeCommand`) and
    ``refused`` (valid but not allowed in the state then)."""

    accepted: int = 0
    malformed: int = 0
    refused: int = 0


def _new_id(prefix: str, t_ns: int) -> str:
    stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime(t_ns / 1e9))
    return f"{prefix}-{stamp}-{secrets.token_hex(2)}"


def wait_until(
    target_ns: int,
    now: Clock,
    *,
    cancel: threading.Event | None = None,
    spin_ns: int = 1_000_000,
    max_sleep_s: float = 0.1,
) -> bool:
    """Block until ``now() >= target_ns`` [ns]: coarse sleeps, then a spin over the last ``spin_ns``.

    ``now`` is re-read after every sleep (at most ``max_sleep_s`` [s]), so a clock estimate that
    improves while waiting moves the wake-up. The spin yields the GIL on every turn.

    Returns:
        ``True`` at the target, ``False`` if ``cancel`` was set first.
    """
    cancel = cancel if cancel is not None else threading.Event()
    while True:
        remaining = target_ns - now()
        if remaining <= spin_ns:
            break
        if cancel.wait(min((remaining - spin_ns) / 1e9, max_sleep_s)):
            return False
    while now() < target_ns:
        if cancel.is_set():
            return False
        time.sleep(0)
    return True


class Coordinator:
    """Runs the session state machine, publishes it retained, answers clock sync and obeys commands.

    Arming an episode sets ``start_at_ns = clock() + lead`` and publishes it, so every station can
    start at that instant of the coordinator clock; the coordinator itself turns ``recording`` at
    that instant (precise wait on a thread). Commands from the bus are validated; a malformed one
    is counted and dropped, one not allowed in the current state is counted, logged and refused.
    Every state change calls the ``on_status`` listeners (on the thread that made it).

    Args:
        bus: A connected bus.
        rig: Rig name.
        lead_s: Default delay between arming and the start [s] (>= 0).
        clock: Coordinator clock [ns]; the rig's common clock by default.
        session_id: Id of the session; generated when ``None``.
        task: Default task label.
        operator: Default operator id.
        serve_clock: Also answer the stations' clock sync pings.
        on_status: Listeners called with every new :class:`SessionStatus`.
        devices: The rig's input device ids: ``pause_device`` of any other is refused. ``None``
            (a coordinator without a rig) refuses every device command.
    """

    def __init__(
        self,
        bus: Bus,
        rig: str,
        *,
        lead_s: float = 5.0,
        clock: Clock = now_ns,
        session_id: str | None = None,
        task: str | None = None,
        operator: str | None = None,
        serve_clock: bool = True,
        on_status: Sequence[Callable[[SessionStatus], None]] = (),
        devices: Sequence[str] | None = None,
    ) -> None:
        if lead_s < 0:
            raise ValueError(f"lead_s must be >= 0, got {lead_s}")
        self._bus = bus
        self._rig = rig
        self._session_topic = str(Topic(rig, COORDINATOR, SESSION))
        self._command_topic = str(Topic(rig, COORDINATOR, COMMAND))
        self.lead_s = lead_s
        self._clock = clock
        self._listeners = list(on_status)
        self._devices = frozenset(devices or ())
        self._clock_server = ClockSyncServer(bus, rig, clock=clock) if serve_clock else None
        self._lock = threading.RLock()
        self._status = SessionStatus(
            rig=rig,
            state=SessionState.IDLE,
            session_id=session_id or _new_id("ses", clock()),
            task=task,
            operator=operator,
        )
        self._cancel_start = threading.Event()
        self._sub: Subscription | None = None
        self._started = False
        self.stats = CoordinatorStats()
        #: The message of the last refused command, for a UI to show.
        self.last_refusal: str | None = None

    @property
    def status(self) -> SessionStatus:
        """The current session status."""
        return self._status

    @property
    def state(self) -> SessionState:
        """The current state."""
        return self._status.state

    def start(self) -> Coordinator:
        """Publish the idle state, answer clock pings and listen for commands. Returns ``self``."""
        with self._lock:
            if self._started:
                return self
            self._started = True
            if self._clock_server is not None:
                self._clock_server.start()
            self._sub = self._bus.subscribe(self._command_topic, self._on_command, qos=1)
            self._publish(self._status)
        return self

    def close(self) -> None:
        """Stop listening and cancel a pending start; the last status stays retained. Idempotent."""
        self._cancel_start.set()
        if self._sub is not None:
            self._sub.cancel()
            self._sub = None
        if self._clock_server is not None:
            self._clock_server.close()

    def __enter__(self) -> Coordinator:
        return self.start()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    # Lifecycle commands (also reachable from the bus through EpisodeCommand).

    def arm(
        self, *, task: str | None = None, operator: str | None = None, lead_s: float | None = None
    ) -> SessionStatus:
        """Announce the next episode, starting ``lead_s`` [s] from now on every station."""
        with self._lock:
            self._check("start", SessionState.ARMED)
            start_at = self._clock() + round((self.lead_s if lead_s is None else lead_s) * 1e9)
            status = self._change(
                SessionState.ARMED,
                episode_id=_new_id("ep", start_at),
                task=task or self._status.task,
                operator=operator or self._status.operator,
                start_at_ns=start_at,
                reason="start",
                outcome=None,
                discarded=False,
                ended=False,
            )
            self._cancel_start.set()
            self._cancel_start = cancel = threading.Event()
            threading.Thread(
                target=self._go_recording, args=(status.episode_id, start_at, cancel), daemon=True
            ).start()
            return status

    def stop(self, reason: str = "stop") -> SessionStatus:
        """End the episode and keep it."""
        with self._lock:
            self._check("stop", SessionState.STOPPED)
            self._cancel_start.set()
            return self._change(SessionState.STOPPED, reason=reason, discarded=False)

    def discard(self, reason: str = "discard") -> SessionStatus:
        """End the episode and throw it away."""
        with self._lock:
            self._check("discard", SessionState.STOPPED)
            self._cancel_start.set()
            return self._change(SessionState.STOPPED, reason=reason, discarded=True)

    def pause(self, reason: str = "pause") -> SessionStatus:
        """Pause the recording episode."""
        with self._lock:
            self._check("pause", SessionState.PAUSED)
            return self._change(SessionState.PAUSED, reason=reason)

    def resume(self, reason: str = "resume") -> SessionStatus:
        """Resume a paused episode."""
        with self._lock:
            if self._status.state is not SessionState.PAUSED:
                raise SessionError(
                    f"cannot resume in state {self._status.state}: only a paused episode resumes"
                )
            return self._change(SessionState.RECORDING, reason=reason)

    def restart(
        self, *, task: str | None = None, operator: str | None = None, lead_s: float | None = None
    ) -> SessionStatus:
        """Discard the current episode (armed, recording or paused) and arm a new one."""
        with self._lock:
            if self._status.state not in (SessionState.ARMED, SessionState.RECORDING, SessionState.PAUSED):
                raise SessionError(
                    f"cannot restart in state {self._status.state}: restart needs an armed, recording "
                    "or paused episode; use start"
                )
            self.discard("restart")
            return self.arm(task=task, operator=operator, lead_s=lead_s)

    def mark(
        self, outcome: Outcome, *, task: str | None = None, operator: str | None = None
    ) -> SessionStatus:
        """Mark the current (or last) episode a success or failure, optionally fixing its task/operator."""
        with self._lock:
            if self._status.episode_id is None:
                raise SessionError("cannot mark an outcome: no episode yet; start one first")
            return self._change(
                self._status.state,
                outcome=outcome,
                task=task or self._status.task,
                operator=operator or self._status.operator,
                reason=f"mark {outcome}",
            )

    def pause_device(self, device: str, reason: str | None = None) -> SessionStatus:
        """Pause one input device in any state: its robots hold their pose, the rest of the rig goes on."""
        with self._lock:
            paused = self._device_check("pause", device)
            if device in paused:
                raise SessionError(f"device {device!r} is already paused; resume_device resumes it")
            return self._change(
                self._status.state,
                paused_devices=tuple(sorted({*paused, device})),
                reason=reason or f"pause_device {device}",
            )

    def resume_device(self, device: str, reason: str | None = None) -> SessionStatus:
        """Resume a paused input device: its robots re-anchor where they are and follow it again."""
        with self._lock:
            paused = self._device_check("resume", device)
            if device not in paused:
                raise SessionError(f"device {device!r} is not paused (paused: {', '.join(paused) or 'none'})")
            return self._change(
                self._status.state,
                paused_devices=tuple(d for d in paused if d != device),
                reason=reason or f"resume_device {device}",
            )

    def _device_check(self, what: str, device: str) -> tuple[str, ...]:
        if device not in self._devices:
            valid = ", ".join(sorted(self._devices)) or "none (no rig given to the coordinator)"
            raise SessionError(
                f"cannot {what} device {device!r}: not an input device of the rig; valid: {valid}"
            )
        return self._status.paused_devices

    def end(self, reason: str = "end") -> SessionStatus:
        """Stop the episode if one is open (kept), then go idle."""
        with self._lock:
            if self._status.state in (SessionState.ARMED, SessionState.RECORDING, SessionState.PAUSED):
                self._check("end", SessionState.STOPPED)
                self._cancel_start.set()
                self._change(SessionState.STOPPED, reason=reason, discarded=False, ended=True)
            self._check("end", SessionState.IDLE)
            return self._change(SessionState.IDLE, reason=reason)

    def handle(self, command: EpisodeCommand) -> SessionStatus:
        """Apply one command.

        Raises:
            SessionError: The command is not allowed in the current state.
        """
        c = command
        match c.command:
            case "start":
                return self.arm(task=c.task, operator=c.operator, lead_s=c.lead_s)
            case "restart":
                return self.restart(task=c.task, operator=c.operator, lead_s=c.lead_s)
            case "mark":
                assert c.outcome is not None  # checked by the model
                return self.mark(c.outcome, task=c.task, operator=c.operator)
            case "stop":
                return self.stop(c.reason or "stop")
            case "discard":
                return self.discard(c.reason or "discard")
            case "pause":
                return self.pause(c.reason or "pause")
            case "resume":
                return self.resume(c.reason or "resume")
            case "end":
                return self.end(c.reason or "end")
            case "pause_device" | "resume_device":
                assert c.device is not None  # checked by the model
                act = self.pause_device if c.command == "pause_device" else self.resume_device
                return act(c.device, c.reason)

    # Internals.

    def _check(self, command: str, target: SessionState) -> None:
        state = self._status.state
        allowed = TRANSITIONS[state]
        if target not in allowed:
            names = ", ".join(sorted(allowed))
            raise SessionError(
                f"cannot {command} in state {state} (-> {target}); from {state} the allowed next states are: "
                f"{names}"
            )

    def _change(self, state: SessionState, **changes: object) -> SessionStatus:
        old = self._status
        if state is not old.state and state not in TRANSITIONS[old.state]:  # internal misuse guard
            raise SessionError(f"invalid session transition {old.state} -> {state}")
        status = old.model_copy(
            update={"state": state, "seq": old.seq + 1, "stamp_ns": self._clock(), **changes}
        )
        self._status = status
        self._publish(status)
        log.info(
            "%s: session %s episode %s -> %s (%s)",
            COORDINATOR,
            status.session_id,
            status.episode_id,
            state,
            status.reason,
        )
        for listener in self._listeners:
            try:
                listener(status)
            except Exception:
                log.exception("%s: session listener failed", COORDINATOR)
        return status

    def _publish(self, status: SessionStatus) -> None:
        if self._started:
            qos, retain = qos_for(SESSION)
            self._bus.publish(self._session_topic, status.model_dump_json().encode(), qos=qos, retain=retain)

    def _go_recording(self, episode_id: str | None, start_at_ns: int, cancel: threading.Event) -> None:
        if not wait_until(start_at_ns, self._clock, cancel=cancel):
            return
        with self._lock:
            if cancel.is_set() or self._status.episode_id != episode_id:
                return
            if self._status.state is SessionState.ARMED:
                self._change(SessionState.RECORDING, reason="start_at")

    def _on_command(self, message: Message) -> None:
        command = parse_payload(EpisodeCommand, message)
        if isinstance(command, str):
            self.stats.malformed += 1
            log.warning("%s: dropped a malformed command on %s: %s", COORDINATOR, message.topic, command)
            return
        try:
            self.handle(command)
        except SessionError as exc:
            self.stats.refused += 1
            self.last_refusal = str(exc)
            log.warning("%s: refused %s from %s: %s", COORDINATOR, command.command, command.source, exc)
            return
        self.stats.accepted += 1


@dataclass(frozen=True, slots=True)
class StartReport:
    """When a station started an episode, published retained on ``telerig/v1/<rig>/<station>/session``.

    Attributes:
        station: Station id.
        episode_id: The episode started.
        start_at_ns: The requested start, coordinator clock [ns].
        started_local_ns: When the start callback was entered, station clock [ns].
        started_ns: The same instant in the coordinator clock, by the station's estimate [ns].
        late_ns: ``started_ns - start_at_ns`` [ns]: the wake-up error, or how late a late joiner was.
        clock: The clock estimate at the start (:meth:`ClockEstimate.as_dict`).
    """

    station: str
    episode_id: str
    start_at_ns: int
    started_local_ns: int
    started_ns: int
    late_ns: int
    clock: dict[str, int | float | bool] = field(default_factory=dict)

    def as_dict(self) -> dict[str, object]:
        """JSON values."""
        return {
            "station": self.station,
            "episode_id": self.episode_id,
            "start_at_ns": self.start_at_ns,
            "started_local_ns": self.started_local_ns,
            "started_ns": self.started_ns,
            "late_ns": self.late_ns,
            "clock": self.clock,
        }


class StationAgent:
    """A station's view of the session: keeps its clock synced and starts episodes at ``start_at_ns``.

    Session updates are handled on the agent's thread (``on_status`` runs there; it must return
    quickly). When an episode is armed, a waiter thread sleeps until ``start_at_ns`` in the
    coordinator clock (station clock corrected by :class:`ClockSyncClient`, re-read while
    waiting), spins the last ``spin_ns``, then calls ``on_start`` and publishes a
    :class:`StartReport`. A stop or discard before the start cancels it. A station joining while an
    episode records starts at once (``late_ns`` says how late).

    Args:
        bus: A connected bus.
        rig: Rig name.
        station: Station id (node name on the bus).
        clock: The station clock [ns].
        on_start: Called at the start with the status and the report.
        on_status: Called with every session update.
        spin_ns: Busy-wait at the end of the start wait [ns].
        sync: The clock sync client; one on ``clock`` with default rates when ``None``.
    """

    def __init__(
        self,
        bus: Bus,
        rig: str,
        station: str,
        *,
        clock: Clock = now_ns,
        on_start: Callable[[SessionStatus, StartReport], None] | None = None,
        on_status: Callable[[SessionStatus], None] | None = None,
        spin_ns: int = 1_000_000,
        sync: ClockSyncClient | None = None,
    ) -> None:
        self._bus = bus
        self.station = station
        self._session_topic = str(Topic(rig, COORDINATOR, SESSION))
        self._ack_topic = str(Topic(rig, station, SESSION))
        self.clock = clock
        self.sync = sync if sync is not None else ClockSyncClient(bus, rig, station, clock=clock)
        self._on_start = on_start
        self._on_status = on_status
        self.spin_ns = spin_ns
        self._inbox = Inbox(maxlen=256)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._sub: Subscription | None = None
        self._armed_episode: str | None = None
        self._cancel = threading.Event()
        self._waiters: list[threading.Thread] = []
        #: The latest session status seen, and start reports of this agent (oldest first).
        self.status: SessionStatus | None = None
        self.reports: list[StartReport] = []
        #: Session messages dropped as malformed.
        self.malformed = 0

    @property
    def estimate(self) -> ClockEstimate:
        """The station's current clock estimate."""
        return self.sync.estimate

    def clock_record(self) -> dict[str, int | float | bool | str]:
        """The clock estimate for the manifest and MCAP metadata (:meth:`ClockSyncClient.record`)."""
        return self.sync.record()

    def coordinator_now(self) -> int:
        """Now in the coordinator clock by the current estimate (raw before the first exchange) [ns]."""
        local = self.clock()
        return self.sync.sync.to_coordinator(local) if self.sync.sync.synced else local

    def start(self) -> StationAgent:
        """Start clock sync and follow the session. Returns ``self``."""
        if self._thread is None:
            self.sync.start()
            self._thread = threading.Thread(target=self._run, name=f"station-{self.station}", daemon=True)
            self._thread.start()
            self._sub = self._bus.subscribe(self._session_topic, self._inbox, qos=1)
        return self

    def close(self) -> None:
        """Stop following the session, cancel a pending start, stop clock sync. Idempotent."""
        self._stop.set()
        self._cancel.set()
        if self._sub is not None:
            self._sub.cancel()
            self._sub = None
        if self._thread is not None:
            self._thread.join()
        for waiter in self._waiters:
            waiter.join()
        self.sync.close()

    def __enter__(self) -> StationAgent:
        return self.start()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def _run(self) -> None:
        while not self._stop.is_set():
            message = self._inbox.get(timeout=0.1)
            if message is None:
                continue
            status = parse_payload(SessionStatus, message)
            if isinstance(status, str):
                self.malformed += 1
                log.warning("%s: dropped a malformed session message: %s", self.station, status)
                continue
            self._follow(status)

    def _follow(self, status: SessionStatus) -> None:
        previous = self.status
        if previous is not None and previous.session_id == status.session_id and status.seq < previous.seq:
            return  # an older retained copy after a reconnect
        self.status = status
        episode = status.episode_id
        if status.state in (SessionState.ARMED, SessionState.RECORDING) and episode != self._armed_episode:
            if episode is not None and status.start_at_ns is not None:
                self._armed_episode = episode
                self._cancel.set()
                self._cancel = cancel = threading.Event()
                waiter = threading.Thread(
                    target=self._wait_and_start, args=(status, cancel), name=f"start-{episode}", daemon=True
                )
                self._waiters = [w for w in self._waiters if w.is_alive()]
                self._waiters.append(waiter)
                waiter.start()
        elif status.state in (SessionState.STOPPED, SessionState.IDLE) and episode == self._armed_episode:
            self._cancel.set()  # a start still pending for this episode is off
        if self._on_status is not None:
            try:
                self._on_status(status)
            except Exception:
                log.exception("%s: on_status failed", self.station)

    def _wait_and_start(self, status: SessionStatus, cancel: threading.Event) -> None:
        assert status.start_at_ns is not None
        assert status.episode_id is not None
        if not self.sync.sync.synced:
            log.warning("%s: waiting for the start with no clock sync yet", self.station)
        if not wait_until(status.start_at_ns, self.coordinator_now, cancel=cancel, spin_ns=self.spin_ns):
            return
        local = self.clock()
        started = self.sync.sync.to_coordinator(local) if self.sync.sync.synced else local
        report = StartReport(
            station=self.station,
            episode_id=status.episode_id,
            start_at_ns=status.start_at_ns,
            started_local_ns=local,
            started_ns=started,
            late_ns=started - status.start_at_ns,
            clock=self.sync.estimate.as_dict(),
        )
        self.reports.append(report)
        if self._on_start is not None:
            try:
                self._on_start(status, report)
            except Exception:
                log.exception("%s: on_start failed", self.station)
        qos, retain = qos_for(SESSION)
        self._bus.publish(self._ack_topic, json.dumps(report.as_dict()).encode(), qos=qos, retain=retain)


# Command line: station and command publisher (the two-station test and demos run these).


def _station_main(args: argparse.Namespace) -> int:
    from telerig.bus.mqtt import MqttBus

    fake_ns = round(args.fake_offset_ms * 1e6)
    clock = offset_clock(fake_ns) if fake_ns else now_ns
    done = threading.Event()
    started = 0

    def emit(event: str, **data: object) -> None:
        print(json.dumps({"event": event, "station": args.id, **data}), flush=True)

    def on_start(status: SessionStatus, report: StartReport) -> None:
        nonlocal started
        # The host clock is the coordinator's on one machine: the truth the fake clock hides.
        true_ns = now_ns()
        started += 1
        emit("started", true_start_ns=true_ns, fake_offset_ns=fake_ns, **report.as_dict())
        if started >= args.episodes:
            done.set()

    with MqttBus(args.url, client_id=f"station-{args.id}") as bus:
        sync = ClockSyncClient(bus, args.rig, args.id, clock=clock, rate_hz=args.rate_hz, burst=args.burst)
        with StationAgent(bus, args.rig, args.id, clock=clock, on_start=on_start, sync=sync) as agent:
            if not sync.wait_synced(args.timeout_s):
                emit("error", message="no clock sync answer; is a coordinator running on this rig?")
                return 1
            time.sleep(args.settle_s)
            emit("synced", fake_offset_ns=fake_ns, clock=agent.clock_record())
            ok = done.wait(args.timeout_s)
            emit("exit", clock=agent.clock_record())
            return 0 if ok else 1


def send_command(url: str, rig: str, command: EpisodeCommand, *, tls: TlsOptions | None = None) -> None:
    """Publish one episode command to the coordinator of ``rig`` through the broker at ``url``.

    Raises:
        SessionError: The broker cannot be reached; one line naming the URL and the fix.
    """
    from telerig.bus.mqtt import MqttBus

    try:
        bus = MqttBus(url, client_id=f"cli-{secrets.token_hex(3)}", tls=tls).connect()
    except BusError as exc:
        where = url.rsplit("@", 1)[-1]  # never echo a password
        where = where if "://" in where else f"{url.split('://', 1)[0]}://{where}"
        reason = re.search(r"\(([^()]*)\)", str(exc))
        raise SessionError(
            f"cannot reach the rig's broker at {where}"
            + (f" ({reason.group(1)})" if reason else "")
            + ": is `telerig run` running? Give the broker URL it printed with --url"
        ) from None
    with bus:
        bus.publish(str(Topic(rig, COORDINATOR, COMMAND)), command.model_dump_json().encode(), qos=1)
        time.sleep(0.2)  # let the QoS 1 publish leave before disconnecting


def _command_main(args: argparse.Namespace) -> int:

    fields = {
        "command": args.command,
        "task": args.task,
        "operator": args.operator,
        "outcome": args.outcome,
        "reason": args.reason,
        "lead_s": args.lead_s,
        "device": args.device,
        "source": "cli",
    }
    try:
        command = EpisodeCommand.model_validate({k: v for k, v in fields.items() if v is not None})
    except ValidationError as exc:
        print(f"error: {exc.errors()[0]['msg']}", file=sys.stderr)
        return 2
    send_command(args.url, args.rig, command)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m telerig.runtime.session station|command ...``; returns the exit status."""
    parser = argparse.ArgumentParser(prog="python -m telerig.runtime.session", description=__doc__)
    sub = parser.add_subparsers(dest="mode", required=True)
    st = sub.add_parser("station", help="follow the session; print JSON lines when synced and started")
    st.add_argument("--url", required=True, help="mqtt://host:port")
    st.add_argument("--rig", default="demo")
    st.add_argument("--id", required=True, help="station id")
    st.add_argument("--fake-offset-ms", type=float, default=0.0, help="shift this station's clock [ms]")
    st.add_argument("--rate-hz", type=float, default=2.0, help="clock sync exchanges per second")
    st.add_argument("--burst", type=int, default=8, help="clock sync exchanges at start")
    st.add_argument("--settle-s", type=float, default=0.3, help="sync time before reporting 'synced' [s]")
    st.add_argument("--episodes", type=int, default=1, help="exit after starting this many episodes")
    st.add_argument("--timeout-s", type=float, default=30.0)
    cm = sub.add_parser("command", help="publish one episode command")
    cm.add_argument("command", choices=list(COMMANDS))
    cm.add_argument("--url", required=True)
    cm.add_argument("--rig", default="demo")
    cm.add_argument("--task")
    cm.add_argument("--operator")
    cm.add_argument("--outcome", choices=["success", "failure"])
    cm.add_argument("--reason")
    cm.add_argument("--lead-s", type=float)
    cm.add_argument("--device", help="input device of pause_device/resume_device")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(name)s: %(message)s")
    try:
        return _station_main(args) if args.mode == "station" else _command_main(args)
    except TelerigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
