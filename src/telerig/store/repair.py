"""Crash recovery: commit the longest verified prefix of an episode interrupted in ``.incoming``."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import errno
import fcntl
import hashlib
import logging
import os
import struct
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, get_args

from pydantic import JsonValue, ValidationError

from telerig.bus.broker import remove_stale_broker_dirs
from telerig.bus.metrics import StreamMeter
from telerig.errors import RecordingError, WireError
from telerig.ir import wire
from telerig.ir.types import CameraFrame
from telerig.store.episodes import EpisodeDraft, EpisodeManifest, EpisodeStatus, EpisodeStore
from telerig.store.manifest_extra import CameraRecord, EpisodeExtra

__all__ = [
    "REPAIRED_STATUS",
    "VideoRepair",
    "StreamRepair",
    "add_repair_arguments",
    "cmd_repair",
    "interrupted",
    "repair",
    "repair_all",
]

_log = logging.getLogger("telerig.store.repair")

#: Status of a repaired episode; ``complete`` (with ``extra["repair"]``) until the store knows ``repaired``.
REPAIRED_STATUS = "repaired" if "repaired" in get_args(EpisodeStatus) else "complete"
#: A file modified at most this long [s] after the newest recovered data counts as evidence that the
#: episode ran until then (writers flush within ~1 s); a later time means the file was copied or touched.
MTIME_EVIDENCE_S = 2.0
#: Suffix of an original file kept by ``repair(..., keep_originals=True)``.
TORN_SUFFIX = ".torn"
#: A draft touched more recently than this [s] may still be recording; :func:`repair` refuses it.
DEFAULT_MIN_IDLE_S = 5.0

_INCOMING = ".incoming"
_MANIFEST = "manifest.json"
_MCAP = "episode.mcap"
_CAMERAS = "cameras"
_TMP_SUFFIX = ".repair-tmp"
_MCAP_MAGIC = b"\x89MCAP0\r\n"
_MCAP_CHUNK_SIZE = 1 << 20
_FRAMES_STREAM = "frames"
_HASH_BLOCK = 1 << 20


@dataclass(frozen=True, slots=True)
class StreamRepair:
    """What survived of one MCAP topic.

    Attributes:
        topic: Full topic, e.g. ``telerig/v1/demo/arm0/joint_state``.
        messages: Messages recovered.
        first_ns: Log (receive) time of the first recovered message, common clock [ns].
        last_ns: Log time of the last recovered message [ns].
        lost_s: Time from ``last_ns`` to the last evidence that the episode ran [s]; a lower bound
            of what the crash cost this stream.
    """

    topic: str
    messages: int
    first_ns: int
    last_ns: int
    lost_s: float


@dataclass(frozen=True, slots=True)
class VideoRepair:
    """What survived of one camera video.

    Attributes:
        name: Camera name (the file is ``cameras/<name>.mp4``).
        frames: Frames that decode in the repaired file.
        fragments: Whole MP4 fragments (``moof`` + ``mdat``) kept.
        bytes_dropped: Bytes of the torn tail removed [bytes].
        start_ns: Capture time of frame 0 from the MCAP ``frames`` stream [ns]; ``None`` if not recovered.
        end_ns: Capture time of the last kept frame [ns] (``start_ns`` + its pts); ``None`` likewise.
        lost_s: Time from ``end_ns`` to the last evidence that the episode ran [s]; ``None`` when
            ``end_ns`` is unknown.
    """

    name: str
    frames: int
    fragments: int
    bytes_dropped: int
    start_ns: int | None
    end_ns: int | None
    lost_s: float | None


# --- MCAP -------------------------------------------------------------------------------------------


@dataclass(slots=True)
class _McapResult:
    streams: dict[str, StreamMeter]
    first_log: dict[str, int]
    last_log: dict[str, int]
    counts: dict[str, int]
    first_frame_ns: dict[str, int]
    rewritten: bool
    bytes_before: int
    bytes_after: int


def _mcap_complete(path: Path) -> bool:
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        if f.read(len(_MCAP_MAGIC)) != _MCAP_MAGIC:
            return False
        f.seek(0, os.SEEK_END)
        if f.tell() < 2 * len(_MCAP_MAGIC):
            return False
        f.seek(-len(_MCAP_MAGIC), os.SEEK_END)
        if f.read() != _MCAP_MAGIC:
            return False
        f.seek(0)
        try:
            return make_reader(f).get_summary() is not None
        except (McapError, struct.error, ValueError, EOFError):
            return False


def _mcap_records(path: Path) -> Iterator[Any]:
    """Records of the data section up to the first damage: whole, CRC-checked chunks only."""
    from mcap.exceptions import McapError
    from mcap.records import DataEnd, Footer
    from mcap.stream_reader import StreamReader

    try:
        import zstandard

        zstd_error: type[Exception] = zstandard.ZstdError
    except ImportError:  # pragma: no cover - mcap depends on it
        zstd_error = McapError
    damage = (McapError, struct.error, ValueError, EOFError, zstd_error)
    with open(path, "rb") as f:
        records = StreamReader(f, validate_crcs=True).records
        while True:
            try:
                record = next(records)
            except StopIteration:
                return
            except damage as exc:
                _log.info(
                    "%s: data ends at a torn or damaged record (%s)", path, str(exc) or type(exc).__name__
                )
                return
            if isinstance(record, (DataEnd, Footer)):
                return
            yield record


def _repair_mcap(path: Path, keep_original: bool) -> _McapResult:
    """Rewrite a torn MCAP into a valid one (summary, footer) holding every recoverable record."""
    from mcap.reader import make_reader
    from mcap.records import Attachment, Channel, Header, Message, Metadata, Schema
    from mcap.writer import CompressionType, Writer

    result = _McapResult({}, {}, {}, {}, {}, False, path.stat().st_size, 0)
    complete = _mcap_complete(path)
    tmp = path.with_name(path.name + _TMP_SUFFIX)
    channels: dict[int, Channel] = {}

    def account(record: Message) -> None:
        channel = channels.get(record.channel_id)
        if channel is None:
            return
        topic = channel.topic
        result.counts[topic] = result.counts.get(topic, 0) + 1
        result.first_log.setdefault(topic, record.log_time)
        result.last_log[topic] = max(result.last_log.get(topic, record.log_time), record.log_time)
        if channel.message_encoding != "protobuf":
            return
        try:
            sample = wire.decode(record.data)
        except WireError:
            return
        meter = result.streams.get(topic)
        if meter is None:
            meter = result.streams[topic] = StreamMeter(topic, 0.0)
        meter.add(sample.stamp.capture_ns, sample.stamp.seq)
        if (
            isinstance(sample, CameraFrame)
            and sample.frame_index == 0
            and topic.rsplit("/", 1)[-1] == _FRAMES_STREAM
        ):
            result.first_frame_ns.setdefault(sample.camera_id, sample.stamp.capture_ns)

    if complete:
        with open(path, "rb") as f:
            summary = make_reader(f).get_summary()
            assert summary is not None
            channels.update(summary.channels)
            f.seek(0)
            for _schema, _channel, message in make_reader(f).iter_messages(log_time_order=False):
                account(message)
        result.bytes_after = result.bytes_before
        return result

    written = 0
    with open(tmp, "wb") as out:
        writer: Writer | None = None
        schema_ids: dict[int, int] = {}
        channel_ids: dict[int, int] = {}
        pending: list[Any] = []  # records seen before the header (never in a valid file)
        for record in _mcap_records(path):
            if isinstance(record, Header):
                writer = Writer(out, chunk_size=_MCAP_CHUNK_SIZE, compression=CompressionType.ZSTD)
                writer.start(profile=record.profile, library=record.library)
                continue
            if writer is None:
                pending.append(record)
                continue
            if isinstance(record, Schema):
                if record.id not in schema_ids:
                    schema_ids[record.id] = writer.register_schema(record.name, record.encoding, record.data)
            elif isinstance(record, Channel):
                if record.id not in channel_ids:
                    channels[record.id] = record
                    channel_ids[record.id] = writer.register_channel(
                        record.topic,
                        record.message_encoding,
                        schema_ids.get(record.schema_id, 0),
                        dict(record.metadata),
                    )
            elif isinstance(record, Message):
                if record.channel_id not in channel_ids:
                    continue
                writer.add_message(
                    channel_ids[record.channel_id],
                    log_time=record.log_time,
                    data=record.data,
                    publish_time=record.publish_time,
                    sequence=record.sequence,
                )
                written += 1
                account(record)
            elif isinstance(record, Metadata):
                writer.add_metadata(record.name, dict(record.metadata))
            elif isinstance(record, Attachment):
                writer.add_attachment(
                    record.create_time, record.log_time, record.name, record.media_type, record.data
                )
        if writer is None:  # not even a header survived: an empty, valid log
            writer = Writer(out, chunk_size=_MCAP_CHUNK_SIZE, compression=CompressionType.ZSTD)
            writer.start(profile="", library="telerig repair")
        writer.finish()
        out.flush()
        os.fsync(out.fileno())
    with open(tmp, "rb") as f:
        reread = sum(1 for _ in make_reader(f).iter_messages(log_time_order=False))
    if reread != written:
        tmp.unlink()
        raise RecordingError(
            f"{path}: the rewritten log reads back {reread} of {written} messages; file kept as is"
        )
    if keep_original:
        os.replace(path, path.with_name(path.name + TORN_SUFFIX))
    os.replace(tmp, path)
    result.rewritten = True
    result.bytes_after = path.stat().st_size
    return result


# --- MP4 --------------------------------------------------------------------------------------------


def _mp4_boxes(f: IO[bytes], size: int) -> list[tuple[bytes, int, int]]:
    """Complete top-level boxes ``(type, offset, length)`` up to the first torn one."""
    boxes: list[tuple[bytes, int, int]] = []
    offset = 0
    while offset + 8 <= size:
        f.seek(offset)
        head = f.read(16)
        length, kind = struct.unpack(">I4s", head[:8])
        if length == 1:
            if len(head) < 16:
                break
            (length,) = struct.unpack(">Q", head[8:16])
        elif length == 0:  # "to the end of the file": only a finished writer may leave that
            break
        if length < 8 or offset + length > size:
            break
        boxes.append((kind, offset, length))
        offset += length
    return boxes


def _decode(path: Path) -> tuple[int, int | None, Any]:
    """``(frames, last pts, time base)`` of the video stream, decoding every frame; raises on damage."""
    import av

    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        frames = 0
        last_pts: int | None = None
        for frame in container.decode(stream):
            frames += 1
            if frame.pts is not None:
                last_pts = frame.pts if last_pts is None else max(last_pts, frame.pts)
        return frames, last_pts, stream.time_base


def _copy_prefix(src: Path, dst: Path, length: int) -> None:
    with open(src, "rb") as fin, open(dst, "wb") as fout:
        remaining = length
        while remaining > 0:
            block = fin.read(min(_HASH_BLOCK, remaining))
            if not block:
                break
            fout.write(block)
            remaining -= len(block)
        fout.flush()
        os.fsync(fout.fileno())


def _repair_mp4(path: Path, keep_original: bool) -> tuple[int, int, int, int | None]:
    """Keep the whole fragments of a fragmented MP4 that decode: ``(frames, fragments, bytes cut, end µs)``.

    ``end µs`` is the last kept frame's pts in µs from the first frame. The file is removed (or
    kept as ``.torn``) when no fragment survives.
    """
    import av

    size = path.stat().st_size
    with open(path, "rb") as f:
        boxes = _mp4_boxes(f, size)
    header_end = 0
    cuts: list[int] = []  # end offset after each complete moof + mdat pair
    for i, (kind, offset, length) in enumerate(boxes):
        if kind == b"moof":
            if not header_end:
                header_end = offset
            continue
        if kind == b"mdat" and i > 0 and boxes[i - 1][0] == b"moof":
            cuts.append(offset + length)
    tmp = path.with_name(path.name + _TMP_SUFFIX)
    finished = bool(boxes) and boxes[-1][1] + boxes[-1][2] == size and boxes[-1][0] == b"mfra"
    candidates = [size] if finished else []
    candidates += cuts[::-1]
    for n_kept, cut in zip([len(cuts)] * finished + list(range(len(cuts), 0, -1)), candidates, strict=True):
        if cut == size:
            target = path
        else:
            _copy_prefix(path, tmp, cut)
            target = tmp
        try:
            frames, last_pts, time_base = _decode(target)
        except (av.error.FFmpegError, IndexError, ValueError) as exc:
            _log.info("%s: %d fragment(s) do not decode (%s); dropping one more", path, n_kept, exc)
            continue
        if frames == 0:
            continue
        if target is tmp:
            if keep_original:
                os.replace(path, path.with_name(path.name + TORN_SUFFIX))
            os.replace(tmp, path)
        end_us = None if last_pts is None else round(last_pts * time_base * 1_000_000)
        return frames, n_kept, size - cut, end_us
    tmp.unlink(missing_ok=True)
    if keep_original:
        os.replace(path, path.with_name(path.name + TORN_SUFFIX))
    else:
        path.unlink()
    return 0, 0, size, None


# --- the episode ------------------------------------------------------------------------------------


def interrupted(store: EpisodeStore) -> list[str]:
    """Ids of the drafts left in ``.incoming`` by a crash (or still recording), oldest first."""
    return [s.id for s in store.list(include_unfinished=True) if s.status == "interrupted"]


def _resolve(store: EpisodeStore, episode_id: str) -> str:
    everything = store.list(include_unfinished=True)
    ids = [s.id for s in everything if s.status == "interrupted"]
    matches = [i for i in ids if i == episode_id] or [i for i in ids if i.startswith(episode_id)]
    if len(matches) == 1:
        return matches[0]
    if len(matches) > 1:
        raise RecordingError(f"episode id prefix {episode_id!r} is ambiguous: {', '.join(matches)}")
    for s in everything:
        if s.id == episode_id or s.id.startswith(episode_id):
            raise RecordingError(
                f"episode {s.id} is {s.status}, not interrupted; only crashed drafts need repair"
            )
    raw = store.root / _INCOMING / episode_id
    if raw.is_dir():
        raise RecordingError(
            f"{raw} has no readable {_MANIFEST}, so it cannot be repaired; inspect it and delete it by hand"
        )
    available = ", ".join(ids) or "none"
    raise RecordingError(f"no interrupted episode {episode_id!r} in {store.root}. Interrupted: {available}")


@contextlib.contextmanager
def _locked(directory: Path) -> Iterator[None]:
    """Hold an exclusive flock on the draft directory; refuse if a live writer (or repair) holds it."""
    fd = os.open(directory, os.O_RDONLY)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN):
                raise RecordingError(
                    f"{directory} is locked by a running recorder or repair; stop it first"
                ) from None
            raise
        yield
    finally:
        os.close(fd)


def _newest_mtime_ns(directory: Path) -> int:
    return max((p.stat().st_mtime_ns for p in directory.rglob("*") if p.is_file()), default=0)


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(_HASH_BLOCK):
            digest.update(block)
    return digest.hexdigest()


def _finish_interrupted_commit(
    store: EpisodeStore, directory: Path, draft: EpisodeManifest
) -> EpisodeManifest | None:
    """A crash between writing the final manifest and the move: finish the move if every file verifies."""
    on_disk = {p.relative_to(directory).as_posix() for p in directory.rglob("*") if p.is_file()} - {_MANIFEST}
    if on_disk != {f.path for f in draft.files}:
        return None
    if any(_sha256(directory / f.path) != f.sha256 for f in draft.files):
        return None
    reopened = EpisodeDraft(store, draft.model_copy(update={"status": "recording"}), directory)
    if draft.status == "complete":
        return reopened.commit(draft.extra, end_ns=draft.end_ns)
    return reopened.abandon(
        draft.reason or "interrupted while being abandoned", draft.extra, end_ns=draft.end_ns
    )


def repair(
    store: EpisodeStore,
    episode_id: str,
    *,
    keep_originals: bool = False,
    min_idle_s: float = DEFAULT_MIN_IDLE_S,
) -> EpisodeManifest:
    """Commit the longest verified prefix of an episode interrupted by a crash.

    The draft in ``<root>/.incoming/<id>/`` is repaired in place, then committed to
    ``episodes/`` with status :data:`REPAIRED_STATUS`:

    - ``episode.mcap``: every message of every whole, CRC-checked chunk is rewritten into a new,
      valid MCAP with summary and footer (schemas, channels and metadata kept; the rewrite is
      read back and compared before it replaces the torn file). A log that is already complete
      is kept byte for byte.
    - ``cameras/<name>.mp4`` (fragmented): truncated after the last whole ``moof`` + ``mdat``
      fragment that decodes (checked by decoding every frame with PyAV); no bytes are
      re-encoded, so pts stay exact. A video with no whole fragment is removed.
    - Originals are deleted once their repair is verified, or kept next to it as
      ``<name>.torn`` (listed in the manifest) with ``keep_originals``.

    ``extra["repair"]`` records what was lost per stream and camera [s], measured from the last
    evidence that the episode ran: the newest timestamp recovered from any stream or video, or
    the newest file modification time when it is at most :data:`MTIME_EVIDENCE_S` later (a
    copied draft's times say nothing). So it is a lower bound. ``end_ns`` is the end of the
    recovered data. A draft whose final manifest was written but not moved (a crash inside
    commit) is moved as it was, if every file still matches its sha256.

    Args:
        store: The store holding the draft.
        episode_id: Full id or unique prefix of an interrupted episode.
        keep_originals: Keep torn originals as ``*.torn`` instead of deleting them.
        min_idle_s: Refuse a draft with a file modified less than this long ago [s] (it may still be
            recording); 0 disables the check.

    Raises:
        RecordingError: no such interrupted episode, it is still being written, or a rewrite does
            not verify (the draft is then left as it was, apart from ``*.repair-tmp`` files removed).
    """
    episode_id = _resolve(store, episode_id)
    directory = store.root / _INCOMING / episode_id
    with _locked(directory):
        idle_s = (time.time_ns() - _newest_mtime_ns(directory)) / 1e9
        if min_idle_s > 0 and idle_s < min_idle_s:
            raise RecordingError(
                f"episode {episode_id} was written {idle_s:.1f} s ago and may still be recording; "
                f"retry after {min_idle_s:g} s idle, or stop its recorder"
            )
        try:
            draft = EpisodeManifest.model_validate_json((directory / _MANIFEST).read_bytes())
        except (OSError, ValidationError) as exc:
            raise RecordingError(f"cannot read the draft manifest of {episode_id}: {exc}") from None
        for leftover in directory.rglob(f"*{_TMP_SUFFIX}"):
            leftover.unlink()
        (directory / (_MANIFEST + ".tmp")).unlink(missing_ok=True)
        if draft.status in ("complete", "incomplete"):
            moved = _finish_interrupted_commit(store, directory, draft)
            if moved is not None:
                _log.info("episode %s: finished its interrupted commit", episode_id)
                return moved
        return _repair_draft(store, directory, draft, keep_originals)


#: A sample stream with fewer messages than this is an event, not a stream, for the loss estimate.
_MIN_STREAM_MESSAGES = 2


def _repair_draft(
    store: EpisodeStore, directory: Path, draft: EpisodeManifest, keep_originals: bool
) -> EpisodeManifest:
    mtime_ns = _newest_mtime_ns(directory)
    mcap_path = directory / _MCAP
    mcap = _repair_mcap(mcap_path, keep_originals) if mcap_path.is_file() else None
    videos: list[tuple[str, int, int, int, int | None]] = []
    cameras = directory / _CAMERAS
    for video in sorted(cameras.glob("*.mp4")) if cameras.is_dir() else []:
        frames, fragments, dropped, end_us = _repair_mp4(video, keep_originals)
        videos.append((video.stem, frames, fragments, dropped, end_us))

    data_end = [draft.start_ns]
    if mcap is not None:
        data_end += mcap.last_log.values()
    video_reports: list[VideoRepair] = []
    for name, frames, fragments, dropped, end_us in videos:
        start = mcap.first_frame_ns.get(name) if mcap is not None else None
        end = None if start is None or end_us is None or frames == 0 else start + end_us * 1000
        if end is not None:
            data_end.append(end)
        video_reports.append(VideoRepair(name, frames, fragments, dropped, start, end, None))
    end_ns = max(data_end)
    evidence_ns = mtime_ns if end_ns < mtime_ns <= end_ns + round(MTIME_EVIDENCE_S * 1e9) else end_ns
    video_reports = [
        dataclasses.replace(v, lost_s=None if v.end_ns is None else (evidence_ns - v.end_ns) / 1e9)
        for v in video_reports
    ]
    streams = (
        [
            StreamRepair(
                t, mcap.counts[t], mcap.first_log[t], mcap.last_log[t], (evidence_ns - mcap.last_log[t]) / 1e9
            )
            for t in sorted(mcap.counts)
        ]
        if mcap is not None
        else []
    )
    extra = _extra(draft, mcap, streams, video_reports, evidence_ns)
    # Only sample streams say how long the episode ran on: a JSON event (an alert or a session
    # state, retained and published once at the start) is no stream, and its age is no loss.
    sampled = set(mcap.streams) if mcap is not None else set()
    lost = [s.lost_s for s in streams if s.topic in sampled and s.messages >= _MIN_STREAM_MESSAGES]
    lost += [v.lost_s for v in video_reports if v.lost_s is not None]
    reason = (
        f"repaired after a crash: kept {(end_ns - draft.start_ns) / 1e9:.1f} s, "
        f"lost at least {max(lost, default=0.0):.1f} s at the end"
    )
    manifest = _commit(EpisodeDraft(store, draft, directory), extra, end_ns, reason)
    _log.info("episode %s %s", manifest.id, reason)
    return manifest


def _extra(
    draft: EpisodeManifest,
    mcap: _McapResult | None,
    streams: list[StreamRepair],
    videos: list[VideoRepair],
    evidence_ns: int,
) -> dict[str, JsonValue]:
    summaries: list[dict[str, JsonValue]] = []
    if mcap is not None:
        for meter in mcap.streams.values():
            s = meter.summary()
            summaries.append(
                {
                    "name": s.name,
                    "expected_hz": s.expected_hz,
                    "measured_hz": s.measured_hz,
                    "messages": s.messages,
                    "drops": s.drops,
                    "max_gap_ms": s.max_gap_ms,
                }
            )
    # Read and rewritten through the typed model the runtime writes (a foreign extra is one line).
    typed = EpisodeExtra.of(draft).model_copy(
        update={
            "streams": summaries,
            "cameras": {
                v.name: CameraRecord(file=f"{_CAMERAS}/{v.name}.mp4", frames=v.frames)
                for v in videos
                if v.frames
            },
        }
    )
    extra = typed.to_json()
    extra["repair"] = {
        "repaired_ns": time.time_ns(),
        "last_evidence_ns": evidence_ns,
        "mcap": None
        if mcap is None
        else {
            "rewritten": mcap.rewritten,
            "bytes_before": mcap.bytes_before,
            "bytes_after": mcap.bytes_after,
        },
        "streams": {
            s.topic: {
                "messages": s.messages,
                "first_ns": s.first_ns,
                "last_ns": s.last_ns,
                "lost_s": s.lost_s,
            }
            for s in streams
        },
        "cameras": {
            v.name: {
                "frames": v.frames,
                "fragments": v.fragments,
                "bytes_dropped": v.bytes_dropped,
                "start_ns": v.start_ns,
                "end_ns": v.end_ns,
                "lost_s": v.lost_s,
            }
            for v in videos
        },
    }
    return extra


def _commit(draft: EpisodeDraft, extra: dict[str, JsonValue], end_ns: int, reason: str) -> EpisodeManifest:
    hook = getattr(draft, "commit_repaired", None)
    if hook is not None:
        manifest: EpisodeManifest = hook(reason, extra, end_ns=end_ns)
        return manifest
    # Until the store has the "repaired" status: a complete episode whose extra["repair"] says so.
    extra = {**extra, "repair": {**_as_dict(extra["repair"]), "reason": reason}}
    return draft.commit(extra, end_ns=end_ns)


def _as_dict(value: JsonValue) -> dict[str, JsonValue]:
    return value if isinstance(value, dict) else {}


def repair_all(
    store: EpisodeStore, *, keep_originals: bool = False, min_idle_s: float = DEFAULT_MIN_IDLE_S
) -> list[EpisodeManifest]:
    """Repair every interrupted episode of ``store`` (see :func:`repair`), oldest first; first finish the
    moves between ``episodes`` and ``failures`` a crash cut short
    (:meth:`~telerig.store.episodes.EpisodeStore.finish_interrupted_moves`)."""
    store.finish_interrupted_moves()
    return [
        repair(store, episode_id, keep_originals=keep_originals, min_idle_s=min_idle_s)
        for episode_id in interrupted(store)
    ]


# --- CLI --------------------------------------------------------------------------------------------


def add_repair_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``telerig repair``; pair with ``parser.set_defaults(handler=cmd_repair)``."""
    which = parser.add_mutually_exclusive_group(required=True)
    which.add_argument("episode_id", nargs="?", help="id (or unique prefix) of an interrupted episode")
    which.add_argument("--all", action="store_true", help="repair every interrupted episode")
    parser.add_argument("--data-root", type=Path, default=Path("telerig-data"))
    parser.add_argument(
        "--keep-originals", action="store_true", help="keep torn files as *.torn in the episode"
    )
    parser.add_argument(
        "--force",
        action="store_true",
        help=f"repair a draft written less than {DEFAULT_MIN_IDLE_S:g} s ago (its recorder must be dead)",
    )


def cmd_repair(args: argparse.Namespace) -> int:
    """``telerig repair [ID | --all] --data-root DIR``: print what each repair kept and lost.

    Also finishes the quality-gate moves between ``episodes`` and ``failures`` a crash cut short.
    """
    from rich.console import Console

    console = Console()
    for directory in remove_stale_broker_dirs():
        console.print(f"removed {directory}, left by an embedded broker that was killed", highlight=False)
    store = EpisodeStore(args.data_root)
    for moved in store.finish_interrupted_moves():  # quality-gate moves a crash cut short
        console.print(f"{moved.id}: finished its interrupted move to {moved.to}", highlight=False)
    ids = interrupted(store) if args.all else [args.episode_id]
    if not ids:
        console.print(f"no interrupted episodes in {args.data_root}")
        return 0
    min_idle = 0.0 if args.force else DEFAULT_MIN_IDLE_S
    failed = 0
    for episode_id in ids:
        try:
            manifest = repair(store, episode_id, keep_originals=args.keep_originals, min_idle_s=min_idle)
        except RecordingError as exc:
            if not args.all:
                raise
            console.print(f"[red]{episode_id}: {exc}[/]", highlight=False)
            failed += 1
            continue
        console.print(f"[green]{manifest.id}[/] {manifest.status}: {_losses_line(manifest)}", highlight=False)
    return 1 if failed else 0


def _losses_line(manifest: EpisodeManifest) -> str:
    report = _as_dict(manifest.extra.get("repair"))
    kept = f"kept {manifest.duration_s or 0.0:.2f} s"
    if not report:
        return f"{kept}; its commit had been interrupted, nothing lost"
    parts: list[str] = []
    for name, cam in _as_dict(report.get("cameras")).items():
        c = _as_dict(cam)
        lost = c.get("lost_s")
        parts.append(f"camera {name} {c.get('frames')} frames, lost {_secs(lost)}")
    streams = _as_dict(report.get("streams"))
    lost_streams = [v for v in (_as_dict(s).get("lost_s") for s in streams.values()) if isinstance(v, float)]
    if lost_streams:
        parts.append(f"{len(streams)} streams lost {min(lost_streams):.2f}-{max(lost_streams):.2f} s")
    return f"{kept}; " + "; ".join(parts or ["no data recovered"])


def _secs(value: JsonValue) -> str:
    return f"{value:.2f} s" if isinstance(value, (int, float)) else "unknown"
