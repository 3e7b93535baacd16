"""Resumable, verified episode upload, the upload-now-or-later policy and a persistent upload queue."""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import threading
import time
from collections.abc import Callable, Collection, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import TracebackType
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from telerig import priority
from telerig.errors import DependencyError, RecordingError
from telerig.store.episodes import EpisodeManifest, EpisodeStore
from telerig.store.remote import (
    ChecksumMismatchError,
    ObjectStore,
    UploadError,
    multipart_etag,
)

__all__ = [
    "EpisodeUploader",
    "Later",
    "Now",
    "RateLimiter",
    "StationLoad",
    "UploadCancelled",
    "UploadEvent",
    "UploadJob",
    "UploadPolicy",
    "UploadQueue",
    "UploadResult",
    "episode_size",
]

_log = logging.getLogger("telerig.store.upload")

_MiB = 1 << 20
_MANIFEST = "manifest.json"
_UPLOADS = ".uploads"
_QUEUE = "queue.jsonl"
#: S3 allows at most this many parts per object.
_MAX_PARTS = 10_000


class UploadCancelled(UploadError):  # noqa: N818 - reads as the event it is
    """The upload was stopped on request (queue paused or closed); it resumes where it stopped."""


# --------------------------------------------------------------------------------------------
# Bandwidth


class RateLimiter:
    """Paces sends to an average of ``bytes_per_s`` (the first send goes at once).

    Thread-safe. ``sleep`` returns early (True) when the caller should stop, e.g. an
    ``Event.wait``.
    """

    def __init__(
        self,
        bytes_per_s: float,
        *,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], object] = time.sleep,
    ) -> None:
        """Limit to ``bytes_per_s`` [bytes]/[s] (> 0)."""
        if not bytes_per_s > 0:
            raise ValueError(f"bytes_per_s must be > 0, got {bytes_per_s}")
        self._rate = float(bytes_per_s)
        self._clock = clock
        self._sleep = sleep
        self._next = -math.inf
        self._lock = threading.Lock()

    @property
    def bytes_per_s(self) -> float:
        """The limit [bytes]/[s]."""
        return self._rate

    def acquire(self, n: int, sleep: Callable[[float], object] | None = None) -> None:
        """Wait until ``n`` [bytes] may be sent without exceeding the average rate."""
        with self._lock:
            now = self._clock()
            start = max(self._next, now)
            self._next = start + n / self._rate
            wait = start - now
        if wait > 0:
            (sleep or self._sleep)(wait)


# --------------------------------------------------------------------------------------------
# Upload of one episode


@dataclass(frozen=True, slots=True)
class UploadEvent:
    """Progress of an upload, reported after each part or whole file.

    Attributes:
        episode_id: The episode.
        path: File path relative to the episode directory.
        part: Part number from 1 (1 for a file sent whole).
        parts: Number of parts of the file.
        nbytes: Bytes of this part [bytes].
        sent: ``True`` if the part was sent now, ``False`` if it was already stored.
    """

    episode_id: str
    path: str
    part: int
    parts: int
    nbytes: int
    sent: bool


@dataclass(frozen=True, slots=True)
class UploadResult:
    """An uploaded and verified episode.

    Attributes:
        episode_id: The episode.
        url: Where the episode now lives, e.g. ``s3://bucket/prefix/ep-...`` (store in the index).
        files: Files uploaded, manifest included.
        bytes_total: Size of those files [bytes].
        bytes_sent: Bytes sent by this call [bytes] (less than ``bytes_total`` after a resume).
        parts_sent: Parts (or whole files) sent by this call.
        parts_skipped: Parts (or whole files) already stored and not sent again.
        seconds: Wall time of this call [s].
    """

    episode_id: str
    url: str
    files: int
    bytes_total: int
    bytes_sent: int
    parts_sent: int
    parts_skipped: int
    seconds: float


def _read_manifest(path: Path) -> EpisodeManifest:
    try:
        return EpisodeManifest.model_validate_json(path.read_bytes())
    except OSError as exc:
        raise UploadError(
            f"cannot read {path}: {exc.strerror}; is this a committed episode directory?"
        ) from None
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"]) or "document"
        raise UploadError(f"{path} is not a valid manifest: {where}: {first['msg']}") from None


def episode_size(episode_dir: Path | str) -> int:
    """Total size of an episode's files from its manifest, manifest excluded [bytes]."""
    return sum(f.size for f in _read_manifest(Path(episode_dir) / _MANIFEST).files)


