"""Episode store on local disk: drafts in ``.incoming``, atomic commit to ``episodes``, failures kept.

Quality gates (:mod:`telerig.qa`) move a committed episode they reject to ``failures`` and back
(:meth:`EpisodeStore.move_to_failures`, :meth:`EpisodeStore.restore_from_failures`); its files and
manifest never change, a ``failure.json`` beside them holds the reasons.
"""

from __future__ import annotations

import builtins
import contextlib
import fcntl
import hashlib
import logging
import os
import re
import secrets
import time
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from types import TracebackType
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, JsonValue, TypeAdapter, ValidationError

from telerig.errors import RecordingError
from telerig.ir.types import now_ns

__all__ = [
    "MANIFEST_FORMAT",
    "EpisodeDraft",
    "EpisodeManifest",
    "EpisodeStatus",
    "EpisodeStore",
    "EpisodeSummary",
    "FAILURE_FILE",
    "FailureRecord",
    "FileEntry",
    "MoveRecovery",
    "Partition",
    "check_episode_id",
]

_log = logging.getLogger("telerig.store.episodes")

#: Version of the ``manifest.json`` layout.
MANIFEST_FORMAT = 1
#: ``recording`` is only ever on disk in ``.incoming``; :meth:`EpisodeStore.list` reports such a
#: draft as ``interrupted``. ``repaired``: the verified prefix of an interrupted episode, committed
#: by ``telerig repair`` (:mod:`telerig.store.repair`) into ``episodes/``.
EpisodeStatus = Literal["recording", "complete", "repaired", "incomplete", "interrupted"]

_MANIFEST = "manifest.json"
#: Space a draft holds so that finishing it (writing the manifest) works on a full disk.
_RESERVE = ".reserve"
_RESERVE_BYTES = 64 * 1024
_MCAP = "episode.mcap"
_CAMERAS = "cameras"
_INCOMING = ".incoming"
_EPISODES = "episodes"
_INCOMPLETE = "incomplete"
_FAILURES = "failures"
#: The reasons of an episode in the failures partition, beside its files (not in its manifest).
FAILURE_FILE = "failure.json"
#: Lock file under the root: moves between ``episodes`` and ``failures`` (and their recovery) take it.
_PARTITION_LOCK = ".partitions.lock"
#: Where an episode lies under the root: ``episodes`` (committed), ``failures`` (committed, rejected
#: by a quality gate), ``incomplete`` (abandoned) or ``.incoming`` (a draft, or one left by a crash).
Partition = Literal["episodes", "failures", "incomplete", ".incoming"]
_ID = re.compile(r"^ep-\d{8}-\d{6}-[0-9a-f]{4}$")
_NAME = re.compile(r"^[A-Za-z0-9_.\-]+$")
_HASH_BLOCK = 1 << 20
_MAX_LISTED_IDS = 10
_EXTRA: TypeAdapter[dict[str, JsonValue]] = TypeAdapter(dict[str, JsonValue])


class FileEntry(BaseModel):
    """One file of an episode.

    Attributes:
        path: Path relative to the episode directory, ``/``-separated, e.g. ``cameras/wrist.mp4``.
        size: Size [bytes].
        sha256: Hex SHA-256 of the content.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    path: str
    size: int
    sha256: str


class EpisodeManifest(BaseModel):
    """The ``manifest.json`` of an episode.

    Attributes:
        format: Manifest layout version (:data:`MANIFEST_FORMAT`).
        id: Episode id, ``ep-YYYYMMDD-HHMMSS-xxxx`` (UTC start time + random hex).
        rig: Rig name.
        task: Task name or instruction.
        operator: Operator id.
        status: ``recording`` while a draft, then ``complete``, ``repaired`` or ``incomplete``.
        start_ns: Recording start, common clock [ns].
        end_ns: Recording end [ns]; ``None`` while recording.
        duration_s: ``end_ns - start_ns`` [s]; ``None`` while recording.
        reason: Why the episode is incomplete, or what a repair lost; ``None`` otherwise.
        files: Every file of the episode except the manifest, sorted by path.
        extra: Caller data, e.g. stream stats and camera frame counts.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    format: int = MANIFEST_FORMAT
    id: str
    rig: str
    task: str
    operator: str
    status: EpisodeStatus
    start_ns: int
    end_ns: int | None = None
    duration_s: float | None = None
    reason: str | None = None
    files: tuple[FileEntry, ...] = ()
    extra: dict[str, JsonValue] = Field(default_factory=dict)


