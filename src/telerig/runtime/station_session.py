"""A station's link to the session: the coordinator (on the rig's first station), the station agent,
and the operator commands (bus, CLI, web UI, controller buttons) that end the running episode."""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections.abc import Callable

from telerig.bus.base import Bus, Message
from telerig.bus.topics import Topic
from telerig.config.schema import EpisodeControlConfig, RigConfig, SessionCommand
from telerig.errors import BusError, SessionError, WireError
from telerig.ir import wire
from telerig.ir.types import ControllerState
from telerig.runtime.episode_control import EpisodeController
from telerig.runtime.session import Coordinator, Outcome, SessionState, SessionStatus, StationAgent

__all__ = ["ProgressCallback", "StationSession"]

log = logging.getLogger(__name__)

#: Called with (seconds elapsed, seconds total) while an episode runs; total is ``inf`` while a
#: following station records until the coordinator stops the episode.
ProgressCallback = Callable[[float, float], None]


class StationSession:
    """Follows the session on one station and turns operator commands into :class:`SessionCommand` values.

    The coordinating station also runs the :class:`Coordinator`. Commands end only the running
    episode; the ones that arrive between episodes are dropped (:meth:`begin_episode`).

    Args:
        config: The rig.
        station: This station's id.
        coordinating: Whether this station runs the coordinator.
    """

    def __init__(self, config: RigConfig, station: str, *, coordinating: bool) -> None:
        self._config = config
        self._station_id = station
        self.coordinating = coordinating
        self.coordinator: Coordinator | None = None
        self.station: StationAgent | None = None
        self.started = threading.Event()
        self._commands: queue.SimpleQueue[SessionCommand] = queue.SimpleQueue()
        self._running = False
        #: The operator's success/failure mark of the running episode.
        self.outcome: Outcome | None = None

    def start(self, bus: Bus) -> None:
        """Start the coordinator (if coordinating) and the station agent; wait for clock sync.

        Raises:
            BusError: no clock-sync reply from the coordinator within 5 s.
        """
        cfg = self._config
        if self.coordinating:
            self.coordinator = Coordinator(
                bus,
                cfg.name,
                lead_s=cfg.recording.start_lead_s,
                task=cfg.recording.task,
                operator=cfg.recording.operator,
                on_status=[self._on_status],
                devices=[d.id for d in cfg.devices],
            ).start()
            if cfg.episode_control is not None:
                self._listen_for_buttons(bus, cfg.episode_control)
        started = self.started
        self.station = StationAgent(
            bus,
            cfg.name,
            self._station_id,
            on_start=lambda status, report: started.set(),
            on_status=None if self.coordinating else self._on_status,
        ).start()
        if not self.station.sync.wait_synced(5.0):
            raise BusError("no clock-sync reply from the session coordinator within 5 s; is it running?")

    def agent(self) -> StationAgent:
        """The station agent; ``RuntimeError`` before :meth:`start`."""
        if self.station is None:
            raise RuntimeError("open() the runtime first")
        return self.station

    def to_session_ns(self, local_ns: int) -> int:
        """This station's clock → the coordinator's, by the current estimate [ns]."""
        station = self.station
        if station is None or not station.sync.sync.synced:
            return local_ns
        return station.sync.sync.to_coordinator(local_ns)

    def begin_episode(self) -> None:
        """Before an episode: forget commands and marks given between episodes."""
        while not self._commands.empty():  # presses between episodes do not end the next one
            self._commands.get_nowait()
        self.outcome = None

    def recording(self, running: bool) -> None:
        """Whether an episode records now (session commands end only a running episode)."""
        self._running = running

    def end_episode(self, *, discard: bool) -> None:
        """On the coordinator: move the session to stopped unless a command from elsewhere already did."""
        coordinator = self.coordinator
        if coordinator is None or coordinator.state in (SessionState.STOPPED, SessionState.IDLE):
            return
        try:
            coordinator.discard() if discard else coordinator.stop()
        except SessionError as exc:
            log.warning("session: %s", exc)

    def wait(self, duration_s: float | None, progress: ProgressCallback | None) -> SessionCommand | None:
        """Wait ``duration_s`` (None: no limit) or until a session command arrives; returns the command."""
        start = time.monotonic()
        total = math.inf if duration_s is None else duration_s
        while True:
            elapsed = time.monotonic() - start
            if progress is not None:
                progress(min(elapsed, total), total)
            if elapsed >= total:
                return None
            try:
                return self._commands.get(timeout=min(0.1, total - elapsed))
            except queue.Empty:
                continue

    def close(self) -> None:
        """Stop following the session (and coordinating it). Idempotent."""
        if self.station is not None:
            self.station.close()
        if self.coordinator is not None:
            self.coordinator.close()

    def _on_status(self, status: SessionStatus) -> None:
        """Commands from the CLI or web UI (on the coordinator's command topic) end the running episode:
        ``stop`` keeps it, ``discard`` throws it away, ``restart`` throws it away to record it again;
        only ``end`` ends the session."""
        if status.outcome is not None and self._running:
            self.outcome = status.outcome  # "mark success/failure" from a UI, the CLI or a button
        if not self._running or status.state is not SessionState.STOPPED:
            return
        if status.reason == "restart":
            self._commands.put(SessionCommand.RESTART_EPISODE)
        elif status.ended:
            self._commands.put(SessionCommand.END_SESSION)
        elif status.discarded:
            self._commands.put(SessionCommand.DISCARD_EPISODE)
        else:  # stop (or discard) ends the running episode only; the session goes on
            self._commands.put(SessionCommand.STOP_EPISODE)

    def _listen_for_buttons(self, bus: Bus, config: EpisodeControlConfig) -> None:
        """Turn controller button presses into session commands (seed 000: A end, B next, X redo, Y stop)."""
        controller = EpisodeController(config)
        commands = self._commands

        def on_message(message: Message) -> None:
            if not message.topic.endswith("_controller"):
                return
            try:
                sample = wire.decode(message.payload)
            except WireError:
                return  # the control node and recorder count malformed messages
            if isinstance(sample, ControllerState):
                command = controller.update(sample)
                if command is not None:
                    log.info("operator command: %s", command)
                    commands.put(command)

        bus.subscribe(Topic.pattern(self._config.name, config.device or "+"), on_message)
