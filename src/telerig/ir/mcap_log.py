"""MCAP episode log, the IR on disk: wire Envelopes per topic, zstd chunks flushed often, crash-readable."""

from __future__ import annotations

import json
import logging
import os
import struct
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import IO, Any, NamedTuple

from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer
from pydantic import JsonValue

from telerig import priority
from telerig.errors import DependencyError, RecordingError, WireError
from telerig.ir import wire
from telerig.ir.types import ControlKind, ControlMode, ControlSource, RetargetResidual, Sample, Stamp

__all__ = [
    "DEFAULT_CHUNK_SIZE",
    "DEFAULT_FLUSH_INTERVAL_S",
    "RESIDUAL_STREAM",
    "LogEntry",
    "McapLog",
    "TopicStats",
    "control_source_from_json",
    "decode_residual",
    "iter_raw",
    "iter_tagged",
    "read_control_sources",
    "read_json",
    "read_log",
    "read_residuals",
    "residual_from_json",
    "residual_source",
]

_log = logging.getLogger(__name__)

#: Uncompressed chunk size [bytes] at which a chunk is compressed and written.
DEFAULT_CHUNK_SIZE = 256 * 1024
#: Longest time [s] a written message stays buffered in memory before it reaches the file.
DEFAULT_FLUSH_INTERVAL_S = 1.0
#: How long the flush thread leaves a log's writing thread to write out the open chunk [s].
_ASK_WAIT_S = 0.05

_MAGIC = b"\x89MCAP0\r\n"
_MESSAGE_ENCODING = "protobuf"
_JSON_ENCODING = "json"
_SCHEMA_ENCODING = "protobuf"
_LIBRARY = "telerig"


@dataclass(frozen=True, slots=True)
class TopicStats:
    """What one topic of a log holds so far.

    Attributes:
        topic: Full topic, e.g. ``telerig/v1/demo/vr0/controller_right``.
        count: Messages written.
        first_log_ns: Log time of the first message, common clock [ns].
        last_log_ns: Log time of the last message [ns].
        first_publish_ns: Publish (capture) time of the first message [ns].
        last_publish_ns: Publish (capture) time of the last message [ns].
    """

    topic: str
    count: int
    first_log_ns: int
    last_log_ns: int
    first_publish_ns: int
    last_publish_ns: int


class _Channel:
    __slots__ = (
        "count",
        "encoding",
        "first_log_ns",
        "first_publish_ns",
        "id",
        "last_log_ns",
        "last_publish_ns",
    )

    def __init__(self, channel_id: int, encoding: str, log_time_ns: int, publish_time_ns: int) -> None:
        self.id = channel_id
        self.encoding = encoding
        self.count = 0
        self.first_log_ns = log_time_ns
        self.first_publish_ns = publish_time_ns
        self.last_log_ns = log_time_ns
        self.last_publish_ns = publish_time_ns


