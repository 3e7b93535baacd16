"""Recorder node: writes every stream of a rig from the bus into the current episode's MCAP log."""

from __future__ import annotations

import json
import logging
import threading
from collections.abc import Callable, Collection
from pathlib import Path

from telerig.bus.base import Bus, Message
from telerig.bus.topics import Topic
from telerig.errors import WireError
from telerig.ir import wire
from telerig.record.align import CaptureTimes
from telerig.record.health import StreamHealthMonitor
from telerig.record.mcap_log import McapLog
from telerig.runtime.metrics import StreamMeter, StreamSummary
from telerig.runtime.session import JSON_STREAMS
from telerig.runtime.streams import PREVIEW, RESIDUAL

__all__ = ["Recorder"]

#: Streams whose payload is JSON (state, health, alerts, session control, clock sync), not an IR envelope.
_JSON_STREAMS = frozenset({"status", "alerts", "health", "motion_scale", "fixture", RESIDUAL}) | JSON_STREAMS

log = logging.getLogger(__name__)


class Recorder:
    """Records ``telerig/v1/<rig>/#`` at native rates while an episode is active.

    Each message keeps both times: MCAP ``publish_time`` is the sample's capture
    time, ``log_time`` the moment the recorder received it, both in the session clock
    (``to_session_ns``; payload stamps stay in the clock that made them, and the offset goes
    into the log's ``clock`` metadata). Malformed payloads are counted per topic and dropped.

    Args:
        rig: Rig name.
        bus: The recorder's own bus client.
        expected_rates: Expected rate [Hz] per topic, for the rate/drop summary.
        node: Node name of the recorder's health and alert streams (one per station).
        skip_nodes: Nodes not to record: those of other stations, which record their own.
        to_session_ns: Station clock → session (coordinator) clock [ns]; identity when ``None``
            (the station is the coordinator).
    """

    def __init__(
        self,
        rig: str,
        bus: Bus,
        expected_rates: dict[str, float],
        *,
        node: str = "recorder",
        skip_nodes: Collection[str] = (),
        to_session_ns: Callable[[int], int] | None = None,
    ) -> None:
        self.rig = rig
        self.bus = bus
        self._skip = frozenset(skip_nodes)
        self._to_session = to_session_ns
        self._expected = dict(expected_rates)
        self._lock = threading.Lock()
        self._log: McapLog | None = None
        self._meters: dict[str, StreamMeter] = {}
        self.malformed: dict[str, int] = {}
        self.health = StreamHealthMonitor(rig, node, bus, self._expected)
        self.health.watch_counter("recorder.inbox_overflow", lambda: bus.stats.inbox_overflow)
        self.health.watch_counter("recorder.publish_overflow", lambda: bus.stats.publish_overflow)
        self.capture_times = CaptureTimes()
        self._sub = bus.subscribe(Topic.pattern(rig, "+", "+"), self._on_message)

    def start(self, path: Path) -> None:
        """Begin a new episode log at ``path``."""
        with self._lock:
            if self._log is not None:
                raise RuntimeError("recorder is already recording; stop() first")
            self._meters = {t: StreamMeter(t, hz) for t, hz in self._expected.items()}
            self.malformed = {}
            self.capture_times = CaptureTimes()
            self._log = McapLog(path)
        # Health runs only while recording (devices are stopped between episodes, not stalled).
        self.health.start()

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """Write a named string map into the current episode's MCAP (e.g. the station clock estimate)."""
        with self._lock:
            if self._log is not None:
                self._log.add_metadata(name, data)

    def stop(self) -> list[StreamSummary]:
        """Close the current log (idempotent) and return per-stream rate and drop statistics."""
        self.health.stop()  # outside the lock: it publishes, and an in-memory bus delivers back here
        with self._lock:
            log_, self._log = self._log, None
        if log_ is not None:
            log_.close()
        return [m.summary() for m in self._meters.values()]

    def close(self) -> None:
        """Stop recording and unsubscribe. Idempotent."""
        self.stop()
        self._sub.cancel()

    def _on_message(self, message: Message) -> None:
        with self._lock:
            mcap = self._log
            if mcap is None:
                return
            if self._skip and message.topic.split("/", 4)[3] in self._skip:
                return
            received_ns = message.received_ns
            to_session = self._to_session
            if to_session is not None:
                received_ns = to_session(received_ns)
            try:
                sample = wire.decode(message.payload)
            except WireError:
                stream = Topic.parse(message.topic).stream
                if stream == PREVIEW:
                    return  # JPEG previews are for the dashboard; the MP4 has every frame
                if stream in _JSON_STREAMS or _is_json_object(message.payload):
                    # State and events of nodes (aids such as the motion scale, safety events) are JSON.
                    mcap.write_json(message.topic, message.payload, log_time_ns=received_ns)
                else:
                    self.malformed[message.topic] = self.malformed.get(message.topic, 0) + 1
                return
            stamp = sample.stamp
            mcap.write(
                message.topic,
                message.payload,
                log_time_ns=received_ns,
                publish_time_ns=stamp.capture_ns if to_session is None else to_session(stamp.capture_ns),
            )
            self.capture_times.add(message.topic, stamp.capture_ns)
            self.health.observe(
                message.topic, capture_ns=stamp.capture_ns, seq=stamp.seq, received_ns=message.received_ns
            )
            meter = self._meters.get(message.topic)
            if meter is None:
                meter = self._meters[message.topic] = StreamMeter(message.topic, 0.0)
            meter.add(stamp.capture_ns, stamp.seq)


def _is_json_object(payload: bytes) -> bool:
    """Whether ``payload`` is a JSON object (an IR envelope never starts with ``{``: field 15, group)."""
    if not payload.startswith(b"{"):
        return False
    try:
        return isinstance(json.loads(payload), dict)
    except ValueError:
        return False