class EpisodeSummary(BaseModel):
    """What :meth:`EpisodeStore.list` shows of an episode.

    Attributes:
        path: The episode directory.
        files: Files listed in the manifest (empty for an unfinished draft).
        partition: Where it lies (:data:`Partition`): ``failures`` for a committed episode a quality
            gate rejected (its status stays the manifest's ``complete`` or ``repaired``).
        (the rest as in :class:`EpisodeManifest`; status ``interrupted`` for a draft left by a crash)
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    id: str
    status: EpisodeStatus
    rig: str
    task: str
    operator: str
    start_ns: int
    end_ns: int | None
    duration_s: float | None
    reason: str | None
    files: tuple[FileEntry, ...]
    path: Path
    partition: Partition


class FailureRecord(BaseModel):
    """The ``failure.json`` of an episode in the failures partition.

    Attributes:
        id: Episode id.
        reasons: Why it was rejected, one line each (e.g. the failed gates with value and threshold).
        moved_ns: When it was moved, wall clock [ns].
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    format: int = 1
    id: str
    reasons: tuple[str, ...]
    moved_ns: int


class MoveRecovery(BaseModel):
    """A move between ``episodes`` and ``failures`` that a crash interrupted, finished by
    :meth:`EpisodeStore.finish_interrupted_moves`: ``to`` is where the episode lies now."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    id: str
    to: Literal["episodes", "failures"]


def check_episode_id(episode_id: str) -> str:
    """``episode_id`` if it is a full episode id (``ep-YYYYMMDD-HHMMSS-xxxx``); no path can pass.

    Raises:
        RecordingError: anything else, e.g. ``../x``.
    """
    if not isinstance(episode_id, str) or not _ID.match(episode_id):
        raise RecordingError(f"{episode_id!r} is not an episode id (ep-YYYYMMDD-HHMMSS-xxxx)")
    return episode_id


def _new_id(start_ns: int) -> str:
    stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime(start_ns / 1e9))
    return f"ep-{stamp}-{secrets.token_hex(2)}"


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _write_json_atomic(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    try:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise RecordingError(f"cannot write {path}: {exc.strerror or exc}") from exc
    _fsync_dir(path.parent)


def _hash_and_sync(path: Path) -> tuple[int, str]:
    digest = hashlib.sha256()
    size = 0
    with open(path, "rb") as f:
        while block := f.read(_HASH_BLOCK):
            digest.update(block)
            size += len(block)
        os.fsync(f.fileno())  # the writer may not have; the commit must not outrun the data
    return size, digest.hexdigest()


def _read_manifest(path: Path) -> EpisodeManifest:
    try:
        return EpisodeManifest.model_validate_json(path.read_bytes())
    except OSError as exc:
        raise RecordingError(f"cannot read {path}: {exc.strerror}") from None
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"]) or "document"
        raise RecordingError(f"{path} is not a valid manifest: {where}: {first['msg']}") from None


class EpisodeDraft:
    """An episode being recorded in ``<root>/.incoming/<id>/``; end it with :meth:`commit` or :meth:`abandon`.

    Obtain one from :meth:`EpisodeStore.begin`. Writers put the MCAP log at :attr:`mcap_path`
    and camera videos at :meth:`camera_path`; any other file placed in :attr:`dir` is listed in
    the manifest too.
    """

    def __init__(self, store: EpisodeStore, manifest: EpisodeManifest, directory: Path) -> None:
        self._store = store
        self._manifest = manifest
        self._dir = directory
        self._state: Literal["open", "committed", "abandoned"] = "open"

    @property
    def id(self) -> str:
        """Episode id."""
        return self._manifest.id

    @property
    def dir(self) -> Path:
        """Draft directory (in ``.incoming``; it moves on commit or abandon)."""
        return self._dir

    @property
    def start_ns(self) -> int:
        """Recording start, common clock [ns]."""
        return self._manifest.start_ns

    @property
    def state(self) -> Literal["open", "committed", "abandoned"]:
        """``open`` until :meth:`commit` or :meth:`abandon`."""
        return self._state

    @property
    def mcap_path(self) -> Path:
        """Where the episode's MCAP log goes."""
        return self._dir / _MCAP

    def camera_path(self, name: str) -> Path:
        """Where camera ``name``'s video goes (``cameras/<name>.mp4``); creates ``cameras/``."""
        if not _NAME.match(name):
            raise ValueError(f"camera name {name!r} must use only letters, digits, '_', '-', '.'")
        cameras = self._dir / _CAMERAS
        cameras.mkdir(exist_ok=True)
        return cameras / f"{name}.mp4"

    def commit(
        self, manifest_extra: Mapping[str, JsonValue] | None = None, *, end_ns: int | None = None
    ) -> EpisodeManifest:
        """Write the final manifest and atomically move the episode to ``<root>/episodes/<id>/``.

        Args:
            manifest_extra: Caller data stored under ``extra`` (stream stats, frame counts...).
            end_ns: Recording end, common clock [ns]; now when ``None``.

        Returns:
            The committed manifest.
        """
        return self._finish("complete", None, manifest_extra, end_ns)

    def abandon(
        self, reason: str, manifest_extra: Mapping[str, JsonValue] | None = None, *, end_ns: int | None = None
    ) -> EpisodeManifest:
        """Keep the draft as a failure: move it to ``<root>/incomplete/<id>/`` with status and ``reason``."""
        if not reason:
            raise ValueError("abandon() needs a reason")
        return self._finish("incomplete", reason, manifest_extra, end_ns)

    def commit_repaired(
        self, reason: str, manifest_extra: Mapping[str, JsonValue] | None = None, *, end_ns: int | None = None
    ) -> EpisodeManifest:
        """Commit the recovered prefix of an interrupted episode to ``episodes/`` with status ``repaired``.

        Used by :func:`telerig.store.repair.repair`; ``reason`` says what the crash cost.
        """
        if not reason:
            raise ValueError("commit_repaired() needs a reason")
        return self._finish("repaired", reason, manifest_extra, end_ns)

    def __enter__(self) -> EpisodeDraft:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        """Abandon a draft still open: with the exception as reason, or as not committed."""
        if self._state == "open" and self._dir.is_dir():
            reason = "left without commit" if exc is None else f"{type(exc).__name__}: {exc}"
            self.abandon(reason)

    def _finish(
        self,
        status: Literal["complete", "repaired", "incomplete"],
        reason: str | None,
        extra: Mapping[str, JsonValue] | None,
        end_ns: int | None,
    ) -> EpisodeManifest:
        if self._state != "open":
            raise RecordingError(f"episode {self.id} is already {self._state}")
        try:
            # What the draft carried from begin() (e.g. the rig fingerprint) stays unless overridden.
            extra_json = _EXTRA.validate_python({**self._manifest.extra, **dict(extra or {})})
        except ValidationError as exc:
            first = exc.errors()[0]
            where = ".".join(str(p) for p in first["loc"])
            raise ValueError(f"manifest_extra is not JSON data at {where}: {first['msg']}") from None
        if not self._dir.is_dir():
            raise RecordingError(f"draft directory {self._dir} is gone; cannot finish episode {self.id}")
        # Free the space reserved at begin() so the manifest can be written even on a full disk.
        (self._dir / _RESERVE).unlink(missing_ok=True)
        end = now_ns() if end_ns is None else end_ns
        files = tuple(
            FileEntry(path=p.relative_to(self._dir).as_posix(), size=size, sha256=digest)
            for p in sorted(self._dir.rglob("*"))
            if p.is_file() and p.name not in (_MANIFEST, _MANIFEST + ".tmp")
            for size, digest in [_hash_and_sync(p)]
        )
        manifest = self._manifest.model_copy(
            update={
                "status": status,
                "end_ns": end,
                "duration_s": (end - self._manifest.start_ns) / 1e9,
                "reason": reason,
                "files": files,
                "extra": extra_json,
            }
        )
        _write_json_atomic(self._dir / _MANIFEST, manifest.model_dump_json(indent=2))
        for sub in (p for p in self._dir.rglob("*") if p.is_dir()):
            _fsync_dir(sub)
        target_root = self._store.root / (_INCOMPLETE if status == "incomplete" else _EPISODES)
        target_root.mkdir(parents=True, exist_ok=True)
        target = target_root / self.id
        if target.exists():
            raise RecordingError(f"{target} already exists; refusing to overwrite an episode")
        os.rename(self._dir, target)
        _fsync_dir(target_root)
        _fsync_dir(self._dir.parent)
        self._dir = target
        self._manifest = manifest
        self._state = "abandoned" if status == "incomplete" else "committed"
        _log.info("episode %s %s in %s", self.id, status, target)
        return manifest