class McapLog:
    """Append-only MCAP file of encoded ``telerig.v1.Envelope`` messages, one channel per topic.

    State streams that are JSON rather than IR go on their own ``json`` channels (:meth:`write_json`).

    The file embeds the Envelope schema (a protobuf ``FileDescriptorSet``), so standard MCAP
    tools and viewers decode it. Messages are grouped in zstd chunks of ``chunk_size`` bytes; the
    open chunk is also written out about every half ``flush_interval_s`` and fsynced, so a crash
    loses at most about that much. Without the summary written by :meth:`close`,
    :func:`read_log` still recovers every flushed chunk.

    Who writes the open chunk out: the thread that writes messages, at its next message after the
    background flush thread asked it to; the flush thread itself only when no message came within
    ``_ASK_WAIT_S`` of asking (nobody is waiting for the log then). The flush thread runs below the
    control loop (``priority.enter("work")``): when the recorder still wrote on the bus delivery
    thread, at the robots' real-time priority in a station, compressing the chunk under the log's
    lock on the flush thread kept that thread waiting for one the real-time threads did not let
    run. The fsync stays on the flush thread, outside the lock.

    Time convention: ``publish_time_ns`` is the sample's capture time, ``log_time_ns`` the time
    the recorder received it, both in the common clock [ns].

    ``write`` may be called from any thread. Use as a context manager or call :meth:`close`.
    """

    def __init__(
        self,
        path: Path | str,
        *,
        chunk_size: int = DEFAULT_CHUNK_SIZE,
        flush_interval_s: float = DEFAULT_FLUSH_INTERVAL_S,
    ) -> None:
        """Create the file at ``path`` (which must not exist) and write the MCAP header and schema.

        Args:
            path: File to create; its directory must exist.
            chunk_size: Uncompressed chunk size [bytes] that triggers writing a chunk. > 0.
            flush_interval_s: Period [s] of the background flush + fsync. > 0.
        """
        if chunk_size <= 0:
            raise ValueError(f"chunk_size must be > 0 bytes, got {chunk_size}")
        if flush_interval_s <= 0:
            raise ValueError(f"flush_interval_s must be > 0 s, got {flush_interval_s}")
        self._path = Path(path)
        try:
            self._file: IO[bytes] = open(self._path, "xb")  # noqa: SIM115 - closed in close()
        except FileExistsError:
            raise RecordingError(f"{self._path} already exists; an MCAP log is never overwritten") from None
        except OSError as exc:
            raise RecordingError(f"cannot create {self._path}: {exc.strerror}") from None
        self._writer = Writer(self._file, chunk_size=chunk_size, compression=CompressionType.ZSTD)
        self._writer.start(profile="", library=_LIBRARY)
        self._schema_id: int = self._writer.register_schema(
            name=wire.ENVELOPE_SCHEMA_NAME, encoding=_SCHEMA_ENCODING, data=wire.file_descriptor_set()
        )
        self._channels: dict[str, _Channel] = {}
        self._lock = threading.Lock()
        self._dirty = False  # messages in the open chunk
        self._flush_asked = False  # the flush thread asked the writing thread to write it out
        self._unsynced = False  # written out since the last fsync
        self._closed = False
        # Held by the flush thread while it flushes and fsyncs this log (writers only take _lock).
        self._flushing = threading.RLock()
        self._flush_interval_s = flush_interval_s
        _FLUSHER.add(self)

    @property
    def path(self) -> Path:
        """The MCAP file."""
        return self._path

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` has been called."""
        return self._closed

    def write(self, topic: str, payload: bytes, *, log_time_ns: int, publish_time_ns: int) -> None:
        """Append one encoded Envelope on ``topic`` (the channel is created on first use).

        Args:
            topic: Bus topic, e.g. ``telerig/v1/demo/vr0/controller_right``.
            payload: Serialized ``telerig.v1.Envelope``; written as is, not re-encoded.
            log_time_ns: When the recorder received it, common clock [ns]. >= 0.
            publish_time_ns: The sample's capture time, common clock [ns]. >= 0.

        Raises:
            RecordingError: the log is closed, the file cannot be written, or ``topic`` is a
                JSON channel.
        """
        self._write(topic, payload, log_time_ns, publish_time_ns, _MESSAGE_ENCODING)

    def write_json(
        self, topic: str, payload: bytes, *, log_time_ns: int, publish_time_ns: int | None = None
    ) -> None:
        """Append one UTF-8 JSON message (state streams: session, status, alerts, health).

        The channel has message encoding ``json`` and no schema; :func:`read_log` skips it.
        ``publish_time_ns`` defaults to ``log_time_ns`` [ns].
        """
        publish = log_time_ns if publish_time_ns is None else publish_time_ns
        self._write(topic, payload, log_time_ns, publish, _JSON_ENCODING)

    def _write(
        self, topic: str, payload: bytes, log_time_ns: int, publish_time_ns: int, encoding: str
    ) -> None:
        if log_time_ns < 0 or publish_time_ns < 0:
            raise ValueError(
                f"log_time_ns and publish_time_ns must be >= 0 ns, got {log_time_ns}, {publish_time_ns}"
            )
        with self._lock:
            if self._closed:
                raise RecordingError(f"write to closed MCAP log {self._path}")
            channel = self._channels.get(topic)
            if channel is None:
                schema_id = self._schema_id if encoding == _MESSAGE_ENCODING else 0
                channel_id = self._writer.register_channel(
                    topic=topic, message_encoding=encoding, schema_id=schema_id
                )
                channel = self._channels[topic] = _Channel(channel_id, encoding, log_time_ns, publish_time_ns)
            elif channel.encoding != encoding:
                raise RecordingError(
                    f"topic {topic} is a {channel.encoding} channel in {self._path}; cannot add {encoding}"
                )
            try:
                self._writer.add_message(
                    channel_id=channel.id,
                    log_time=log_time_ns,
                    data=payload,
                    publish_time=publish_time_ns,
                    sequence=channel.count & 0xFFFFFFFF,
                )
                channel.count += 1
                channel.last_log_ns = log_time_ns
                channel.last_publish_ns = publish_time_ns
                self._dirty = True
                if self._flush_asked:
                    self._flush_locked()
            except OSError as exc:
                raise RecordingError(f"cannot write {self._path}: {exc.strerror}") from None

    def add_metadata(self, name: str, data: Mapping[str, str]) -> None:
        """Write a named string map (e.g. episode id, rig) into the file as an MCAP Metadata record."""
        with self._lock:
            if self._closed:
                raise RecordingError(f"add_metadata on closed MCAP log {self._path}")
            self._writer.add_metadata(name, dict(data))

    def stats(self) -> dict[str, TopicStats]:
        """Per-topic message counts and first/last times so far, keyed by topic."""
        with self._lock:
            return {
                topic: TopicStats(
                    topic, c.count, c.first_log_ns, c.last_log_ns, c.first_publish_ns, c.last_publish_ns
                )
                for topic, c in self._channels.items()
            }

    def flush(self) -> None:
        """Write the open chunk to the file and fsync it (the background thread does this periodically)."""
        with self._lock:
            if self._closed:
                return
            self._flush_locked()
        os.fsync(self._file.fileno())

    def close(self) -> None:
        """Write the last chunk, the summary and the footer, fsync and close the file. Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        _FLUSHER.remove(self)
        with self._flushing, self._lock:  # after a flush the flush thread is doing now
            try:
                self._writer.finish()
                self._file.flush()
                os.fsync(self._file.fileno())
            except OSError as exc:
                raise RecordingError(f"cannot finish {self._path}: {exc.strerror}") from None
            finally:
                self._file.close()

    def __enter__(self) -> McapLog:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def _flush_locked(self) -> None:
        self._flush_asked = False
        if self._dirty:
            self._writer.flush()
            self._dirty = False
            self._unsynced = True

    def _flush_once(self) -> float | None:
        """On the flush thread: fsync what the writing thread wrote out when asked; else ask it to
        write out the open chunk, or write it out here when the ask went unanswered (the log is
        idle). Returns when to come back [s]; None once the log is closed or flushing failed (it
        is then left alone)."""
        with self._flushing:
            try:
                with self._lock:
                    if self._closed:
                        return None
                    again = self._flush_interval_s / 2
                    if not self._unsynced and self._dirty and not self._flush_asked:
                        self._flush_asked = True
                        again = min(_ASK_WAIT_S, again)
                    elif not self._unsynced:
                        self._flush_locked()  # nothing came since the ask: nobody waits for the lock
                    synced, self._unsynced = self._unsynced, False
                if synced:
                    os.fsync(self._file.fileno())
            except (OSError, ValueError) as exc:  # disk full, or the file was closed under us
                _log.error("flushing %s failed: %s", self._path, exc)
                return None
        return again


class _Flusher:
    """The process's one MCAP flush thread: each open log's open chunk is written out (by its
    writing thread when asked, see :class:`McapLog`) and fsynced about every half of its
    ``flush_interval_s``, so data waits at most about one interval before reaching the disk.

    One thread for every log rather than one per log: the open chunk is zstd-compressed where it is
    flushed, and one-shot ``zstandard.compress`` allocates its ~1 MiB context each time, in the
    calling thread's malloc arena. With a thread per log (per episode), each episode left that
    resident in another of glibc's arenas (trimming is off in control processes,
    :func:`~telerig.runtime.realtime.keep_heap`): +1.1 MiB RSS per log, measured with keep_heap and
    20 threads holding arenas, 3 s of joint states per log; on one thread it is reused.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._due: dict[McapLog, float] = {}  # log → when it is flushed next [time.monotonic s]
        self._changed = threading.Event()
        self._thread: threading.Thread | None = None

    def add(self, log: McapLog) -> None:
        with self._lock:
            self._due[log] = time.monotonic() + log._flush_interval_s / 2
            if self._thread is None or not self._thread.is_alive():
                self._thread = threading.Thread(target=self._run, name="mcap-flush", daemon=True)
                self._thread.start()
        self._changed.set()

    def remove(self, log: McapLog) -> None:
        with self._lock:
            self._due.pop(log, None)

    def forget(self) -> None:
        """In a forked child: the parent's thread does not exist there, nor do its logs."""
        self._lock = threading.Lock()
        self._due = {}
        self._changed = threading.Event()
        self._thread = None

    def _run(self) -> None:
        entered: priority.Priorities | None = None
        while True:
            self._changed.clear()
            if priority.settings() is not entered:  # the first time, and after a new configure()
                entered = priority.settings()
                priority.enter("work")  # below the control loop
            with self._lock:
                now = time.monotonic()
                due = [log for log, at in self._due.items() if at <= now]
            for log in due:
                again = log._flush_once()
                with self._lock:
                    if again is None:
                        self._due.pop(log, None)
                    elif log in self._due:  # not removed meanwhile (closed)
                        self._due[log] = time.monotonic() + again
            with self._lock:
                wake = min(self._due.values(), default=None)
            self._changed.wait(None if wake is None else max(0.0, wake - time.monotonic()))


_FLUSHER = _Flusher()
if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_FLUSHER.forget)


# --- reading ------------------------------------------------------------------------------------


class LogEntry(NamedTuple):
    """One decoded message of an MCAP log."""

    topic: str
    sample: Sample
    log_time_ns: int
    publish_time_ns: int


def read_log(path: Path | str, *, topics: Iterable[str] | None = None) -> Iterator[LogEntry]:
    """Yield the IR samples of an MCAP log in file order (the order they were written).

    A file whose footer is missing (the recorder crashed) is read sequentially and yields every
    message of every complete chunk before the damage. Channels that do not carry
    ``telerig.v1.Envelope`` are skipped.

    Args:
        path: The MCAP file.
        topics: Only these topics; all when ``None``.

    Raises:
        RecordingError: the file does not exist or is not MCAP.
        WireError: a message in an intact chunk is not a valid Envelope.
    """
    for topic, data, log_time_ns, publish_time_ns in iter_raw(path, topics=topics):
        yield LogEntry(topic, wire.decode(data), log_time_ns, publish_time_ns)


def iter_raw(
    path: Path | str, *, topics: Iterable[str] | None = None
) -> Iterator[tuple[str, bytes, int, int]]:
    """Like :func:`read_log` but yield ``(topic, envelope bytes, log_time_ns, publish_time_ns)`` undecoded."""
    yield from _iter_channels(path, topics, _envelope_channel)


def iter_tagged(path: Path | str) -> Iterator[tuple[str, bytes, int, int, bool]]:
    """Every Envelope and JSON message of a log in one pass, in file order: ``(topic, bytes,
    log_time_ns, publish_time_ns, is_json)``, undecoded (a reader that wants both kinds parses the
    file once, not once per kind; like :func:`read_log`, a file without footer yields its complete
    chunks).

    Raises:
        RecordingError: the file does not exist or is not MCAP.
    """
    is_json = [False]  # the encoding of the channel of the message yielded next

    def keep(schema: Any, channel: Any) -> bool:
        is_json[0] = _json_channel(schema, channel)
        return is_json[0] or _envelope_channel(schema, channel)

    for topic, data, log_time_ns, publish_time_ns in _iter_channels(path, None, keep):
        yield topic, data, log_time_ns, publish_time_ns, is_json[0]


def read_json(
    path: Path | str, *, topics: Iterable[str] | None = None
) -> Iterator[tuple[str, JsonValue, int]]:
    """Yield ``(topic, value, log_time_ns)`` of the JSON channels (node state, residuals, alerts), in
    file order; like :func:`read_log`, a file without footer yields its complete chunks.

    Raises:
        RecordingError: the file does not exist or is not MCAP.
    """
    for topic, data, log_time_ns, _ in _iter_channels(path, topics, _json_channel):
        try:
            value = json.loads(data)
        except ValueError:
            continue  # a non-JSON state payload (e.g. a bare status word)
        except RecursionError:
            continue  # absurdly nested JSON that a recorder without bounds let in
        yield topic, value, log_time_ns


_CONTROL_KINDS: dict[object, ControlKind] = {
    None: "none",
    "policy": "policy",
    "operator": "operator",
    "paused": "paused",
    "home": "home",
}
_CONTROL_MODES: dict[object, ControlMode] = {"auto": "auto", "operator": "operator", "policy": "policy"}


def control_source_from_json(value: JsonValue, source_id: str, seq: int) -> ControlSource | None:
    """The :class:`ControlSource` of a ``control_source`` JSON object as telerig recorded it before
    the stream was typed (``{"capture_ns", "source", "kind", "mode"}``, ``kind`` null when nobody
    drove); None when ``value`` is not such an object.

    Args:
        value: The decoded JSON value.
        source_id: The stamp's source (the robot: the JSON form had none).
        seq: The stamp's sequence number (the JSON form had none).
    """
    if not isinstance(value, dict):
        return None
    capture, source = value.get("capture_ns"), value.get("source")
    kind_value, mode_value = value.get("kind"), value.get("mode", "auto")
    kind = _CONTROL_KINDS.get(kind_value) if _hashable(kind_value) else None
    mode = _CONTROL_MODES.get(mode_value) if _hashable(mode_value) else None
    if not isinstance(capture, int) or isinstance(capture, bool) or kind is None or mode is None:
        return None
    if not (source is None or isinstance(source, str)):
        return None
    try:
        return ControlSource(Stamp(source_id, seq, capture, capture), source, kind, mode)
    except ValueError:  # source and kind disagree (a source named with a null kind, or "")
        return None


def _hashable(value: JsonValue) -> bool:
    return not isinstance(value, dict | list)


def read_control_sources(path: Path | str, topics: Iterable[str]) -> Iterator[tuple[str, ControlSource, int]]:
    """Yield ``(topic, sample, log_time_ns)`` of the ``control_source`` streams ``topics`` in file
    order: the IR samples, and the JSON objects of episodes recorded before the stream was typed as
    :class:`ControlSource` (see :func:`control_source_from_json`; the stamp's source is the topic's
    node, its seq counts from 1). Messages that are neither (malformed JSON, other IR types) are
    counted and left out, with one warning per file.

    Raises:
        RecordingError: the file does not exist or is not MCAP.
        WireError: an IR message in an intact chunk is not a valid Envelope.
    """
    seqs: dict[str, int] = {}
    dropped = 0
    is_json = [False]  # the encoding of the channel of the message yielded next

    def keep(schema: Any, channel: Any) -> bool:
        is_json[0] = _json_channel(schema, channel)
        return is_json[0] or _envelope_channel(schema, channel)

    for topic, data, log_time_ns, _ in _iter_channels(path, list(topics), keep):
        sample: Sample | None
        if is_json[0]:
            seq = seqs[topic] = seqs.get(topic, 0) + 1
            try:
                value = json.loads(data)
            except (ValueError, RecursionError):
                value = None
            sample = control_source_from_json(value, topic.rsplit("/", 2)[-2], seq)
        else:
            sample = wire.decode(data)
        if isinstance(sample, ControlSource):
            yield topic, sample, log_time_ns
        else:
            dropped += 1
    if dropped:
        _log.warning("%s: %d control_source messages are not control sources; left out", path, dropped)


#: Stream name of the robots' retargeting residuals (``telerig.bus.catalogue.RESIDUAL``; the IR
#: layer sits below the catalogue, a test keeps the two equal).
RESIDUAL_STREAM = "residual"
#: Largest capture time a JSON residual may carry [ns] (int64, as on the wire).
_INT64_MAX = 2**63 - 1


def residual_from_json(
    value: JsonValue, source_id: str, seq: int, log_time_ns: int
) -> RetargetResidual | None:
    """The :class:`RetargetResidual` of a ``residual`` JSON object as telerig recorded it before the
    stream was typed (``{"capture_ns", "flagged", <metric>: <number>, ...}``); None when ``value``
    is not a JSON object.

    ``flagged`` is true only for JSON ``true``; every other key with a number (not a boolean) is a
    metric, in the object's order, other keys (and integers beyond a double's range) are left out;
    a missing or invalid ``capture_ns`` (not an integer in [0, 2^63)) is replaced by the log time,
    as the readers did before.

    Args:
        value: The decoded JSON value.
        source_id: The stamp's source (the robot: the JSON form had none).
        seq: The stamp's sequence number (the JSON form had none).
        log_time_ns: The message's log time [ns].
    """
    if not isinstance(value, dict):
        return None
    capture = value.get("capture_ns")
    if not isinstance(capture, int) or isinstance(capture, bool) or not 0 <= capture <= _INT64_MAX:
        capture = log_time_ns
    names: list[str] = []
    values: list[float] = []
    for key, number in value.items():
        if key in ("capture_ns", "flagged") or not key or isinstance(number, bool):
            continue
        if isinstance(number, int | float):
            try:
                values.append(float(number))
            except OverflowError:  # a JSON integer beyond a double's range
                continue
            names.append(key)
    stamp = Stamp(source_id, seq, capture, capture)
    flagged = value.get("flagged") is True
    return RetargetResidual(stamp, flagged, tuple(names), tuple(values))


def decode_residual(
    data: bytes, *, json_form: bool, source_id: str, seq: int, log_time_ns: int
) -> RetargetResidual:
    """One ``residual`` message, typed or (``json_form``) the JSON object of earlier telerig
    versions (see :func:`residual_from_json`): the one way every reader turns residual bytes into a
    :class:`RetargetResidual`.

    Args:
        data: The message bytes.
        json_form: The bytes are JSON (an MCAP ``json`` channel, or a payload starting with ``{``).
        source_id: For the JSON form: the stamp's source (the topic's node).
        seq: For the JSON form: the stamp's sequence number.
        log_time_ns: For the JSON form: the capture time when the object has none [ns].

    Raises:
        WireError: not an Envelope or not a residual, or not JSON or not a JSON object; one line.
    """
    if not json_form:
        sample = wire.decode(data)
        if not isinstance(sample, RetargetResidual):
            raise WireError(f"a {type(sample).__name__} where a RetargetResidual belongs")
        return sample
    try:
        value = json.loads(data)
    except (ValueError, RecursionError):
        raise WireError(f"residual payload of {len(data)} bytes is neither an Envelope nor JSON") from None
    residual = residual_from_json(value, source_id, seq, log_time_ns)
    if residual is None:
        raise WireError(f"residual JSON is a {type(value).__name__}, not an object")
    return residual


def residual_source(topic: str) -> str:
    """The stamp source :func:`read_residuals` gives a residual recorded on ``topic``: the topic's
    node (the level before the stream), or the whole topic when it has no ``/``."""
    return topic.rsplit("/", 2)[-2] if topic.count("/") >= 1 else topic


def read_residuals(
    path: Path | str, topics: Iterable[str] | None = None
) -> Iterator[tuple[str, RetargetResidual, int]]:
    """Yield ``(topic, residual, log_time_ns)`` of the robots' ``residual`` streams in file order:
    the IR samples, and the JSON objects of episodes recorded before the stream was typed (see
    :func:`decode_residual`; the stamp's source is the topic's node, its seq counts from 1).
    Messages that are neither (malformed JSON, other IR types, undecodable bytes) are counted and
    left out, with one warning per file. Values are as recorded: a reader that needs finite ones
    (a mean, a plot) checks them.

    Args:
        path: The MCAP file.
        topics: Only these topics; every topic of stream :data:`RESIDUAL_STREAM` when ``None``.

    Raises:
        RecordingError: the file does not exist or is not MCAP.
    """
    seqs: dict[str, int] = {}
    dropped = 0
    is_json = [False]  # the encoding of the channel of the message yielded next

    def keep(schema: Any, channel: Any) -> bool:
        if topics is None and channel.topic.rsplit("/", 1)[-1] != RESIDUAL_STREAM:
            return False
        is_json[0] = _json_channel(schema, channel)
        return is_json[0] or _envelope_channel(schema, channel)

    for topic, data, log_time_ns, _ in _iter_channels(path, None if topics is None else list(topics), keep):
        seq = seqs[topic] = seqs.get(topic, 0) + 1
        node = residual_source(topic)
        try:
            residual = decode_residual(
                data, json_form=is_json[0], source_id=node, seq=seq, log_time_ns=log_time_ns
            )
        except WireError:
            dropped += 1
            continue
        yield topic, residual, log_time_ns
    if dropped:
        _log.warning("%s: %d residual messages are not residuals; left out", path, dropped)


def _iter_channels(
    path: Path | str, topics: Iterable[str] | None, keep: Callable[[Any, Any], bool]
) -> Iterator[tuple[str, bytes, int, int]]:
    path = Path(path)
    wanted = None if topics is None else frozenset(topics)
    try:
        f = open(path, "rb")  # noqa: SIM115 - closed below, after the generator is done
    except OSError as exc:
        raise RecordingError(f"cannot open MCAP log {path}: {exc.strerror}") from None
    with f:
        head = f.read(len(_MAGIC))
        if len(head) < len(_MAGIC) and _MAGIC.startswith(head):
            return  # crashed before the header was written: nothing to recover
        if head != _MAGIC:
            raise RecordingError(f"{path} is not an MCAP file (bad magic)")
        f.seek(-len(_MAGIC), os.SEEK_END)
        complete = f.tell() > len(_MAGIC) and f.read() == _MAGIC
        f.seek(0)
        if complete:
            yield from _iter_indexed(f, wanted, keep)
        else:
            _log.warning("%s has no footer (recorder crashed?); recovering complete chunks", path)
            yield from _iter_recovered(f, wanted, path, keep)


def _envelope_channel(schema: Any, channel: Any) -> bool:
    return bool(
        channel.message_encoding == _MESSAGE_ENCODING
        and schema is not None
        and schema.name == wire.ENVELOPE_SCHEMA_NAME
    )


def _json_channel(schema: Any, channel: Any) -> bool:
    return bool(channel.message_encoding == _JSON_ENCODING)


def _iter_indexed(
    f: IO[bytes], wanted: frozenset[str] | None, keep: Callable[[Any, Any], bool]
) -> Iterator[tuple[str, bytes, int, int]]:
    reader = make_reader(f, validate_crcs=True)
    for schema, channel, message in reader.iter_messages(topics=wanted, log_time_order=False):
        if keep(schema, channel):
            yield channel.topic, message.data, message.log_time, message.publish_time


def _zstd_error() -> type[Exception]:
    try:
        import zstandard
    except ImportError as exc:
        raise DependencyError("zstandard is missing: pip install 'telerig[record]'") from exc
    error: type[Exception] = zstandard.ZstdError
    return error


def _iter_recovered(
    f: IO[bytes], wanted: frozenset[str] | None, path: Path, keep: Callable[[Any, Any], bool]
) -> Iterator[tuple[str, bytes, int, int]]:
    # Chunk records are decompressed and CRC-checked whole, so a torn chunk yields nothing and
    # every message before it is intact. Schemas and channels live inside the chunks.
    from mcap.records import Channel, Message, Schema

    schemas: dict[int, Any] = {}
    channels: dict[int, Any] = {}
    count = 0
    damage = (McapError, struct.error, ValueError, EOFError, _zstd_error())
    records = StreamReader(f, validate_crcs=True).records
    while True:
        try:
            record = next(records)
        except StopIteration:
            break
        except damage as exc:
            _log.warning(
                "%s: stopped at truncated or damaged record after %d messages (%s)",
                path,
                count,
                str(exc) or type(exc).__name__,
            )
            break
        if isinstance(record, Schema):
            schemas[record.id] = record
        elif isinstance(record, Channel):
            channels[record.id] = record
        elif isinstance(record, Message):
            channel = channels.get(record.channel_id)
            if channel is None or (wanted is not None and channel.topic not in wanted):
                continue
            if keep(schemas.get(channel.schema_id), channel):
                count += 1
                yield channel.topic, record.data, record.log_time, record.publish_time
