"""Recorder node: writes the rig's catalogued streams from the bus into the episode's MCAP log.

A message is recorded only when a node of the rig publishes it on a stream the catalogue
(:mod:`telerig.bus.catalogue`) gives that node's role, decoded by the stream's payload kind,
within the stream's size limit and with a plausible stamp. Everything else goes to the
``rejected`` channel (topic, size, reason and at most :data:`REJECTED_HEAD_BYTES` of the
payload), is counted per reason, and is logged once per reason every few seconds.

The bus delivery thread only queues each message; the recorder's writer thread checks and writes
it, below the control loops (``priority.enter("work")``). In a station under ``SCHED_RR`` the
delivery thread keeps the robots' priority and keeps draining the broker, while
the recording work (decode, checks, MCAP, ~40 us a message) no longer counts as real-time load.
On the fleet rig (2 cores) that load was ~0.4 cores of the ~1.7 the real-time threads took; near
the whole machine, the kernel then stopped every real-time thread on a CPU for ~50 ms to run
ordinary tasks (benchmarks/rt_blackout.py), and the robots missed ticks in those stops (benchmarks/fleet.py).
With the writer below them (7 alternating pairs of 20 s fleet runs): 0-19 missed ticks per run and
a blackout in 1 run, the worst robot's p99 latency 5.2-12.3 ms; before, 0-319 missed, blackouts in 4
runs, p99 up to 83 ms.
:meth:`Recorder.stop` writes whatever is still queued before it closes the log: nothing received
during an episode is lost to a writer that ran behind. The queue holds at most
:data:`MAX_QUEUED` messages and :data:`MAX_QUEUED_BYTES` of payload; beyond that a message is
dropped and counted (``recorder.queue_overflow`` in the health report).
"""

from __future__ import annotations

import base64
import json
import logging
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Collection
from pathlib import Path

from telerig import priority
from telerig.bus.base import Bus, Message
from telerig.bus.catalogue import PayloadKind, RigNodes, StreamSpec, bundled, device_stream, spec_by_name
from telerig.bus.jsonpayload import parse_json_object
from telerig.bus.metrics import StreamMeter, StreamSummary
from telerig.bus.topics import Topic
from telerig.errors import RecordingError, WireError
from telerig.ir import wire
from telerig.ir.mcap_log import McapLog
from telerig.ir.types import Sample
from telerig.record.align import CaptureTimes
from telerig.record.health import StreamHealthMonitor

__all__ = [
    "BEFORE_START_SLACK_S",
    "MAX_QUEUED",
    "MAX_QUEUED_BYTES",
    "REJECTED",
    "REJECTED_HEAD_BYTES",
    "REJECT_REASONS",
    "Recorder",
]

log = logging.getLogger(__name__)

#: Stream of the recorder node under which the MCAP's rejected channel is written (JSON
#: ``{"topic", "size", "reason", "detail", "head_b64"}``, one per refused message).
REJECTED = "rejected"
#: Bytes of a refused payload kept in the rejected channel (base64), enough to tell what it was.
REJECTED_HEAD_BYTES = 256
#: Why a message was refused:
#: ``bad_topic`` not a telerig topic; ``unknown_stream`` no node of the rig publishes this stream;
#: ``oversized`` over the stream's size limit; ``malformed`` not the stream's payload kind (not an
#: IR envelope, not a JSON object, not text); ``wrong_type`` an IR type the stream does not carry;
#: ``wrong_stream`` a device sample on another part's stream; ``wrong_source`` a sample whose
#: source is not the node that alone makes it; ``negative_time`` a negative stamp;
#: ``future_stamp`` / ``stale_stamp`` captured far after / before it was received;
#: ``replayed`` a sequence number and capture time not newer than the source's last.
REJECT_REASONS = (
    "bad_topic",
    "unknown_stream",
    "oversized",
    "malformed",
    "wrong_type",
    "wrong_stream",
    "wrong_source",
    "negative_time",
    "future_stamp",
    "stale_stamp",
    "replayed",
)
#: Defaults of the plausible-stamp window around the receive time [s]. Clocks of one station agree
#: to well under a second (device clocks are mapped to it); the bus delivers in milliseconds.
DEFAULT_MAX_FUTURE_S = 10.0
DEFAULT_MAX_AGE_S = 60.0
#: How long before an episode's start a sample may have been captured and still be recorded in it [s]
#: (see :meth:`Recorder.start`).
BEFORE_START_SLACK_S = 1.0
_BEFORE_START_SLACK_NS = round(BEFORE_START_SLACK_S * 1e9)
#: Sources remembered for replay checks; the oldest is forgotten beyond this (forged source ids).
_MAX_SOURCES = 4096
#: Least time between two log lines of one reject reason [s].
_LOG_INTERVAL_S = 5.0
#: Most messages received and not yet written (the writer thread runs behind): ~25 s of the fleet
#: rig's 3 900 messages a second. Beyond it, or beyond :data:`MAX_QUEUED_BYTES` of payload, a message
#: is dropped and counted (``queue_overflow``).
MAX_QUEUED = 100_000
#: Most payload bytes received and not yet written (a stream may carry up to 4 MiB a message).
MAX_QUEUED_BYTES = 256 << 20
#: Messages the writer thread writes per hold of the recorder's lock (~0.7 ms), which
#: :meth:`Recorder.stop` and :meth:`Recorder.newest` take too.
_WRITE_BATCH = 16