def _append_jsonl(path: Path, record: dict[str, Any]) -> None:
    with open(path, "a", encoding="utf-8") as f:
        f.write(json.dumps(record, separators=(",", ":")) + "\n")
        f.flush()
        os.fsync(f.fileno())


def _read_jsonl(path: Path) -> Iterator[dict[str, Any]]:
    """Records of a JSON-lines journal; a torn last line (crash mid-write) is skipped."""
    if not path.is_file():
        return
    with open(path, encoding="utf-8") as f:
        for number, line in enumerate(f, 1):
            if not line.endswith("\n"):
                _log.warning("%s: ignoring torn last line %d", path, number)
                return
            try:
                record = json.loads(line)
            except json.JSONDecodeError:
                _log.warning("%s: ignoring unreadable line %d", path, number)
                continue
            if isinstance(record, dict):
                yield record


@dataclass
class _Multipart:
    upload_id: str
    part_size: int
    sha256: str
    parts: dict[int, str] = field(default_factory=dict)  # number -> etag


@dataclass
class _FileState:
    multipart: _Multipart | None = None
    done_etag: str | None = None  # set when the object is stored: its expected ETag ("" if none)
    bad: bool = False  # failed verification: the stored object must not be trusted


class _EpisodeJournal:
    """Per-episode upload journal (JSON lines): multipart ids, stored parts, stored files.

    Records: ``{"op": "mpu", "path", "upload_id", "part_size", "sha256"}``,
    ``{"op": "part", "path", "upload_id", "n", "etag"}``, ``{"op": "file", "path", "etag"}``,
    ``{"op": "bad", "path"}`` (verification failed: send again) and ``{"op": "done", "url"}``.
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        self.files: dict[str, _FileState] = {}
        self.done_url: str | None = None
        for r in _read_jsonl(path):
            self._apply(r)

    def _apply(self, r: dict[str, Any]) -> None:
        op = r.get("op")
        state = self.files.setdefault(str(r.get("path", "")), _FileState())
        if op == "mpu":
            state.multipart = _Multipart(str(r["upload_id"]), int(r["part_size"]), str(r["sha256"]))
            state.done_etag = None
        elif op == "part" and state.multipart is not None and state.multipart.upload_id == r["upload_id"]:
            state.multipart.parts[int(r["n"])] = str(r["etag"])
        elif op == "file":
            state.done_etag = str(r["etag"])
            state.multipart = None
            state.bad = False
        elif op == "bad":
            state.done_etag = None
            state.multipart = None
            state.bad = True
            self.done_url = None
        elif op == "done":
            self.done_url = str(r["url"])

    def record(self, **r: Any) -> None:
        _append_jsonl(self.path, r)
        self._apply(r)


class EpisodeUploader:
    """Uploads committed episode directories to an :class:`ObjectStore`, resumably, and verifies them.

    Layout at the store: ``<base url>/<episode id>/<file path>``; ``manifest.json`` goes last,
    so a remote episode with a manifest is complete.

    How a re-run avoids sending data twice: a journal per episode
    (``<journal_dir>/<episode id>.jsonl``, fsynced after every record) lists multipart upload
    ids, stored parts with their ETags, and stored files. On resume the store's own part list
    (``ListParts``) is the authority: a journaled part is skipped if the store still has it with
    the same ETag, and a part the store has but the journal missed (crash between send and
    journal write) is skipped if its ETag equals the local part's MD5. A file already at the
    store with the manifest sha256 in its metadata is skipped even without a journal.

    How content is checked: (1) every request carries Content-MD5, so the server rejects bytes
    damaged in transit; (2) the local file is hashed while it is read and must equal the manifest
    sha256 before the multipart upload is completed (else it is aborted: nothing wrong becomes
    visible); (3) at the end every object's size, recorded sha256 metadata and ETag (MD5, or
    MD5-of-part-MD5s for multipart, where the backend has MD5 ETags) are compared with the
    local values, and objects up to ``readback_max_bytes`` are read back and hashed with SHA-256.
    A mismatch raises :class:`ChecksumMismatchError` and marks the file to be sent again.
    """

    def __init__(
        self,
        store: ObjectStore,
        journal_dir: Path | str,
        *,
        part_size: int = 8 * _MiB,
        multipart_threshold: int = 16 * _MiB,
        readback_max_bytes: int = 4 * _MiB,
        limiter: RateLimiter | None = None,
        progress: Callable[[UploadEvent], None] | None = None,
    ) -> None:
        """Upload to ``store``, journaling in ``journal_dir``.

        Args:
            store: Destination.
            journal_dir: Directory of the per-episode journals (e.g. ``<data root>/.uploads``).
            part_size: Multipart part size [bytes]; at least the store's minimum (5 MiB for S3);
                grown for files that would need more than 10000 parts.
            multipart_threshold: Files of at least this size go in parts [bytes].
            readback_max_bytes: Objects up to this size are read back and hashed [bytes]; 0: none.
            limiter: Bandwidth limit shared by every send; ``None``: unlimited.
            progress: Called after each part or file (also for parts skipped on resume). An
                exception raised in it stops the upload, which resumes on the next call.
        """
        if part_size < store.min_part_size:
            raise ValueError(f"part_size {part_size} is below the store minimum {store.min_part_size} bytes")
        if multipart_threshold < 1 or readback_max_bytes < 0:
            raise ValueError("multipart_threshold must be >= 1 and readback_max_bytes >= 0")
        self._store = store
        self._journal_dir = Path(journal_dir)
        self._part_size = part_size
        self._threshold = multipart_threshold
        self._readback = readback_max_bytes
        self._limiter = limiter
        self._progress = progress

    @property
    def store(self) -> ObjectStore:
        """The destination."""
        return self._store

    def url_for(self, episode_id: str) -> str:
        """Where episode ``episode_id`` goes."""
        return self._store.url_for(episode_id)

    def journal_path(self, episode_id: str) -> Path:
        """The episode's upload journal."""
        return self._journal_dir / f"{episode_id}.jsonl"

    def upload(self, episode_dir: Path | str, *, cancel: threading.Event | None = None) -> UploadResult:
        """Upload (or finish uploading) an episode, verify it, and return where it lives.

        Args:
            episode_dir: A committed (or abandoned) episode directory with its ``manifest.json``.
            cancel: When set, the upload stops between parts with :class:`UploadCancelled`.

        Raises:
            UploadError: The store failed or refused; re-running resumes.
            ChecksumMismatchError: A local file differs from its manifest, or a stored object from
                its file; the message names the files.
        """
        t0 = time.perf_counter()
        directory = Path(episode_dir)
        manifest_path = directory / _MANIFEST
        manifest = _read_manifest(manifest_path)
        if manifest.status == "recording":
            raise UploadError(f"episode {manifest.id} is still recording; commit it before uploading")
        self._store.check()
        self._journal_dir.mkdir(parents=True, exist_ok=True)
        journal = _EpisodeJournal(self.journal_path(manifest.id))
        manifest_bytes = manifest_path.read_bytes()
        manifest_sha = hashlib.sha256(manifest_bytes).hexdigest()
        stats = _Stats()
        for entry in manifest.files:
            self._upload_file(
                manifest.id, directory, entry.path, entry.size, entry.sha256, journal, stats, cancel
            )
        # The manifest goes last: a remote episode that has one is complete.
        self._upload_file(
            manifest.id, directory, _MANIFEST, len(manifest_bytes), manifest_sha, journal, stats, cancel
        )
        self._verify(manifest, manifest_sha, len(manifest_bytes), journal)
        url = self.url_for(manifest.id)
        if journal.done_url != url:
            journal.record(op="done", path="", url=url)
        total = sum(f.size for f in manifest.files) + len(manifest_bytes)
        result = UploadResult(
            episode_id=manifest.id,
            url=url,
            files=len(manifest.files) + 1,
            bytes_total=total,
            bytes_sent=stats.bytes_sent,
            parts_sent=stats.parts_sent,
            parts_skipped=stats.parts_skipped,
            seconds=time.perf_counter() - t0,
        )
        _log.info(
            "episode %s uploaded to %s: %.1f MB sent, %d parts sent, %d already stored, %.1f s",
            manifest.id, url, result.bytes_sent / 1e6, result.parts_sent, result.parts_skipped,
            result.seconds,
        )  # fmt: skip
        return result

    def verify(self, episode_dir: Path | str) -> None:
        """Check a finished upload against the local episode; raises :class:`ChecksumMismatchError`."""
        directory = Path(episode_dir)
        manifest = _read_manifest(directory / _MANIFEST)
        journal = _EpisodeJournal(self.journal_path(manifest.id))
        data = (directory / _MANIFEST).read_bytes()
        self._verify(manifest, hashlib.sha256(data).hexdigest(), len(data), journal)

    # -- internals ---------------------------------------------------------------------------

    def _emit(self, event: UploadEvent, cancel: threading.Event | None) -> None:
        if self._progress is not None:
            self._progress(event)
        if cancel is not None and cancel.is_set():
            raise UploadCancelled(f"upload of episode {event.episode_id} stopped; it resumes on the next run")

    def _send_wait(self, n: int, cancel: threading.Event | None) -> None:
        if cancel is not None and cancel.is_set():
            raise UploadCancelled("upload stopped before sending; it resumes on the next run")
        if self._limiter is not None:
            self._limiter.acquire(n, cancel.wait if cancel is not None else None)
            if cancel is not None and cancel.is_set():
                raise UploadCancelled("upload stopped while pacing; it resumes on the next run")

    def _upload_file(
        self,
        episode_id: str,
        directory: Path,
        path: str,
        size: int,
        sha256: str,
        journal: _EpisodeJournal,
        stats: _Stats,
        cancel: threading.Event | None,
    ) -> None:
        key = f"{episode_id}/{path}"
        local = directory / path
        state = journal.files.get(path, _FileState())
        if state.done_etag is not None:
            stats.skip(episode_id, path, 1, size, self, cancel)
            return
        # Without a journal entry, an object already stored with this size and sha256 is trusted
        # (e.g. the journal was lost); one that failed verification never is.
        info = None if state.bad else self._store.head(key)
        if info is not None and state.multipart is None and info.size == size and info.sha256 == sha256:
            journal.record(op="file", path=path, etag=info.etag or "")
            stats.skip(episode_id, path, 1, size, self, cancel)
            return
        try:
            actual_size = local.stat().st_size
        except OSError as exc:
            raise UploadError(f"cannot read {local}: {exc.strerror}; the episode is damaged") from None
        if actual_size != size:
            raise ChecksumMismatchError(
                f"{local} is {actual_size} bytes but its manifest says {size}; the episode changed "
                "after commit; run `telerig repair` on it"
            )
        if size < self._threshold:
            data = local.read_bytes()
            if hashlib.sha256(data).hexdigest() != sha256:
                raise ChecksumMismatchError(
                    f"{local} does not match its manifest sha256; the episode changed after commit; "
                    "run `telerig repair` on it"
                )
            self._send_wait(len(data), cancel)
            self._store.put(key, data, sha256=sha256)
            journal.record(op="file", path=path, etag=hashlib.md5(data).hexdigest())
            stats.sent(episode_id, path, 1, 1, size, self, cancel)
            return
        self._upload_multipart(episode_id, key, local, path, size, sha256, journal, stats, cancel)

    def _upload_multipart(
        self,
        episode_id: str,
        key: str,
        local: Path,
        path: str,
        size: int,
        sha256: str,
        journal: _EpisodeJournal,
        stats: _Stats,
        cancel: threading.Event | None,
    ) -> None:
        mpu = journal.files.get(path, _FileState()).multipart
        stored: dict[int, str] | None = None
        if mpu is not None and mpu.sha256 == sha256:
            stored = self._store.list_parts(key, mpu.upload_id)
            if stored is None:
                _log.info("multipart upload of %s is gone at the store; starting it again", key)
        if mpu is None or stored is None or mpu.sha256 != sha256:
            part_size = max(self._part_size, -(-size // _MAX_PARTS))
            upload_id = self._store.begin_multipart(key, sha256=sha256)
            journal.record(op="mpu", path=path, upload_id=upload_id, part_size=part_size, sha256=sha256)
            mpu = _Multipart(upload_id, part_size, sha256)
            stored = {}
        n_parts = max(1, -(-size // mpu.part_size))
        digest = hashlib.sha256()
        md5s: list[bytes] = []
        etags: list[tuple[int, str]] = []
        with open(local, "rb") as f:
            for number in range(1, n_parts + 1):
                data = f.read(mpu.part_size)
                digest.update(data)
                md5 = hashlib.md5(data)
                md5s.append(md5.digest())
                have = stored.get(number)
                journaled = mpu.parts.get(number)
                if have is not None and (
                    have == md5.hexdigest() if self._store.etag_is_md5 else have == journaled
                ):
                    etags.append((number, have))
                    stats.skip(episode_id, path, number, len(data), self, cancel, parts=n_parts)
                    continue
                self._send_wait(len(data), cancel)
                etag = self._store.put_part(key, mpu.upload_id, number, data)
                if self._store.etag_is_md5 and etag != md5.hexdigest():
                    raise UploadError(f"store returned ETag {etag} for part {number} of {key}; expected MD5")
                journal.record(op="part", path=path, upload_id=mpu.upload_id, n=number, etag=etag)
                etags.append((number, etag))
                stats.sent(episode_id, path, number, n_parts, len(data), self, cancel)
        if digest.hexdigest() != sha256:
            self._store.abort_multipart(key, mpu.upload_id)
            journal.record(op="bad", path=path)
            raise ChecksumMismatchError(
                f"{local} does not match its manifest sha256; the episode changed after commit; "
                "run `telerig repair` on it"
            )
        self._store.complete_multipart(key, mpu.upload_id, etags)
        journal.record(op="file", path=path, etag=multipart_etag(md5s))

    def _verify(
        self, manifest: EpisodeManifest, manifest_sha: str, manifest_size: int, j: _EpisodeJournal
    ) -> None:
        expected = [(f.path, f.size, f.sha256) for f in manifest.files] + [
            (_MANIFEST, manifest_size, manifest_sha)
        ]
        problems: list[str] = []
        for path, size, sha in expected:
            key = f"{manifest.id}/{path}"
            info = self._store.head(key)
            problem: str | None = None
            if info is None:
                problem = "missing"
            elif info.size != size:
                problem = f"{info.size} bytes, expected {size}"
            elif info.sha256 is not None and info.sha256 != sha:
                problem = "recorded sha256 differs"
            else:
                etag = j.files.get(path, _FileState()).done_etag
                if self._store.etag_is_md5 and info.etag and etag and info.etag != etag:
                    problem = f"ETag {info.etag}, expected {etag}"
                elif size <= self._readback and self._store.read_sha256(key) != sha:
                    problem = "content sha256 differs"
            if problem is not None:
                problems.append(f"{path} ({problem})")
                j.record(op="bad", path=path)
        if problems:
            raise ChecksumMismatchError(
                f"episode {manifest.id} at {self.url_for(manifest.id)} does not match: "
                f"{', '.join(problems)}; upload it again to resend these files"
            )


@dataclass
class _Stats:
    bytes_sent: int = 0
    parts_sent: int = 0
    parts_skipped: int = 0

    def sent(
        self,
        ep: str,
        path: str,
        n: int,
        parts: int,
        nbytes: int,
        up: EpisodeUploader,
        cancel: threading.Event | None,
    ) -> None:
        self.bytes_sent += nbytes
        self.parts_sent += 1
        up._emit(UploadEvent(ep, path, n, parts, nbytes, True), cancel)

    def skip(
        self,
        ep: str,
        path: str,
        n: int,
        nbytes: int,
        up: EpisodeUploader,
        cancel: threading.Event | None,
        parts: int = 1,
    ) -> None:
        self.parts_skipped += 1
        up._emit(UploadEvent(ep, path, n, parts, nbytes, False), cancel)


# --------------------------------------------------------------------------------------------
# Policy


@dataclass(frozen=True, slots=True)
class StationLoad:
    """A station's load over a short window.

    Attributes:
        cpu_percent: CPU use, all cores [%] (0-100).
        memory_percent: Memory in use [%] (0-100).
        net_sent_bytes_per_s: Network send rate, all interfaces [bytes]/[s].
        net_recv_bytes_per_s: Network receive rate, all interfaces [bytes]/[s].
    """

    cpu_percent: float
    memory_percent: float
    net_sent_bytes_per_s: float
    net_recv_bytes_per_s: float

    @classmethod
    def sample(cls, interval_s: float = 0.5) -> StationLoad:
        """Measure over ``interval_s`` [s] (blocks that long) with psutil."""
        try:
            import psutil
        except ImportError:
            raise DependencyError(
                "StationLoad.sample needs psutil; install it with `pip install psutil`"
            ) from None
        net0 = psutil.net_io_counters()
        t0 = time.monotonic()
        cpu = psutil.cpu_percent(interval=interval_s)
        net1 = psutil.net_io_counters()
        dt = max(time.monotonic() - t0, 1e-3)
        return cls(
            cpu_percent=cpu,
            memory_percent=psutil.virtual_memory().percent,
            net_sent_bytes_per_s=(net1.bytes_sent - net0.bytes_sent) / dt,
            net_recv_bytes_per_s=(net1.bytes_recv - net0.bytes_recv) / dt,
        )


@dataclass(frozen=True, slots=True)
class Now:
    """Upload now.

    Attributes:
        reason: Why, for the log.
    """

    reason: str


@dataclass(frozen=True, slots=True)
class Later:
    """Upload later.

    Attributes:
        reason: Why, for the log and the dashboard.
        retry_at: When to look again, Unix time [s].
    """

    reason: str
    retry_at: float


class UploadPolicy(BaseModel):
    """Decides at the end of a session whether to upload now or later, so the next session is not starved.

    An upload goes now when the station is quiet (CPU, memory and network below their limits)
    and it would finish within ``max_now_s`` at ``uplink_bytes_per_s``; an episode up to
    ``small_bytes`` goes now unless memory is short. Otherwise it is scheduled ``retry_after_s``
    later, when the queue checks the load again (:meth:`check_load`) and uploads once the station is
    quiet, paced by the queue's bandwidth limit.

    Attributes:
        max_cpu_percent: CPU above this [%] means busy.
        max_memory_percent: Memory above this [%] means busy, even for small uploads.
        max_net_bytes_per_s: Send + receive above this [bytes]/[s] means the network is busy.
        uplink_bytes_per_s: Expected upload rate to the store [bytes]/[s].
        max_now_s: Longest upload done right after a session [s].
        small_bytes: Uploads up to this size ignore CPU and network load [bytes].
        retry_after_s: Delay before looking again [s].
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    max_cpu_percent: float = Field(default=60.0, gt=0, le=100)
    max_memory_percent: float = Field(default=85.0, gt=0, le=100)
    max_net_bytes_per_s: float = Field(default=5e6, gt=0)
    uplink_bytes_per_s: float = Field(default=20e6, gt=0)
    max_now_s: float = Field(default=60.0, ge=0)
    small_bytes: int = Field(default=16 * _MiB, ge=0)
    retry_after_s: float = Field(default=600.0, gt=0)

    def check_load(self, load: StationLoad, *, now: float | None = None) -> Now | Later:
        """Whether the station is quiet enough to upload, whatever the size."""
        t = time.time() if now is None else now
        if load.memory_percent > self.max_memory_percent:
            return Later(
                f"memory {load.memory_percent:.0f}% > {self.max_memory_percent:.0f}%", t + self.retry_after_s
            )
        if load.cpu_percent > self.max_cpu_percent:
            return Later(f"cpu {load.cpu_percent:.0f}% > {self.max_cpu_percent:.0f}%", t + self.retry_after_s)
        net = load.net_sent_bytes_per_s + load.net_recv_bytes_per_s
        if net > self.max_net_bytes_per_s:
            return Later(
                f"network {net / 1e6:.1f} MB/s > {self.max_net_bytes_per_s / 1e6:.1f} MB/s",
                t + self.retry_after_s,
            )
        return Now("station idle")

    def decide(self, size_bytes: int, load: StationLoad, *, now: float | None = None) -> Now | Later:
        """Upload an episode of ``size_bytes`` [bytes] now, or later (with the reason and when)?"""
        if size_bytes < 0:
            raise ValueError(f"size_bytes must be >= 0, got {size_bytes}")
        t = time.time() if now is None else now
        if size_bytes <= self.small_bytes:
            if load.memory_percent > self.max_memory_percent:
                return self.check_load(load, now=t)
            return Now(f"small ({size_bytes / 1e6:.1f} MB)")
        eta = size_bytes / self.uplink_bytes_per_s
        if eta > self.max_now_s:
            return Later(
                f"{size_bytes / 1e6:.0f} MB needs ~{eta:.0f} s at {self.uplink_bytes_per_s / 1e6:.0f} MB/s "
                f"(> {self.max_now_s:.0f} s); deferred to idle time",
                t + self.retry_after_s,
            )
        return self.check_load(load, now=t)


# --------------------------------------------------------------------------------------------
# Queue


@dataclass(frozen=True, slots=True)
class UploadJob:
    """A queued episode upload.

    Attributes:
        episode_id: The episode (one job per episode).
        episode_dir: Its directory.
        size_bytes: Its size [bytes].
        not_before: Earliest start, Unix time [s].
        attempts: Failed attempts so far.
        reason: Why it waits (policy decision or last error).
        urgent: Asked for now (``upload: now``): the station-load check does not hold it back.
    """

    episode_id: str
    episode_dir: Path
    size_bytes: int
    not_before: float
    attempts: int = 0
    reason: str = ""
    urgent: bool = False


class UploadQueue:
    """Episode uploads persisted in ``<root>/.uploads/queue.jsonl``, run by a background worker.

    The journal is append-only JSON lines (``add``, ``wait``, ``fail``, ``done``), fsynced per
    record and compacted on open, so pending uploads survive a crash or restart; an upload cut
    short resumes from the uploader's per-episode journal. The worker takes due jobs oldest first,
    asks the policy whether the station is quiet (:meth:`UploadPolicy.check_load`), uploads with
    the uploader's bandwidth limit, and backs off exponentially on failure. :meth:`pause` (e.g.
    while a session records) stops the current upload between parts; :meth:`resume` lets it go on.
    One queue per data root: the journal is not shared between processes.
    """

    def __init__(
        self,
        root: Path | str,
        uploader: EpisodeUploader,
        *,
        policy: UploadPolicy | None = None,
        sample_load: Callable[[], StationLoad] = StationLoad.sample,
        on_uploaded: Callable[[UploadResult], None] | None = None,
        clock: Callable[[], float] = time.time,
        backoff_s: float = 30.0,
        max_backoff_s: float = 3600.0,
        poll_s: float = 5.0,
    ) -> None:
        """Open (or create) the queue of data root ``root``; nothing starts until :meth:`start`.

        Args:
            root: Data root (the episode store root); the journal is ``<root>/.uploads/queue.jsonl``.
            uploader: Does the uploads; give it a :class:`RateLimiter` to cap bandwidth.
            policy: Upload-now-or-later rules.
            sample_load: Station load probe (inject a fake in tests).
            on_uploaded: Called with each verified upload (record ``result.url`` as the episode's
                location); if it raises, the job is retried later and the upload is not redone.
            clock: Unix time [s].
            backoff_s: First retry delay after a failure [s]; doubles per failure.
            max_backoff_s: Longest retry delay [s].
            poll_s: Longest idle sleep of the worker [s].
        """
        self._root = Path(root)
        self._dir = self._root / _UPLOADS
        self._path = self._dir / _QUEUE
        self._uploader = uploader
        self._policy = policy or UploadPolicy()
        self._sample_load = sample_load
        self._on_uploaded = on_uploaded
        self._clock = clock
        self._backoff = backoff_s
        self._max_backoff = max_backoff_s
        self._poll = poll_s
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._cancel = threading.Event()
        self._paused = False
        self._thread: threading.Thread | None = None
        self._jobs: dict[str, UploadJob] = {}
        self._dir.mkdir(parents=True, exist_ok=True)
        for r in _read_jsonl(self._path):
            self._apply(r)
        self._compact()

    # -- journal -----------------------------------------------------------------------------

    def _apply(self, r: dict[str, Any]) -> None:
        op, episode_id = r.get("op"), str(r.get("episode_id", ""))
        job = self._jobs.get(episode_id)
        if op == "add":
            self._jobs[episode_id] = UploadJob(
                episode_id,
                Path(r["episode_dir"]),
                int(r["size"]),
                float(r["not_before"]),
                0,
                str(r["reason"]),
                bool(r.get("urgent", False)),
            )
        elif job is not None and op == "wait":
            self._jobs[episode_id] = replace(job, not_before=float(r["not_before"]), reason=str(r["reason"]))
        elif job is not None and op == "fail":
            self._jobs[episode_id] = replace(
                job, not_before=float(r["not_before"]), reason=str(r["reason"]), attempts=job.attempts + 1
            )
        elif op == "done":
            self._jobs.pop(episode_id, None)

    def _record(self, **r: Any) -> None:
        with self._lock:
            _append_jsonl(self._path, r)
            self._apply(r)

    def _compact(self) -> None:
        lines: list[str] = []
        for job in self._jobs.values():
            add = {
                "op": "add", "episode_id": job.episode_id, "episode_dir": str(job.episode_dir),
                "size": job.size_bytes, "not_before": job.not_before, "reason": job.reason,
                "urgent": job.urgent,
            }  # fmt: skip
            lines.append(json.dumps(add, separators=(",", ":")))
            lines.extend(
                json.dumps({"op": "fail", "episode_id": job.episode_id, "not_before": job.not_before,
                            "reason": job.reason}, separators=(",", ":"))
                for _ in range(job.attempts)
            )  # fmt: skip
        tmp = self._path.with_name(_QUEUE + ".tmp")
        with open(tmp, "w", encoding="utf-8") as f:
            f.write("".join(line + "\n" for line in lines))
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, self._path)

    # -- public ------------------------------------------------------------------------------

    @property
    def path(self) -> Path:
        """The queue journal."""
        return self._path

    def pending(self) -> list[UploadJob]:
        """Jobs not yet uploaded, earliest start first."""
        with self._lock:
            return sorted(self._jobs.values(), key=lambda j: (j.not_before, j.episode_id))

    def submit(
        self, episode_dir: Path | str, *, load: StationLoad | None = None, now: bool = False
    ) -> Now | Later:
        """Queue an episode, deciding with the policy whether it goes now or later.

        Args:
            episode_dir: A committed episode directory.
            load: Station load; sampled when ``None``.
            now: Skip the policy (an operator asked for it).

        Returns:
            The decision; a ``Now`` job is due immediately, a ``Later`` one at ``retry_at``.
        """
        directory = Path(episode_dir).absolute()
        manifest = _read_manifest(directory / _MANIFEST)
        size = sum(f.size for f in manifest.files)
        t = self._clock()
        decision: Now | Later = (
            Now("requested")
            if now
            else self._policy.decide(size, self._sample_load() if load is None else load, now=t)
        )
        not_before = t if isinstance(decision, Now) else decision.retry_at
        self._record(
            op="add", episode_id=manifest.id, episode_dir=str(directory), size=size,
            not_before=not_before, reason=decision.reason, urgent=now,
        )  # fmt: skip
        _log.info(
            "episode %s queued for upload (%s): %s", manifest.id, type(decision).__name__, decision.reason
        )
        self._wake.set()
        return decision

    def run_pending(self, *, ignore_load: bool = False) -> list[UploadResult]:
        """Upload every due job in the calling thread (CLI, tests); returns what was uploaded."""
        results: list[UploadResult] = []
        tried: set[str] = set()
        while (job := self._next_due(exclude=tried)) is not None:
            tried.add(job.episode_id)
            result = self._run(job, ignore_load=ignore_load)
            if result is not None:
                results.append(result)
        return results

    def start(self) -> None:
        """Start the background worker (idempotent)."""
        if self._thread is not None:
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._loop, name="telerig-upload", daemon=True)
        self._thread.start()

    def pause(self) -> None:
        """Stop uploading (the current upload stops between parts) until :meth:`resume`."""
        with self._lock:
            self._paused = True
        self._cancel.set()

    def resume(self) -> None:
        """Let the worker upload again."""
        with self._lock:
            self._paused = False
        self._cancel.clear()
        self._wake.set()

    @property
    def paused(self) -> bool:
        """Whether :meth:`pause` is in effect."""
        return self._paused

    def close(self, timeout_s: float = 30.0) -> None:
        """Stop the worker, interrupting the current upload between parts (idempotent)."""
        self._stop.set()
        self._cancel.set()
        self._wake.set()
        thread, self._thread = self._thread, None
        if thread is not None:
            thread.join(timeout_s)
            if thread.is_alive():
                _log.warning("upload worker did not stop within %.0f s", timeout_s)

    def __enter__(self) -> UploadQueue:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    # -- worker ------------------------------------------------------------------------------

    def _next_due(self, exclude: Collection[str] = ()) -> UploadJob | None:
        t = self._clock()
        due = [j for j in self.pending() if j.not_before <= t and j.episode_id not in exclude]
        return due[0] if due else None

    def _run(self, job: UploadJob, *, ignore_load: bool = False) -> UploadResult | None:
        try:
            if not ignore_load:
                decision = self._policy.check_load(self._sample_load(), now=self._clock())
                if isinstance(decision, Later):
                    self._record(
                        op="wait",
                        episode_id=job.episode_id,
                        not_before=decision.retry_at,
                        reason=decision.reason,
                    )
                    _log.info("upload of %s waits: %s", job.episode_id, decision.reason)
                    return None
            result = self._uploader.upload(self._episode_dir(job), cancel=self._cancel)
            if self._on_uploaded is not None:
                self._on_uploaded(result)
        except UploadCancelled:
            _log.info("upload of %s paused; it resumes later", job.episode_id)
            return None
        except Exception as exc:  # any failure is retried with back-off; the worker must live on
            delay = min(self._max_backoff, self._backoff * 2**job.attempts)
            reason = f"{type(exc).__name__}: {exc}"
            self._record(
                op="fail", episode_id=job.episode_id, not_before=self._clock() + delay, reason=reason
            )
            _log.warning("upload of %s failed (%s); retry in %.0f s", job.episode_id, reason, delay)
            return None
        self._record(op="done", episode_id=job.episode_id, url=result.url)
        return result

    def _episode_dir(self, job: UploadJob) -> Path:
        """Where the job's episode lies now: a quality gate may have moved it between ``episodes`` and
        ``failures`` since it was queued (failures are uploaded too: they train recovery policies)."""
        if job.episode_dir.is_dir():
            return job.episode_dir
        try:
            return EpisodeStore(self._root).find(job.episode_id).path
        except RecordingError:
            return job.episode_dir  # gone: the upload fails and says which file it missed

    def _loop(self) -> None:
        priority.enter("work")  # below the control loop; hashing and sending take whole cores
        while not self._stop.is_set():
            self._wake.clear()
            job = None if self._paused else self._next_due()
            if job is None:
                pending = self.pending()
                wait = self._poll
                if pending and not self._paused:
                    wait = min(wait, max(0.0, pending[0].not_before - self._clock()))
                self._wake.wait(wait)
                continue
            self._run(job, ignore_load=job.urgent)