class EpisodeStore:
    """Episodes under one root directory.

    Layout::

        <root>/.incoming/<id>/     drafts being recorded (left here by a crash: "interrupted")
        <root>/episodes/<id>/      committed episodes: manifest.json, episode.mcap, cameras/*.mp4
        <root>/failures/<id>/      committed episodes a quality gate rejected, + failure.json (reasons)
        <root>/incomplete/<id>/    abandoned episodes, with the reason in their manifest

    Committed and abandoned episodes are never deleted by the store, and the files their manifest
    lists never change; a move between ``episodes`` and ``failures`` is one ``rename``.
    """

    def __init__(self, root: Path | str) -> None:
        """Use ``root`` (created on the first :meth:`begin`)."""
        self._root = Path(root)

    @property
    def root(self) -> Path:
        """The store's root directory."""
        return self._root

    def begin(
        self,
        *,
        rig: str,
        task: str,
        operator: str,
        start_ns: int | None = None,
        extra: Mapping[str, JsonValue] | None = None,
        episode_id: str | None = None,
    ) -> EpisodeDraft:
        """Create a draft episode in ``<root>/.incoming/<id>/``.

        Args:
            rig: Rig name.
            task: Task name or instruction.
            operator: Operator id.
            start_ns: Recording start, common clock [ns]; now when ``None``. Also names the id.
            extra: Data the draft manifest carries from the start (e.g. the rig fingerprint), so a
                repair after a crash keeps it.
            episode_id: Id to file the episode under (``ep-YYYYMMDD-HHMMSS-xxxx``), e.g. the session
                coordinator's, so every station of a multi-station rig uses the same id; a new id
                when ``None``.

        Raises:
            RecordingError: ``episode_id`` is malformed or already in this store.
        """
        for field, value in (("rig", rig), ("task", task), ("operator", operator)):
            if not value:
                raise ValueError(f"{field} must be a non-empty string")
        start = now_ns() if start_ns is None else start_ns
        incoming = self._root / _INCOMING
        incoming.mkdir(parents=True, exist_ok=True)
        if episode_id is None:
            episode_id, directory = self._new_draft_dir(incoming, start)
        else:
            if not _ID.match(episode_id):
                raise RecordingError(f"episode id {episode_id!r} is not of the form ep-YYYYMMDD-HHMMSS-xxxx")
            directory = incoming / episode_id
            if self._find_dir(episode_id) is not None or directory.exists():
                raise RecordingError(f"episode {episode_id} is already in {self._root}; use a new id")
            directory.mkdir()
        manifest = EpisodeManifest(
            id=episode_id,
            rig=rig,
            task=task,
            operator=operator,
            status="recording",
            start_ns=start,
            extra=_EXTRA.validate_python(dict(extra or {})),
        )
        (directory / _RESERVE).write_bytes(bytes(_RESERVE_BYTES))
        _write_json_atomic(directory / _MANIFEST, manifest.model_dump_json(indent=2))
        _fsync_dir(incoming)
        _log.info("episode %s begins in %s", episode_id, directory)
        return EpisodeDraft(self, manifest, directory)

    def _new_draft_dir(self, incoming: Path, start_ns: int) -> tuple[str, Path]:
        for _ in range(100):
            episode_id = _new_id(start_ns)
            if self._find_dir(episode_id) is not None:
                continue
            directory = incoming / episode_id
            try:
                directory.mkdir()
            except FileExistsError:
                continue
            return episode_id, directory
        raise RecordingError(f"could not allocate a free episode id in {self._root}")  # pragma: no cover

    def list(
        self, *, include_unfinished: bool = False, include_failures: bool = False
    ) -> list[EpisodeSummary]:
        """Committed episodes, oldest first; each says its :attr:`~EpisodeSummary.partition`.

        Args:
            include_unfinished: Every episode: also failures, incomplete and interrupted ones.
            include_failures: Also committed episodes a quality gate moved to ``failures``.
        """
        partitions: list[Partition] = ["episodes"]
        if include_failures or include_unfinished:
            partitions.append("failures")
        if include_unfinished:
            partitions += ["incomplete", ".incoming"]
        out: list[EpisodeSummary] = []
        for partition in partitions:
            base = self._root / partition
            if not base.is_dir():
                continue
            for directory in base.iterdir():
                if not directory.is_dir() or not _ID.match(directory.name):
                    continue
                try:
                    m = _read_manifest(directory / _MANIFEST)
                except RecordingError as exc:
                    _log.warning("skipping %s: %s", directory, exc)
                    continue
                status: EpisodeStatus = "interrupted" if partition == _INCOMING else m.status
                out.append(
                    EpisodeSummary(
                        id=m.id,
                        status=status,
                        rig=m.rig,
                        task=m.task,
                        operator=m.operator,
                        start_ns=m.start_ns,
                        end_ns=m.end_ns,
                        duration_s=m.duration_s,
                        reason=m.reason,
                        files=m.files,
                        path=directory,
                        partition=partition,
                    )
                )
        out.sort(key=lambda s: (s.start_ns, s.id))
        return out

    def find(self, episode_id: str, *, include_unfinished: bool = False) -> EpisodeSummary:
        """An episode by full id or unique id prefix, committed (``episodes`` or ``failures``) or, with
        ``include_unfinished``, any; the summary says where it lies.

        Raises:
            RecordingError: no (or more than one) episode matches; the message lists the candidates.
        """
        everything = self.list(include_unfinished=include_unfinished, include_failures=True)
        ids = [s.id for s in everything]
        matches = [s for s in everything if s.id == episode_id] or [
            s for s in everything if s.id.startswith(episode_id)
        ]
        if len(matches) == 1:
            return matches[0]
        if len(matches) > 1:
            raise RecordingError(
                f"episode id prefix {episode_id!r} is ambiguous: {_id_list([s.id for s in matches])}; "
                "give more characters"
            )
        available = _id_list(ids[::-1]) if ids else "none"
        raise RecordingError(f"episode {episode_id!r} not found in {self._root}. Available: {available}")

    def get(self, episode_id: str, *, include_unfinished: bool = False) -> EpisodeManifest:
        """The manifest of an episode, by full id or unique id prefix (either committed partition).

        Raises:
            RecordingError: no (or more than one) episode matches; the message lists the candidates.
        """
        return _read_manifest(self.find(episode_id, include_unfinished=include_unfinished).path / _MANIFEST)

    def episode_dir(self, episode_id: str) -> Path:
        """Directory of a committed episode (in ``episodes`` or ``failures``), by full id or unique prefix."""
        return self.find(episode_id).path

    # -- the failures partition ----------------------------------------------------------------

    def move_to_failures(self, episode_id: str, reasons: Sequence[str]) -> Path:
        """Move a committed episode to ``<root>/failures/<id>/`` with ``reasons`` in its ``failure.json``.

        Crash-safe: ``failure.json`` is written (atomically) in ``episodes/<id>/`` first, then the
        directory is renamed; a kill between the two leaves the episode in ``episodes`` with its
        reasons, and :meth:`finish_interrupted_moves` (``telerig repair``) completes the move. An
        episode already in ``failures`` gets the new reasons. Returns the new directory.

        Raises:
            RecordingError: ``episode_id`` is not a full id, or no committed episode has it.
        """
        check_episode_id(episode_id)
        lines = tuple(str(r) for r in reasons)
        if not lines:
            raise ValueError("move_to_failures() needs at least one reason")
        record = FailureRecord(id=episode_id, reasons=lines, moved_ns=time.time_ns())
        source, target = self._root / _EPISODES / episode_id, self._root / _FAILURES / episode_id
        with self._partition_lock():
            if target.is_dir() and not source.exists():
                _write_json_atomic(target / FAILURE_FILE, record.model_dump_json(indent=2))
                return target
            self._check_movable(source, target, "episodes", episode_id)
            # The reasons first: they are also the record that a move was under way.
            _write_json_atomic(source / FAILURE_FILE, record.model_dump_json(indent=2))
            _rename_episode(source, target)
        _log.info("episode %s moved to failures: %s", episode_id, "; ".join(lines))
        return target

    def restore_from_failures(self, episode_id: str) -> Path:
        """Move an episode back from ``failures`` to ``episodes`` (e.g. after a threshold change).

        Crash-safe: its ``failure.json`` is removed first, then the directory is renamed; a kill
        between the two leaves it in ``failures`` without reasons, which
        :meth:`finish_interrupted_moves` (``telerig repair``) restores. An episode already in
        ``episodes`` stays there (a stale ``failure.json`` is removed). Returns the new directory.

        Raises:
            RecordingError: ``episode_id`` is not a full id, or no episode in ``failures`` has it.
        """
        check_episode_id(episode_id)
        source, target = self._root / _FAILURES / episode_id, self._root / _EPISODES / episode_id
        with self._partition_lock():
            if target.is_dir() and not source.exists():
                _remove_synced(target / FAILURE_FILE)
                return target
            self._check_movable(source, target, "failures", episode_id)
            _remove_synced(source / FAILURE_FILE)
            _rename_episode(source, target)
        _log.info("episode %s restored from failures", episode_id)
        return target

    def failure(self, episode_id: str) -> FailureRecord | None:
        """The reasons of an episode in ``failures``; ``None`` when it is not there.

        Raises:
            RecordingError: its ``failure.json`` is unreadable (one line naming the file).
        """
        path = self._root / _FAILURES / check_episode_id(episode_id) / FAILURE_FILE
        if not path.is_file():
            return None
        try:
            return FailureRecord.model_validate_json(path.read_bytes())
        except OSError as exc:
            raise RecordingError(f"cannot read {path}: {exc.strerror}") from None
        except ValidationError as exc:
            raise RecordingError(f"{path} is not a failure record: {exc.errors()[0]['msg']}") from None

    def finish_interrupted_moves(self) -> builtins.list[MoveRecovery]:
        """Complete the moves between ``episodes`` and ``failures`` that a crash cut short.

        An episode in ``episodes`` with a ``failure.json`` was being moved to ``failures``; one in
        ``failures`` without it was being restored. Each is moved where it was going; stray
        ``failure.json.tmp`` files go. Returns what was moved.
        """
        done: builtins.list[MoveRecovery] = []
        with self._partition_lock():
            for partition in (_EPISODES, _FAILURES):
                base = self._root / partition
                for directory in sorted(base.iterdir()) if base.is_dir() else []:
                    if not directory.is_dir() or not _ID.match(directory.name):
                        continue
                    (directory / (FAILURE_FILE + ".tmp")).unlink(missing_ok=True)
                    marked = (directory / FAILURE_FILE).is_file()
                    if partition == _EPISODES and marked:
                        target = self._root / _FAILURES / directory.name
                        to: Literal["episodes", "failures"] = "failures"
                    elif partition == _FAILURES and not marked:
                        target = self._root / _EPISODES / directory.name
                        to = "episodes"
                    else:
                        continue
                    if target.exists():
                        _log.warning("%s and %s both exist; left for inspection", directory, target)
                        continue
                    _rename_episode(directory, target)
                    _log.info("episode %s: finished its interrupted move to %s", directory.name, to)
                    done.append(MoveRecovery(id=directory.name, to=to))
        return done

    def _check_movable(self, source: Path, target: Path, partition: str, episode_id: str) -> None:
        if not (source / _MANIFEST).is_file():
            raise RecordingError(f"episode {episode_id} is not in {self._root / partition}")
        if target.exists():
            raise RecordingError(
                f"{target} already exists beside {source}; run `telerig repair --all`, then inspect both"
            )

    @contextlib.contextmanager
    def _partition_lock(self) -> Iterator[None]:
        """Exclusive between processes (a station's gate worker and `telerig qa` or `repair`)."""
        self._root.mkdir(parents=True, exist_ok=True)
        fd = os.open(self._root / _PARTITION_LOCK, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
            yield
        finally:
            os.close(fd)

    def locate(self, episode_id: str) -> Path | None:
        """The directory of episode ``episode_id`` (a full id) in whichever partition holds it now;
        ``None`` when none does. Cheap (no listing): for a caller that holds an id while the quality
        gates may move the episode between ``episodes`` and ``failures``."""
        return self._find_dir(check_episode_id(episode_id))

    def _find_dir(self, episode_id: str) -> Path | None:
        for partition in (_EPISODES, _FAILURES, _INCOMPLETE, _INCOMING):
            directory = self._root / partition / episode_id
            if directory.is_dir():
                return directory
        return None


def _rename_episode(source: Path, target: Path) -> None:
    """One atomic rename of an episode directory, made durable in both partitions."""
    target.parent.mkdir(parents=True, exist_ok=True)
    os.rename(source, target)
    _fsync_dir(target.parent)
    _fsync_dir(source.parent)


def _remove_synced(path: Path) -> None:
    if path.exists():
        path.unlink()
        _fsync_dir(path.parent)


def _id_list(ids: list[str]) -> str:
    shown = ", ".join(ids[:_MAX_LISTED_IDS])
    more = len(ids) - _MAX_LISTED_IDS
    return f"{shown} (and {more} more)" if more > 0 else shown