class _RejectedError(Exception):
    """A refused message: ``reason`` (one of :data:`REJECT_REASONS`) and a one-line detail."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(detail)
        self.reason = reason
        self.detail = detail


class Recorder:
    """Records the rig's streams at native rates while an episode is active.

    Each message keeps both times: MCAP ``publish_time`` is the sample's capture
    time, ``log_time`` the moment the recorder received it, both in the session clock
    (``to_session_ns``; payload stamps stay in the clock that made them, and the offset goes
    into the log's ``clock`` metadata). Refused messages are counted per reason
    (:attr:`rejected`), per topic (:attr:`malformed`) and in the topic's :class:`StreamSummary`.

    Args:
        rig: Rig name.
        bus: The recorder's own bus client.
        expected_rates: Expected rate [Hz] per topic, for the rate/drop summary.
        node: Node name of the recorder's health and alert streams (one per station).
        skip_nodes: Nodes not to record: those of other stations, which record their own.
        to_session_ns: Station clock → session (coordinator) clock [ns]; identity when ``None``
            (the station is the coordinator).
        nodes: The rig's nodes by role; a stream is recorded only from a node whose role
            publishes it. ``None`` (tests, tools): the role is taken from the stream name.
        max_future_s: Latest accepted capture time after the receive time [s].
        max_age_s: Earliest accepted capture time before the receive time [s].
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
        nodes: RigNodes | None = None,
        max_future_s: float = DEFAULT_MAX_FUTURE_S,
        max_age_s: float = DEFAULT_MAX_AGE_S,
    ) -> None:
        if not (max_future_s > 0 and max_age_s > 0):
            raise ValueError(f"max_future_s and max_age_s must be > 0 s, got {max_future_s}, {max_age_s}")
        self.rig = rig
        self.bus = bus
        self._skip = frozenset(skip_nodes)
        self._to_session = to_session_ns
        self._expected = dict(expected_rates)
        self._nodes = nodes
        self._max_future_ns = round(max_future_s * 1e9)
        self._max_age_ns = round(max_age_s * 1e9)
        self._rejected_topic = str(Topic(rig, node, REJECTED))
        self._lock = threading.Lock()
        self._log: McapLog | None = None
        self._meters: dict[str, StreamMeter] = {}
        self._specs: dict[str, StreamSpec | None] = {}
        self._last: OrderedDict[tuple[str, str], tuple[int, int]] = OrderedDict()
        self._logged_at: dict[str, float] = {}
        self._unlogged: dict[str, int] = {}
        #: Refused messages of the current episode per topic (the manifest's ``malformed_messages``).
        self.malformed: dict[str, int] = {}
        #: Refused messages of the current episode per reason (see :data:`REJECT_REASONS`).
        self.rejected: dict[str, int] = {}
        #: Samples of the current episode's streams captured before it started (see :meth:`start`).
        self.before_start = 0
        self._since_ns: int | None = None
        #: The first write failure of the episode (disk full, I/O error); the log stops there and
        #: the runtime ends the episode as incomplete with it. ``None`` while writing works.
        self.write_error: str | None = None
        self.health = StreamHealthMonitor(rig, node, bus, self._expected)
        self.health.watch_counter("recorder.inbox_overflow", lambda: bus.stats.inbox_overflow)
        self.health.watch_counter("recorder.publish_overflow", lambda: bus.stats.publish_overflow)
        #: Messages dropped because the writer thread's queue was full (:data:`MAX_QUEUED`,
        #: :data:`MAX_QUEUED_BYTES`), over all episodes.
        self.queue_overflow = 0
        #: Messages left out because writing them raised something unexpected (a bug; logged once).
        self.write_bugs = 0
        self.health.watch_counter("recorder.queue_overflow", lambda: self.queue_overflow)
        self.health.watch_backlog(self._oldest_queued_ns)
        self.capture_times = CaptureTimes()
        self._queue: deque[Message] = deque()
        # Payload bytes queued = in - out; each counter has one writer (the delivery thread; the
        # thread that holds the lock), so neither needs a lock of its own.
        self._bytes_in = 0
        self._bytes_out = 0
        self._queued = threading.Event()
        self._closed = False
        self._writer = threading.Thread(target=self._write_loop, name="recorder-writer", daemon=True)
        self._writer.start()
        self._sub = bus.subscribe(Topic.pattern(rig, "+", "+"), self._on_message)

    def start(self, path: Path, *, since_ns: int | None = None) -> None:
        """Begin a new episode log at ``path``.

        ``since_ns``: the episode's start [ns, common clock]. A sample captured more than
        :data:`BEFORE_START_SLACK_S` before it belongs to an earlier time: it is left out and counted
        in :attr:`before_start`, not written. A station that receives its streams late (short of
        CPU) still receives the last episode's tail while the next one records; without this it
        went into the next episode. The slack keeps what was in flight as the episode started (a
        camera frame rendered from a snapshot taken just before, which its video keeps). ``None``
        records every sample, whenever captured.
        """
        with self._lock:
            if self._log is not None:
                raise RuntimeError("recorder is already recording; stop() first")
            self._meters = {t: StreamMeter(t, hz) for t, hz in self._expected.items()}
            self.malformed = {}
            self.rejected = {}
            self.before_start = 0
            self._since_ns = since_ns
            self.write_error = None
            self._last.clear()
            self.capture_times = CaptureTimes()
            while self._queue:  # received between episodes: part of none
                self._pop()
            self._log = McapLog(path)
        # Health runs only while recording (devices are stopped between episodes, not stalled).
        self.health.start()

    def newest(self, stream: str) -> dict[str, tuple[int, int]]:
        """Per recorded topic of ``stream`` (e.g. ``joint_state``): the capture time [ns, common clock]
        of the sample recorded last and how many samples of it this episode holds, counting every
        message received so far (what the writer thread has not reached yet is written first, on the
        caller's thread: the episode's end waits on this)."""
        suffix = "/" + stream
        with self._lock:
            self._write_queued()
            return {
                topic: (times[-1], len(times))
                for topic, times in self.capture_times.times.items()
                if topic.endswith(suffix) and times
            }

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """Write a named string map into the current episode's MCAP (e.g. the station clock estimate)."""
        with self._lock:
            if self._log is not None:
                self._log.add_metadata(name, data)

    def stop(self) -> list[StreamSummary]:
        """Close the current log (idempotent) and return per-stream rate, drop and reject statistics."""
        self.health.stop()  # outside the lock: it publishes, and an in-memory bus delivers back here
        with self._lock:
            self._write_queued()  # what the writer thread has not reached yet belongs to this episode
            log_, self._log = self._log, None
            self._flush_log_lines()
            if log_ is not None and self.before_start:
                log.warning(
                    "recorder: %d samples captured before the episode started arrived during it and "
                    "were left out (the station receives its streams late)",
                    self.before_start,
                )
        if log_ is not None:
            try:
                log_.close()
            except RecordingError as exc:
                self._write_failed(exc)
            except OSError as exc:  # the log's own clean-up after a failed finish
                self._write_failed(RecordingError(f"cannot finish the episode log: {exc.strerror}"))
        summaries = [m.summary() for m in self._meters.values()]
        if self.rejected:  # the rejected channel: every refused message of the episode, per reason
            summaries.append(StreamSummary(self._rejected_topic, 0.0, 0.0, 0, 0, 0.0, dict(self.rejected)))
        return summaries

    def close(self) -> None:
        """Stop recording, unsubscribe and end the writer thread. Idempotent."""
        self.stop()
        self._sub.cancel()
        self._closed = True
        self._queued.set()
        if self._writer is not threading.current_thread():
            self._writer.join(timeout=5.0)

    # --- per message -----------------------------------------------------------------------------

    def _on_message(self, message: Message) -> None:
        """On the bus delivery thread: queue the message for the writer thread (nothing else)."""
        if self._log is None:
            return  # between episodes
        spec = self._specs.get(message.topic)
        if spec is not None and not spec.recorded:
            return  # e.g. JPEG previews: for the dashboard; the MP4 has every frame
        queue = self._queue
        size = len(message.payload)
        if len(queue) >= MAX_QUEUED or self._bytes_in - self._bytes_out + size > MAX_QUEUED_BYTES:
            self.queue_overflow += 1
            return
        self._bytes_in += size
        queue.append(message)
        self._queued.set()

    def _write_queued(self) -> None:
        """Write what is queued now, on the calling thread (which holds the lock). Only that: the
        delivery thread goes on queuing meanwhile, and a caller must not chase it."""
        for _ in range(len(self._queue)):
            self._write(self._pop())

    def _pop(self) -> Message:
        """The oldest queued message, out of the queue (the caller holds the lock)."""
        message = self._queue.popleft()
        self._bytes_out += len(message.payload)
        return message

    def _oldest_queued_ns(self) -> int | None:
        """Receive time of the oldest message the writer has not written yet [ns]; ``None``: none."""
        try:
            return self._queue[0].received_ns
        except IndexError:
            return None

    def _write_loop(self) -> None:
        """The writer thread: write queued messages in order, a batch per hold of the lock."""
        entered: priority.Priorities | None = None
        queue = self._queue
        while not self._closed:
            if priority.settings() is not entered:  # the first time, and after a new configure()
                entered = priority.settings()
                priority.enter("work")  # below the control loops (a station's SCHED_RR included)
            self._queued.wait()
            self._queued.clear()
            while queue:
                with self._lock:
                    for _ in range(_WRITE_BATCH):
                        if not queue:
                            break
                        self._write(self._pop())

    def _write(self, message: Message) -> None:
        """Record ``message`` in the current log (the caller holds the lock)."""
        mcap = self._log
        if mcap is None:
            return
        topic = message.topic
        node = topic.split("/", 4)[3]
        if node in self._skip or self.write_error is not None:
            return
        try:
            self._record(mcap, message, node)
        except RecordingError as exc:  # disk full, I/O error: not this message's fault
            self._write_failed(exc)
        except Exception:  # a bug: the writer thread must outlive it, as the bus's delivery did
            self.write_bugs += 1
            if self.write_bugs == 1:
                log.exception("recorder: writing a message on %s failed; it is left out", topic[:256])

    def _record(self, mcap: McapLog, message: Message, node: str) -> None:
        try:
            spec = self._spec(message.topic)
            if spec is not None and not spec.recorded:
                return  # e.g. JPEG previews: for the dashboard; the MP4 has every frame
            if spec is None:
                raise _RejectedError("unknown_stream", "no node of the rig publishes this stream")
            if len(message.payload) > spec.max_bytes:
                raise _RejectedError("oversized", f"{len(message.payload)} bytes, limit {spec.max_bytes}")
            if spec.kind is PayloadKind.IR:
                self._record_sample(mcap, message, spec, node)
            elif spec.kind is PayloadKind.BUNDLE:
                self._record_bundle(mcap, message, spec, node)
            else:
                self._record_state(mcap, message, spec)
        except _RejectedError as rejected:
            self._reject(mcap, message, rejected)

    def _record_bundle(self, mcap: McapLog, message: Message, spec: StreamSpec, node: str) -> None:
        """Record each part of a tick as the message its stream would have carried on its own: under
        ``<node>/<stream>``, checked like one. A refused part is counted on its stream's topic; the
        other parts are recorded."""
        try:
            parts = wire.decode_bundle(message.payload)
        except WireError as exc:
            raise _RejectedError("malformed", str(exc)) from None
        prefix = message.topic.rpartition("/")[0]
        received = message.received_ns
        for stream, envelope in parts:
            part = Message(f"{prefix}/{stream}", envelope, received)
            try:
                part_spec = bundled(spec.role, stream)
                if part_spec is None:
                    if spec_by_name(stream, (spec.role,)) is None:
                        raise _RejectedError("unknown_stream", f"a {stream!r} part in a {spec.name} message")
                    raise _RejectedError(
                        "wrong_stream", f"a {stream!r} part: only IR streams travel in a {spec.name}"
                    )
                if len(envelope) > part_spec.max_bytes:
                    raise _RejectedError("oversized", f"{len(envelope)} bytes, limit {part_spec.max_bytes}")
                if part_spec.recorded:
                    self._record_sample(mcap, part, part_spec, node)
            except _RejectedError as rejected:
                self._reject(mcap, part, rejected)

    def _write_failed(self, exc: RecordingError) -> None:
        if self.write_error is None:
            self.write_error = str(exc)
            log.error("recorder: %s; nothing more is written to this episode's log", exc)

    def _spec(self, topic: str) -> StreamSpec | None:
        # Cached per topic: the catalogue lookup and topic check run once per topic, not per message.
        try:
            return self._specs[topic]
        except KeyError:
            pass
        try:
            parsed = Topic.parse(topic)
        except ValueError:
            raise _RejectedError("bad_topic", "not a telerig topic") from None
        if self._nodes is not None:
            spec = self._nodes.spec(parsed.node, parsed.stream)
        else:
            spec = spec_by_name(parsed.stream)
        if len(self._specs) < _MAX_SOURCES:
            self._specs[topic] = spec
        return spec

    def _record_sample(self, mcap: McapLog, message: Message, spec: StreamSpec, node: str) -> None:
        try:
            sample = wire.decode(message.payload)
        except WireError as exc:
            raise _RejectedError("malformed", str(exc)) from None
        self._check_sample(sample, spec, node, message)
        topic = message.topic
        stamp = sample.stamp
        if self._since_ns is not None and stamp.capture_ns < self._since_ns - _BEFORE_START_SLACK_NS:
            self.before_start += 1
            return
        received_ns = message.received_ns
        to_session = self._to_session
        if to_session is None:
            log_ns, publish_ns = received_ns, stamp.capture_ns
        else:
            log_ns, publish_ns = to_session(received_ns), to_session(stamp.capture_ns)
        if log_ns < 0 or publish_ns < 0:
            raise _RejectedError("negative_time", f"times {log_ns}, {publish_ns} ns in the session clock")
        mcap.write(topic, message.payload, log_time_ns=log_ns, publish_time_ns=publish_ns)
        self.capture_times.add(topic, stamp.capture_ns)
        seq = spec.loss_seq(stamp.seq)
        self.health.observe(topic, capture_ns=stamp.capture_ns, seq=seq, received_ns=received_ns)
        self._meter(topic).add(stamp.capture_ns, seq)

    def _check_sample(self, sample: Sample, spec: StreamSpec, node: str, message: Message) -> None:
        """Raise :class:`_RejectedError` unless ``sample`` is what ``spec`` carries, plausibly stamped."""
        if not isinstance(sample, spec.ir_types):
            raise _RejectedError("wrong_type", f"{type(sample).__name__} on a stream of {_names(spec)}")
        stream = message.topic.rsplit("/", 1)[1]
        if spec.name != stream and device_stream(sample) != stream:  # a device's sample stream
            raise _RejectedError("wrong_stream", f"a {device_stream(sample)} sample")
        stamp = sample.stamp
        source = stamp.source_id
        if spec.from_owner and source != node and not source.startswith(node + "/"):
            raise _RejectedError("wrong_source", f"source {source[:64]!r}, only {node!r} makes this stream")
        if stamp.capture_ns < 0 or stamp.device_ns < 0 or stamp.arrival_ns < 0:
            raise _RejectedError(
                "negative_time", f"capture {stamp.capture_ns} ns, device {stamp.device_ns} ns"
            )
        ahead = stamp.capture_ns - message.received_ns
        if ahead > self._max_future_ns:
            raise _RejectedError("future_stamp", f"captured {ahead / 1e9:.3g} s after it was received")
        if -ahead > self._max_age_ns:
            raise _RejectedError("stale_stamp", f"captured {-ahead / 1e9:.3g} s before it was received")
        key = (message.topic, source)
        last = self._last.get(key)
        if last is not None and stamp.seq <= last[0] and stamp.capture_ns <= last[1]:
            # Not newer by sequence nor by capture time: a copy of an old sample. A restarted source
            # counts from a low seq again but captures later, and is recorded.
            raise _RejectedError("replayed", f"seq {stamp.seq} after {last[0]}, not captured later")
        self._last[key] = (stamp.seq, stamp.capture_ns)
        self._last.move_to_end(key)
        if len(self._last) > _MAX_SOURCES:
            self._last.popitem(last=False)

    def _record_state(self, mcap: McapLog, message: Message, spec: StreamSpec) -> None:
        payload = message.payload
        if spec.kind is PayloadKind.JSON:
            try:
                parse_json_object(payload, max_bytes=spec.max_bytes)
            except WireError as exc:
                raise _RejectedError("malformed", str(exc)) from None
        elif spec.kind is PayloadKind.TEXT:
            try:
                text = payload.decode("utf-8")
            except UnicodeDecodeError:
                raise _RejectedError("malformed", "text payload is not UTF-8") from None
            if not text.isprintable():
                raise _RejectedError("malformed", "text payload has control characters")
            payload = json.dumps(text).encode()  # a JSON string on the JSON channel
        else:
            raise _RejectedError("malformed", f"{spec.kind} payloads are not recorded")
        received_ns = message.received_ns
        log_ns = received_ns if self._to_session is None else self._to_session(received_ns)
        if log_ns < 0:
            raise _RejectedError("negative_time", f"receive time {log_ns} ns in the session clock")
        mcap.write_json(message.topic, payload, log_time_ns=log_ns)

    def _meter(self, topic: str) -> StreamMeter:
        meter = self._meters.get(topic)
        if meter is None:
            meter = self._meters[topic] = StreamMeter(topic, 0.0)
        return meter

    # --- refused messages ------------------------------------------------------------------------

    def _reject(self, mcap: McapLog, message: Message, rejected: _RejectedError) -> None:
        topic, reason = message.topic, rejected.reason
        self.rejected[reason] = self.rejected.get(reason, 0) + 1
        self.malformed[topic] = self.malformed.get(topic, 0) + 1
        if reason not in ("bad_topic", "unknown_stream") or topic in self._meters:
            self._meter(topic).add_rejected(reason)
        record = {
            "topic": topic[:256],
            "size": len(message.payload),
            "reason": reason,
            "detail": rejected.detail[:200],
            "head_b64": base64.b64encode(message.payload[:REJECTED_HEAD_BYTES]).decode(),
        }
        log_ns = max(message.received_ns, 0)
        mcap.write_json(self._rejected_topic, json.dumps(record).encode(), log_time_ns=log_ns)
        self._log_line(reason, f"{topic[:256]}: {rejected.detail} ({len(message.payload)} bytes)")

    def _log_line(self, reason: str, line: str) -> None:
        """One warning per reason per :data:`_LOG_INTERVAL_S`; the ones in between are counted in the next."""
        now = time.monotonic()
        last = self._logged_at.get(reason)
        if last is not None and now - last < _LOG_INTERVAL_S:
            self._unlogged[reason] = self._unlogged.get(reason, 0) + 1
            return
        self._logged_at[reason] = now
        more = self._unlogged.pop(reason, 0)
        suffix = f" (+{more} more {reason} since the last report)" if more else ""
        log.warning("rejected %s message on %s%s", reason, line, suffix)

    def _flush_log_lines(self) -> None:
        for reason, more in self._unlogged.items():
            log.warning(
                "rejected %d more %s messages in this episode (see its rejected channel)", more, reason
            )
        self._unlogged.clear()
        self._logged_at.clear()


def _names(spec: StreamSpec) -> str:
    return "/".join(t.__name__ for t in spec.ir_types)
