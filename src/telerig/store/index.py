"""Episode index database (SQLite file or PostgreSQL): a rebuildable cache of episode manifests."""

from __future__ import annotations

import dataclasses
import logging
import math
import sqlite3
import time
from collections.abc import Callable, Collection, Iterable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, Literal, get_args

import sqlalchemy as sa
from pydantic import JsonValue, ValidationError
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.engine import Connection, Engine

from telerig.errors import ConfigError, DependencyError, RecordingError
from telerig.store.episodes import EpisodeManifest, EpisodeStore
from telerig.store.label_file import LabelRecord, read_label
from telerig.store.manifest_extra import EpisodeExtra
from telerig.store.qa_file import QaRecord, read_qa

__all__ = [
    "DEFAULT_FILENAME",
    "SCHEMA_VERSION",
    "DeviceRecord",
    "EpisodeIndex",
    "EpisodeOrder",
    "EpisodeRecord",
    "IndexStatus",
    "OperatorRecord",
    "ProcessedClipRecord",
    "RebuildResult",
    "SessionRecord",
    "VerdictRecord",
]

_log = logging.getLogger("telerig.store.index")

#: Status of an episode in the index. A draft left in ``.incoming`` (manifest status
#: ``recording``) is indexed as ``interrupted``; ``repaired`` is set by ``telerig repair``;
#: ``failed_qa``: a committed episode a quality gate rejected, in the ``failures`` partition.
IndexStatus = Literal["complete", "incomplete", "interrupted", "repaired", "failed_qa"]
_STATUSES: tuple[str, ...] = get_args(IndexStatus)

#: Sort key of :meth:`EpisodeIndex.list_episodes`; a leading ``-`` sorts descending. Ties break by id.
EpisodeOrder = Literal[
    "start", "-start", "duration", "-duration", "size", "-size", "quality", "-quality", "updated", "-updated",
    "task", "-task", "operator", "-operator", "status", "-status",
]  # fmt: skip
_ORDER_COLUMNS = {
    "start": "start_ns",
    "task": "task",
    "operator": "operator",
    "status": "status",
    "duration": "duration_s",
    "size": "size_bytes",
    "quality": "quality",
    "updated": "updated_ns",
}

#: File name of the SQLite index under a data root.
DEFAULT_FILENAME = "index.sqlite"
_SQLITE_SUFFIXES = (".sqlite", ".sqlite3", ".db")
_IMMEDIATE = "telerig_sqlite_immediate"
_PG_MIGRATION_LOCK = 0x7E1E_1D  # pg_advisory_xact_lock key held while the schema is created/migrated
_MAX_LISTED_IDS = 10
_DELETE_CHUNK = 500

# ---------------------------------------------------------------------------------------------
# Schema. SCHEMA_VERSION is the version the tables below describe.
#
# Adding a migration (schema version N -> N+1):
#   1. Change the tables below to the new schema (a fresh database is created from them).
#   2. Bump SCHEMA_VERSION to N+1.
#   3. Add ``_MIGRATIONS[N + 1] = _migrate_to_<N+1>``: a function of a Connection that brings a
#      version-N database to N+1 with portable DDL (``ALTER TABLE ... ADD COLUMN``, new tables via
#      ``table.create(conn)``, data backfills with UPDATE), valid on SQLite and PostgreSQL.
#   4. Add a test that creates a version-N database, opens it, and checks the new schema and data.
# ``EpisodeIndex.open`` runs the pending migrations in order in one transaction, under an exclusive
# lock (PostgreSQL advisory lock / SQLite ``BEGIN IMMEDIATE``), so stations opening at once are safe.
# Because the index is a cache of the manifests, a migration may also drop and rebuild a table,
# provided the release notes say to run ``EpisodeIndex.rebuild`` afterwards.
# ---------------------------------------------------------------------------------------------

SCHEMA_VERSION = 5

_JSON = sa.JSON(none_as_null=True).with_variant(postgresql.JSONB(none_as_null=True), "postgresql")
_metadata = sa.MetaData()

_schema_version = sa.Table(
    "schema_version",
    _metadata,
    sa.Column("version", sa.Integer, primary_key=True, autoincrement=False),
    sa.Column("applied_ns", sa.BigInteger, nullable=False),
)

_operators = sa.Table(
    "operators",
    _metadata,
    sa.Column("id", sa.String(200), primary_key=True),
    sa.Column("name", sa.String(200)),
    sa.Column("extra", _JSON),
    sa.Column("created_ns", sa.BigInteger, nullable=False),
    sa.Column("updated_ns", sa.BigInteger, nullable=False),
)

_devices = sa.Table(
    "devices",
    _metadata,
    sa.Column("id", sa.String(200), primary_key=True),
    sa.Column("kind", sa.String(100)),
    sa.Column("station", sa.String(200)),
    sa.Column("serial", sa.String(200)),
    sa.Column("extra", _JSON),
    sa.Column("created_ns", sa.BigInteger, nullable=False),
    sa.Column("updated_ns", sa.BigInteger, nullable=False),
)

_sessions = sa.Table(
    "sessions",
    _metadata,
    sa.Column("id", sa.String(200), primary_key=True),
    sa.Column("rig", sa.String(200)),
    sa.Column("operator", sa.String(200), sa.ForeignKey("operators.id")),
    sa.Column("fingerprint", sa.String(200)),
    sa.Column("start_ns", sa.BigInteger),
    sa.Column("end_ns", sa.BigInteger),
    sa.Column("extra", _JSON),
    sa.Column("created_ns", sa.BigInteger, nullable=False),
    sa.Column("updated_ns", sa.BigInteger, nullable=False),
)

_episodes = sa.Table(
    "episodes",
    _metadata,
    sa.Column("id", sa.String(64), primary_key=True),
    sa.Column("task", sa.Text, nullable=False),
    sa.Column("operator", sa.String(200), sa.ForeignKey("operators.id"), nullable=False),
    sa.Column("rig", sa.String(200), nullable=False),
    sa.Column("robots", _JSON, nullable=False),
    sa.Column("session", sa.String(200), sa.ForeignKey("sessions.id")),
    sa.Column("start_ns", sa.BigInteger, nullable=False),
    sa.Column("end_ns", sa.BigInteger),
    sa.Column("duration_s", sa.Float),
    sa.Column("size_bytes", sa.BigInteger, nullable=False),
    sa.Column("quality", sa.Float),
    sa.Column("status", sa.String(16), nullable=False),
    sa.Column("outcome", sa.String(16)),
    sa.Column("instructions", sa.Integer),
    sa.Column("reason", sa.Text),
    sa.Column("location", sa.Text),
    sa.Column("fingerprint", sa.String(200)),
    sa.Column("created_ns", sa.BigInteger, nullable=False),
    sa.Column("updated_ns", sa.BigInteger, nullable=False),
    sa.Index("ix_episodes_start", "start_ns", "id"),
    sa.Index("ix_episodes_task_start", "task", "start_ns"),
    sa.Index("ix_episodes_operator_start", "operator", "start_ns"),
    sa.Index("ix_episodes_status_start", "status", "start_ns"),
    sa.Index("ix_episodes_session", "session"),
)

#: Version 2: every quality gate's verdict on an episode (issue 13); ``qa.json`` beside the episode
#: is its source (:meth:`EpisodeIndex.rebuild` reads it back).
_gate_verdicts = sa.Table(
    "gate_verdicts",
    _metadata,
    sa.Column(
        "episode_id", sa.String(64), sa.ForeignKey("episodes.id", ondelete="CASCADE"), primary_key=True
    ),
    sa.Column("gate", sa.String(64), primary_key=True),
    sa.Column("passed", sa.Boolean),
    sa.Column("value", sa.Float),
    sa.Column("threshold", sa.Float),
    sa.Column("unit", sa.String(32), nullable=False),
    sa.Column("detail", sa.Text, nullable=False),
    sa.Column("checked_ns", sa.BigInteger, nullable=False),
    sa.Column("thresholds_hash", sa.String(64), nullable=False),
    sa.Index("ix_gate_verdicts_gate_passed", "gate", "passed"),
)


#: Version 4: the annotation pipeline's clips (issue 15), linking each raw recording (an episode or a
#: plain video) to the clips ``telerig process`` made of it. Its source is ``<processed>/index.json``
#: (:mod:`telerig.process.layout` writes both); a processed root's rows are replaced as a whole on
#: each run. ``source_id`` is not a foreign key: a plain video is not an episode.
_processed_clips = sa.Table(
    "processed_clips",
    _metadata,
    sa.Column("id", sa.String(64), primary_key=True),
    sa.Column("processed_root", sa.Text, nullable=False),
    sa.Column("source_id", sa.String(200), nullable=False),
    sa.Column("source_kind", sa.String(16), nullable=False),
    sa.Column("source_path", sa.Text, nullable=False),
    sa.Column("source_hash", sa.String(64), nullable=False),
    sa.Column("path", sa.Text, nullable=False),
    sa.Column("scene", sa.String(64), nullable=False),
    sa.Column("label", sa.Text),
    sa.Column("start_s", sa.Float, nullable=False),
    sa.Column("end_s", sa.Float, nullable=False),
    sa.Column("duration_s", sa.Float, nullable=False),
    sa.Column("fps", sa.Float),
    sa.Column("device_id", sa.String(200)),
    sa.Column("date", sa.String(40)),
    sa.Column("updated_ns", sa.BigInteger, nullable=False),
    sa.Index("ix_processed_clips_source", "source_id"),
    sa.Index("ix_processed_clips_scene", "scene"),
    sa.Index("ix_processed_clips_root", "processed_root"),
)


def _migrate_to_2(conn: Connection) -> None:
    """Version 1 -> 2: the ``gate_verdicts`` table (the ``failed_qa`` status needs no DDL)."""
    _gate_verdicts.create(conn)


def _migrate_to_3(conn: Connection) -> None:
    """Version 2 -> 3: ``episodes.outcome``, the success/failure label (``label.json`` beside the
    episode, else the manifest's ``extra.outcome``); ``rebuild`` fills it for existing episodes."""
    conn.execute(sa.text("ALTER TABLE episodes ADD COLUMN outcome VARCHAR(16)"))


def _migrate_to_4(conn: Connection) -> None:
    """Version 3 -> 4: the ``processed_clips`` table (``telerig process`` fills it on its next run)."""
    _processed_clips.create(conn)


def _migrate_to_5(conn: Connection) -> None:
    """Version 4 -> 5: ``episodes.instructions``, the operator instructions of the episode (issue 17,
    the manifest's ``extra.instructions.total``); ``rebuild`` fills it for existing episodes."""
    conn.execute(sa.text("ALTER TABLE episodes ADD COLUMN instructions INTEGER"))


#: ``_MIGRATIONS[v]`` upgrades a database at version ``v - 1`` to ``v`` (see the comment above).
_MIGRATIONS: dict[int, Callable[[Connection], None]] = {
    2: _migrate_to_2,
    3: _migrate_to_3,
    4: _migrate_to_4,
    5: _migrate_to_5,
}


# ---------------------------------------------------------------------------------------------
# Records returned by the index.
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class EpisodeRecord:
    """One episode as the index knows it.

    Attributes:
        id: Episode id (``ep-YYYYMMDD-HHMMSS-xxxx``).
        task: Task name or instruction.
        operator: Operator id.
        rig: Rig name.
        robots: Robot names of the rig, from manifest ``extra["robots"]``; empty if not recorded.
        session: Session id, from manifest ``extra["session_id"]``; ``None`` outside a session.
        start_ns: Recording start, common clock [ns].
        end_ns: Recording end [ns]; ``None`` for an interrupted draft.
        duration_s: Duration [s]; ``None`` for an interrupted draft.
        size_bytes: Total size of the episode's files [bytes].
        quality: Quality score in [0, 1]; ``None`` until scored.
        status: See :data:`IndexStatus`.
        reason: Why the episode is incomplete; ``None`` otherwise.
        location: Absolute local directory, or an object-store URL (``s3://bucket/prefix/<id>``).
        fingerprint: Rig fingerprint digest (rates, cameras, robots), from manifest ``extra["fingerprint"]``
            (:class:`~telerig.store.manifest_extra.EpisodeExtra`).
        created_ns: When the index first saw the episode, wall clock [ns].
        updated_ns: When the index last changed the row, wall clock [ns].
        outcome: The success/failure label: the episode's ``label.json``
            (:mod:`~telerig.store.label_file`), else the manifest's ``extra.outcome``; ``None`` unlabelled.
        instructions: Operator instructions the episode received (seed 002's count, the manifest's
            ``extra.instructions.total``); ``None`` when not counted.
    """

    id: str
    task: str
    operator: str
    rig: str
    robots: tuple[str, ...]
    session: str | None
    start_ns: int
    end_ns: int | None
    duration_s: float | None
    size_bytes: int
    quality: float | None
    status: IndexStatus
    reason: str | None
    location: str | None
    fingerprint: str | None
    created_ns: int
    updated_ns: int
    outcome: Literal["success", "failure"] | None = None
    instructions: int | None = None


@dataclass(frozen=True, slots=True)
class VerdictRecord:
    """One quality gate's verdict on an episode, as last checked.

    Attributes:
        episode_id: The episode.
        gate: Gate name (:data:`~telerig.config.qa.GateName`), e.g. ``joint_limits``.
        passed: True passed, False failed, ``None`` not applicable (``detail`` says why).
        value: Measured value in ``unit``; ``None`` when nothing was measured.
        threshold: The threshold it was held to, in ``unit``.
        unit: Unit of value and threshold, e.g. ``rad``, ``N``, ``ms``, ``fraction``.
        detail: One line a person understands.
        checked_ns: When the gates ran, wall clock [ns].
        thresholds_hash: Digest of the thresholds they ran with.
    """

    episode_id: str
    gate: str
    passed: bool | None
    value: float | None
    threshold: float | None
    unit: str
    detail: str
    checked_ns: int
    thresholds_hash: str


@dataclass(frozen=True, slots=True)
class OperatorRecord:
    """An operator: ``id`` (as in manifests), display ``name``, ``extra`` JSON data, wall-clock times [ns]."""

    id: str
    name: str | None
    extra: dict[str, JsonValue]
    created_ns: int
    updated_ns: int


@dataclass(frozen=True, slots=True)
class DeviceRecord:
    """An input device, camera or robot: ``kind`` (e.g. ``vr``, ``camera``, ``robot``), the ``station``
    it is attached to, its ``serial``, ``extra`` JSON data, wall-clock stamps [ns]."""

    id: str
    kind: str | None
    station: str | None
    serial: str | None
    extra: dict[str, JsonValue]
    created_ns: int
    updated_ns: int


@dataclass(frozen=True, slots=True)
class SessionRecord:
    """A recording session (one or more stations): rig, operator, rig fingerprint, start/end on the
    common clock [ns], ``extra`` JSON data (stations, clock offsets...), wall-clock stamps [ns]."""

    id: str
    rig: str | None
    operator: str | None
    fingerprint: str | None
    start_ns: int | None
    end_ns: int | None
    extra: dict[str, JsonValue]
    created_ns: int
    updated_ns: int


@dataclass(frozen=True, slots=True)
class ProcessedClipRecord:
    """One clip of the annotation pipeline's dataset and the raw recording it was cut from.

    Attributes:
        id: The clip's UUID (its file is ``<scene>/<id>.mp4`` under the dataset).
        processed_root: The processed root that holds it (absolute path).
        source_id: Episode id, or ``video-<hash>`` of a plain video.
        source_kind: ``episode`` or ``video``.
        source_path: The episode directory or the video file.
        source_hash: sha256 of the source's bytes when it was processed (hex).
        path: The clip file, relative to ``processed_root``.
        scene: Scene type from its annotation (``unknown`` when not annotated).
        label: The action label of its segment.
        start_s: Clip start on the source video's timeline [s].
        end_s: Clip end on the source video's timeline [s].
        duration_s: Clip duration [s].
        fps: Frame rate of the clip [Hz].
        device_id: Station or device that recorded the source, where known.
        date: Recording date of the source, ISO 8601 UTC, where known.
    """

    id: str
    processed_root: str
    source_id: str
    source_kind: str
    source_path: str
    source_hash: str
    path: str
    scene: str
    label: str | None
    start_s: float
    end_s: float
    duration_s: float
    fps: float | None
    device_id: str | None
    date: str | None


@dataclass(frozen=True, slots=True)
class RebuildResult:
    """What :meth:`EpisodeIndex.rebuild` did: episodes indexed, rows removed (dir gone), dirs skipped."""

    indexed: int
    removed: int
    skipped: int


# ---------------------------------------------------------------------------------------------
# Helpers.
# ---------------------------------------------------------------------------------------------


def _database_url(target: str | Path) -> sa.URL:
    """The SQLAlchemy URL for a data root, an SQLite file, or a ``sqlite://`` / ``postgresql://`` URL."""
    text = str(target)
    if "://" not in text:
        path = Path(text).expanduser()
        if path.suffix not in _SQLITE_SUFFIXES:
            path = path / DEFAULT_FILENAME
        path.parent.mkdir(parents=True, exist_ok=True)
        return sa.URL.create("sqlite+pysqlite", database=str(path.resolve()))
    try:
        url = sa.make_url(text)
    except sa.exc.ArgumentError:
        raise ConfigError(
            f"index URL {text!r} is malformed; use postgresql://user:pass@host:port/db"
        ) from None
    backend = url.get_backend_name()
    if backend in ("postgresql", "postgres"):
        return url.set(drivername="postgresql+psycopg")
    if backend == "sqlite":
        if url.database and url.database != ":memory:":
            Path(url.database).expanduser().parent.mkdir(parents=True, exist_ok=True)
        return url.set(drivername="sqlite+pysqlite")
    raise ConfigError(
        f"index URL scheme {url.drivername!r} is not supported. Available: a path (SQLite), "
        "sqlite:///path/index.sqlite, postgresql://user:pass@host:port/db"
    )


def _sqlite_on_connect(dbapi_connection: Any, _record: Any) -> None:
    # Let SQLAlchemy's "begin" event emit BEGIN (pysqlite's own implicit BEGIN is unreliable),
    # and use WAL so several processes of a station read while one writes.
    dbapi_connection.isolation_level = None
    cursor = dbapi_connection.cursor()
    try:
        # busy_timeout first: switching to WAL takes a lock, and without a timeout a connection
        # opened while another station writes fails at once with "database is locked".
        cursor.execute("PRAGMA busy_timeout=30000")
        _set_wal(cursor)
        cursor.execute("PRAGMA synchronous=NORMAL")
        cursor.execute("PRAGMA foreign_keys=ON")
    finally:
        cursor.close()


def _set_wal(cursor: Any, timeout_s: float = 30.0) -> None:
    """Switch the database to WAL (persistent in the file); SQLite's busy handler does not cover this
    switch, so a connection opened while another one creates the schema retries it."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            cursor.execute("PRAGMA journal_mode=WAL")
            return
        except sqlite3.OperationalError as exc:
            if "locked" not in str(exc) or time.monotonic() > deadline:
                raise
            time.sleep(0.01)


def _sqlite_on_begin(conn: Connection) -> None:
    # Writers take the write lock up front, so a read-then-write transaction never fails with
    # SQLITE_BUSY halfway; busy_timeout makes them queue instead.
    conn.exec_driver_sql("BEGIN IMMEDIATE" if conn.get_execution_options().get(_IMMEDIATE) else "BEGIN")


def _create_engine(url: sa.URL) -> Engine:
    if url.get_backend_name() == "postgresql":
        try:
            import psycopg  # noqa: F401
        except ImportError:
            raise DependencyError(
                "the PostgreSQL index needs psycopg 3: pip install 'psycopg[binary]'"
            ) from None
        return sa.create_engine(url, pool_pre_ping=True)
    memory = url.database in (None, "", ":memory:")
    # One shared connection for an in-memory database, usable from any thread (a web server's
    # worker threads take turns on it: its callers serialize their use).
    engine = sa.create_engine(
        url,
        poolclass=sa.StaticPool if memory else None,
        connect_args={"check_same_thread": False} if memory else {},
    )
    sa.event.listen(engine, "connect", _sqlite_on_connect)
    sa.event.listen(engine, "begin", _sqlite_on_begin)
    return engine


def _typed_extra(manifest: EpisodeManifest) -> EpisodeExtra:
    """The manifest's typed extra; a manifest whose extra does not fit is indexed without it (one warning)."""
    try:
        return EpisodeExtra.of(manifest)
    except RecordingError as exc:
        _log.warning("%s; indexed without its robots, session, fingerprint and quality", exc)
        return EpisodeExtra()


def _instruction_total(counts: dict[str, JsonValue] | None) -> int | None:
    """``total`` of a manifest's ``extra.instructions``: an integer in [0, 10^6], else ``None``."""
    total = None if counts is None else counts.get("total")
    if isinstance(total, int) and not isinstance(total, bool) and 0 <= total <= 1_000_000:
        return total
    return None


def _check_quality(quality: float | None) -> float | None:
    if quality is None:
        return None
    if isinstance(quality, bool) or not isinstance(quality, int | float) or not math.isfinite(quality):
        raise ValueError(f"quality must be a finite number in [0, 1] or None, got {quality!r}")
    if not 0.0 <= quality <= 1.0:
        raise ValueError(f"quality must be in [0, 1], got {quality}")
    return float(quality)


def _check_status(status: str) -> IndexStatus:
    if status not in _STATUSES:
        raise ValueError(f"status {status!r} is not an index status. Available: {', '.join(_STATUSES)}")
    return status  # type: ignore[return-value]


def _location(location: str | Path) -> str:
    text = str(location)
    if not text:
        raise ValueError("location must be a local path or an object-store URL, got ''")
    return text if "://" in text else str(Path(text).expanduser().resolve())


def _id_list(ids: list[str]) -> str:
    shown = ", ".join(ids[:_MAX_LISTED_IDS])
    more = len(ids) - _MAX_LISTED_IDS
    return f"{shown} (and {more} more)" if more > 0 else shown


def _json_dict(value: Any) -> dict[str, JsonValue]:
    return dict(value) if isinstance(value, dict) else {}


def _episode(row: sa.RowMapping) -> EpisodeRecord:
    return EpisodeRecord(
        id=row["id"],
        task=row["task"],
        operator=row["operator"],
        rig=row["rig"],
        robots=tuple(row["robots"] or ()),
        session=row["session"],
        start_ns=row["start_ns"],
        end_ns=row["end_ns"],
        duration_s=row["duration_s"],
        size_bytes=row["size_bytes"],
        quality=row["quality"],
        status=row["status"],
        reason=row["reason"],
        location=row["location"],
        fingerprint=row["fingerprint"],
        created_ns=row["created_ns"],
        updated_ns=row["updated_ns"],
        outcome=row["outcome"],
        instructions=row["instructions"],
    )


def _operator(row: sa.RowMapping) -> OperatorRecord:
    return OperatorRecord(
        id=row["id"],
        name=row["name"],
        extra=_json_dict(row["extra"]),
        created_ns=row["created_ns"],
        updated_ns=row["updated_ns"],
    )


def _device(row: sa.RowMapping) -> DeviceRecord:
    return DeviceRecord(
        id=row["id"],
        kind=row["kind"],
        station=row["station"],
        serial=row["serial"],
        extra=_json_dict(row["extra"]),
        created_ns=row["created_ns"],
        updated_ns=row["updated_ns"],
    )


def _session(row: sa.RowMapping) -> SessionRecord:
    return SessionRecord(
        id=row["id"],
        rig=row["rig"],
        operator=row["operator"],
        fingerprint=row["fingerprint"],
        start_ns=row["start_ns"],
        end_ns=row["end_ns"],
        extra=_json_dict(row["extra"]),
        created_ns=row["created_ns"],
        updated_ns=row["updated_ns"],
    )


# ---------------------------------------------------------------------------------------------
# The index.
# ---------------------------------------------------------------------------------------------


class EpisodeIndex:
    """Operators, devices, sessions and episodes in SQLite (default) or PostgreSQL.

    The manifests on disk are the source of truth; the index is a cache for listing and filtering
    that :meth:`rebuild` can always recreate. Every write is an idempotent upsert
    (``INSERT ... ON CONFLICT``), so stations can write the same rows concurrently. A row's
    ``updated_ns`` changes only when a value actually changes.

    Obtain one with :meth:`open`; use it as a context manager or call :meth:`close`.

    Example::

        with EpisodeIndex.open(store.root) as index:        # <root>/index.sqlite
            index.upsert_episode(draft.commit(), location=draft.dir)
            recent = index.list_episodes(task="pick", order="-start", limit=20)
    """

    def __init__(self, engine: Engine) -> None:
        """Wrap ``engine`` whose schema is current; use :meth:`open`, which creates/migrates it."""
        self._engine = engine
        self._closed = False

    # -- lifecycle -----------------------------------------------------------------------------

    @classmethod
    def open(cls, target: str | Path) -> EpisodeIndex:
        """Connect to an index, creating or migrating its schema to :data:`SCHEMA_VERSION`.

        Args:
            target: A data root directory (the index is ``<root>/index.sqlite``), an SQLite file
                (``*.sqlite``, ``*.sqlite3``, ``*.db``), ``sqlite:///path``, or
                ``postgresql://user:pass@host:port/db``.

        Raises:
            ConfigError: ``target`` is not a supported URL.
            DependencyError: PostgreSQL was asked for and psycopg is not installed.
            RecordingError: The database cannot be reached, or its schema is newer than this telerig.
        """
        url = _database_url(target)
        engine = _create_engine(url)
        shown = url.render_as_string(hide_password=True)
        try:
            _migrate(engine, shown)
        except sa.exc.OperationalError as exc:
            engine.dispose()
            detail = str(exc.orig).strip().splitlines()[0] if exc.orig else str(exc)
            raise RecordingError(f"cannot open episode index {shown}: {detail}") from None
        except BaseException:
            engine.dispose()
            raise
        _log.info("episode index %s open (schema version %d)", shown, SCHEMA_VERSION)
        return cls(engine)

    @property
    def url(self) -> str:
        """The database URL, password hidden."""
        return self._engine.url.render_as_string(hide_password=True)

    @property
    def schema_version(self) -> int:
        """The schema version recorded in the database."""
        with self._read() as conn:
            return _current_version(conn)

    def close(self) -> None:
        """Release the connections. Idempotent."""
        if not self._closed:
            self._closed = True
            self._engine.dispose()

    def __enter__(self) -> EpisodeIndex:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    # -- episodes ------------------------------------------------------------------------------

    def upsert_episode(
        self,
        manifest: EpisodeManifest,
        *,
        location: str | Path | None = None,
        status: IndexStatus | None = None,
    ) -> EpisodeRecord:
        """Insert or update the episode described by ``manifest``; returns the stored row.

        Task, operator, rig, times, size (sum of the manifest's files) and reason come from the
        manifest; robots, session, fingerprint digest and quality from its typed extra
        (:class:`~telerig.store.manifest_extra.EpisodeExtra`) when present.
        The operator (and session) rows are created if missing.

        Args:
            manifest: The episode manifest.
            location: Local episode directory or object-store URL; ``None`` keeps the stored one.
            status: Overrides the manifest status (``recording`` is indexed as ``interrupted``).
        """
        row = self._manifest_row(manifest, location=location, status=status)
        with self._write() as conn:
            self._upsert_episode_rows(conn, [row])
            return self._get_exact(conn, manifest.id)

    def upsert_episodes(
        self, manifests: Iterable[EpisodeManifest], *, location_root: Path | None = None
    ) -> int:
        """Upsert many manifests in one transaction; returns how many.

        Args:
            manifests: Episode manifests; a later one wins over an earlier one with the same id.
            location_root: If given, each location is ``location_root/<id>``; otherwise kept.
        """
        rows = [
            self._manifest_row(
                m, location=None if location_root is None else location_root / m.id, status=None
            )
            for m in manifests
        ]
        with self._write() as conn:
            self._upsert_episode_rows(conn, rows)
        return len({r["id"] for r in rows})

    def get(self, episode_id: str) -> EpisodeRecord:
        """The episode by full id or unique id prefix.

        Raises:
            RecordingError: No episode (or more than one) matches; the message lists candidates.
        """
        with self._read() as conn:
            row = conn.execute(sa.select(_episodes).where(_episodes.c.id == episode_id)).mappings().first()
            if row is not None:
                return _episode(row)
            prefix = _episodes.c.id.startswith(episode_id, autoescape=True)
            matches = list(
                conn.execute(
                    sa.select(_episodes.c.id).where(prefix).order_by(_episodes.c.id).limit(11)
                ).scalars()
            )
            if len(matches) == 1:
                return self._get_exact(conn, matches[0])
            if matches:
                shown = _id_list(matches)
                raise RecordingError(
                    f"episode id prefix {episode_id!r} is ambiguous: {shown}; give more characters"
                )
            recent = list(
                conn.execute(
                    sa.select(_episodes.c.id).order_by(_episodes.c.start_ns.desc()).limit(_MAX_LISTED_IDS)
                ).scalars()
            )
        available = ", ".join(recent) if recent else "none"
        raise RecordingError(
            f"episode {episode_id!r} is not in the index {self.url}. Recent: {available} "
            "(run EpisodeIndex.rebuild if the store has it)"
        )

    def list_episodes(
        self,
        *,
        task: str | None = None,
        operator: str | None = None,
        rig: str | None = None,
        session: str | None = None,
        status: IndexStatus | Collection[IndexStatus] | None = None,
        since_ns: int | None = None,
        until_ns: int | None = None,
        gate: str | None = None,
        gate_passed: bool | None = None,
        robot: str | None = None,
        outcome: Literal["success", "failure"] | None = None,
        min_quality: float | None = None,
        max_quality: float | None = None,
        order: EpisodeOrder = "start",
        limit: int | None = None,
        offset: int = 0,
    ) -> list[EpisodeRecord]:
        """Episodes matching every given filter.

        Args:
            task, operator, rig, session: Exact matches.
            status: One status or several (``failed_qa``: rejected by a quality gate).
            gate: Only episodes with a verdict of this gate (e.g. ``joint_limits``); with
                ``gate_passed``, only those where it passed (True) or failed (False).
            gate_passed: Without ``gate``: False, episodes where any gate failed; True, episodes
                checked with no gate failed.
            robot: Only episodes whose rig has this robot (a name of :attr:`EpisodeRecord.robots`).
            outcome: Only episodes labelled ``success`` (or ``failure``).
            min_quality, max_quality: Only scored episodes with quality in this range (inclusive).
            since_ns: Only episodes starting at or after this time, common clock [ns].
            until_ns: Only episodes starting before this time [ns].
            order: Sort key (:data:`EpisodeOrder`); ``-`` for descending. Unscored quality sorts last.
            limit: At most this many rows; ``None`` for all.
            offset: Skip this many rows first (paging).
        """
        key = order.removeprefix("-")
        if key not in _ORDER_COLUMNS:
            raise ValueError(
                f"order {order!r} is not supported. Available: {', '.join(sorted(_ORDER_COLUMNS))} "
                "(prefix '-' for descending)"
            )
        if limit is not None and limit < 0:
            raise ValueError(f"limit must be >= 0 or None, got {limit}")
        if offset < 0:
            raise ValueError(f"offset must be >= 0, got {offset}")
        query = sa.select(_episodes)
        for column, value in (("task", task), ("operator", operator), ("rig", rig), ("session", session)):
            if value is not None:
                query = query.where(_episodes.c[column] == value)
        if status is not None:
            statuses = [status] if isinstance(status, str) else list(status)
            for s in statuses:
                _check_status(s)
            query = query.where(_episodes.c.status.in_(statuses))
        if since_ns is not None:
            query = query.where(_episodes.c.start_ns >= since_ns)
        if until_ns is not None:
            query = query.where(_episodes.c.start_ns < until_ns)
        if gate is not None or gate_passed is not None:
            query = query.where(_gate_filter(gate, gate_passed))
        if robot is not None:
            query = query.where(_robot_filter(robot, self._engine.dialect.name))
        if outcome is not None:
            query = query.where(_episodes.c.outcome == outcome)
        if min_quality is not None:
            query = query.where(_episodes.c.quality >= _check_quality(min_quality))
        if max_quality is not None:
            query = query.where(_episodes.c.quality <= _check_quality(max_quality))
        sort = _episodes.c[_ORDER_COLUMNS[key]]
        descending = order.startswith("-")
        keys: list[sa.ColumnElement[Any]] = [
            sort.desc() if descending else sort.asc(),
            _episodes.c.id.desc() if descending else _episodes.c.id.asc(),
        ]
        if sort.nullable:  # NULLs last both ways, on both backends (kept off indexed NOT NULL keys)
            keys.insert(0, sort.is_(None))
        query = query.order_by(*keys)
        if limit is not None:
            query = query.limit(limit)
        if offset:
            query = query.offset(offset)
        with self._read() as conn:
            return [_episode(row) for row in conn.execute(query).mappings()]

    def count_episodes(self) -> int:
        """Number of episodes in the index."""
        with self._read() as conn:
            return int(conn.execute(sa.select(sa.func.count()).select_from(_episodes)).scalar_one())

    def set_status(self, episode_id: str, status: IndexStatus, *, reason: str | None = None) -> EpisodeRecord:
        """Set an episode's status (and reason, cleared when ``None``). The manifest should say the same,
        or the next :meth:`rebuild` restores the manifest's status."""
        return self._update(episode_id, status=_check_status(status), reason=reason)

    def set_location(self, episode_id: str, location: str | Path) -> EpisodeRecord:
        """Set where the episode's files are: a local directory or an object-store URL (after upload)."""
        return self._update(episode_id, location=_location(location))

    def set_outcome(self, episode_id: str, outcome: Literal["success", "failure"]) -> EpisodeRecord:
        """Set the success/failure label (written to the episode's ``label.json`` first: the index
        is rebuilt from it)."""
        if outcome not in ("success", "failure"):
            raise ValueError(f"outcome must be success or failure, got {outcome!r}")
        return self._update(episode_id, outcome=outcome)

    def set_quality(self, episode_id: str, quality: float | None) -> EpisodeRecord:
        """Set the quality score in [0, 1], or ``None`` to clear it."""
        return self._update(episode_id, quality=_check_quality(quality))

    # -- quality gates -------------------------------------------------------------------------

    def record_qa(
        self,
        record: QaRecord,
        *,
        status: IndexStatus,
        reason: str | None = None,
        location: str | Path | None = None,
    ) -> EpisodeRecord:
        """Store an episode's quality-gate verdicts (replacing the previous ones), its score and its
        status after the gates (``failed_qa`` when moved to failures, else its manifest status), in
        one transaction.

        Args:
            record: The episode's ``qa.json`` (:class:`~telerig.store.qa_file.QaRecord`).
            status: The episode's status now.
            reason: Why it failed (the failed gates), or its manifest's reason; cleared when ``None``.
            location: Its directory now (it moves between partitions); ``None`` keeps the stored
                one, as does an object-store URL already stored (the upload is where it is kept).

        Raises:
            RecordingError: the episode is not in the index (upsert it first).
        """
        episode_id = record.episode_id
        rows = _verdict_rows(record)
        values: dict[str, Any] = {
            "status": _check_status(status),
            "reason": reason,
            "quality": _check_quality(record.score_total),
        }
        with self._write() as conn:
            stored = conn.execute(sa.select(_episodes.c.location).where(_episodes.c.id == episode_id)).first()
            if stored is None:
                raise RecordingError(
                    f"episode {episode_id!r} is not in the index {self.url}; upsert it (or rebuild) first"
                )
            if location is not None and "://" not in (stored.location or ""):
                values["location"] = _location(location)
            _replace_verdicts(conn, episode_id, rows)
            changed = sa.or_(*(_episodes.c[k].is_distinct_from(v) for k, v in values.items()))
            conn.execute(
                sa.update(_episodes)
                .where(_episodes.c.id == episode_id, changed)
                .values(**values, updated_ns=time.time_ns())
            )
            return self._get_exact(conn, episode_id)

    def verdicts(self, episode_id: str | None = None, *, gate: str | None = None) -> list[VerdictRecord]:
        """Stored gate verdicts, of one episode and/or one gate, by episode id then gate."""
        query = sa.select(_gate_verdicts).order_by(_gate_verdicts.c.episode_id, _gate_verdicts.c.gate)
        if episode_id is not None:
            query = query.where(_gate_verdicts.c.episode_id == episode_id)
        if gate is not None:
            query = query.where(_gate_verdicts.c.gate == gate)
        with self._read() as conn:
            return [_verdict(row) for row in conn.execute(query).mappings()]

    # -- processed clips (telerig process) ------------------------------------------------------

    def replace_processed_clips(
        self, processed_root: str | Path, clips: Iterable[ProcessedClipRecord]
    ) -> int:
        """Make ``clips`` the index's rows of ``processed_root`` (its earlier rows are removed).

        Returns:
            How many rows it holds now.
        """
        root = _location(processed_root)
        now = time.time_ns()
        rows = [{**dataclasses.asdict(c), "processed_root": root, "updated_ns": now} for c in clips]
        ids = [r["id"] for r in rows]
        table = _processed_clips
        with self._write() as conn:
            conn.execute(sa.delete(table).where(table.c.processed_root == root))
            for i in range(0, len(ids), _DELETE_CHUNK):  # a clip that moved here from another root
                conn.execute(sa.delete(table).where(table.c.id.in_(ids[i : i + _DELETE_CHUNK])))
            if rows:
                conn.execute(sa.insert(table), rows)
        return len(rows)

    def processed_clips(
        self, *, source_id: str | None = None, scene: str | None = None
    ) -> list[ProcessedClipRecord]:
        """Indexed clips, of one source and/or one scene, by source then start time."""
        table = _processed_clips
        query = sa.select(table).order_by(table.c.source_id, table.c.start_s, table.c.id)
        if source_id is not None:
            query = query.where(table.c.source_id == source_id)
        if scene is not None:
            query = query.where(table.c.scene == scene)
        names = [f.name for f in dataclasses.fields(ProcessedClipRecord)]
        with self._read() as conn:
            return [
                ProcessedClipRecord(**{n: row[n] for n in names}) for row in conn.execute(query).mappings()
            ]

    # -- operators, devices, sessions ----------------------------------------------------------

    def upsert_operator(
        self, operator_id: str, *, name: str | None = None, extra: Mapping[str, JsonValue] | None = None
    ) -> OperatorRecord:
        """Insert or update an operator; fields left ``None`` keep their stored value."""
        values = {"id": _nonempty("operator_id", operator_id), "name": name, "extra": _extra(extra)}
        with self._write() as conn:
            _upsert(conn, _operators, [values], keep_if_null=("name", "extra"))
            row = conn.execute(sa.select(_operators).where(_operators.c.id == operator_id)).mappings().one()
            return _operator(row)

    def upsert_device(
        self,
        device_id: str,
        *,
        kind: str | None = None,
        station: str | None = None,
        serial: str | None = None,
        extra: Mapping[str, JsonValue] | None = None,
    ) -> DeviceRecord:
        """Insert or update a device (input device, camera, robot); fields left ``None`` keep their value."""
        values = {
            "id": _nonempty("device_id", device_id),
            "kind": kind,
            "station": station,
            "serial": serial,
            "extra": _extra(extra),
        }
        with self._write() as conn:
            _upsert(conn, _devices, [values], keep_if_null=("kind", "station", "serial", "extra"))
            row = conn.execute(sa.select(_devices).where(_devices.c.id == device_id)).mappings().one()
            return _device(row)

    def upsert_session(
        self,
        session_id: str,
        *,
        rig: str | None = None,
        operator: str | None = None,
        fingerprint: str | None = None,
        start_ns: int | None = None,
        end_ns: int | None = None,
        extra: Mapping[str, JsonValue] | None = None,
    ) -> SessionRecord:
        """Insert or update a session; times on the common clock [ns]; ``None`` fields keep their value."""
        values = {
            "id": _nonempty("session_id", session_id),
            "rig": rig,
            "operator": operator,
            "fingerprint": fingerprint,
            "start_ns": start_ns,
            "end_ns": end_ns,
            "extra": _extra(extra),
        }
        with self._write() as conn:
            if operator is not None:
                _ensure(conn, _operators, {operator})
            _upsert(conn, _sessions, [values], keep_if_null=tuple(k for k in values if k != "id"))
            row = conn.execute(sa.select(_sessions).where(_sessions.c.id == session_id)).mappings().one()
            return _session(row)

    def operators(self) -> list[OperatorRecord]:
        """All operators, by id."""
        with self._read() as conn:
            return [
                _operator(r) for r in conn.execute(sa.select(_operators).order_by(_operators.c.id)).mappings()
            ]

    def devices(self, *, station: str | None = None) -> list[DeviceRecord]:
        """All devices (of ``station`` if given), by id."""
        query = sa.select(_devices).order_by(_devices.c.id)
        if station is not None:
            query = query.where(_devices.c.station == station)
        with self._read() as conn:
            return [_device(r) for r in conn.execute(query).mappings()]

    def sessions(self) -> list[SessionRecord]:
        """All sessions, oldest start first (sessions with no start last)."""
        query = sa.select(_sessions).order_by(
            _sessions.c.start_ns.is_(None), _sessions.c.start_ns, _sessions.c.id
        )
        with self._read() as conn:
            return [_session(r) for r in conn.execute(query).mappings()]

    # -- rebuild -------------------------------------------------------------------------------

    def rebuild(self, store: EpisodeStore) -> RebuildResult:
        """Re-index every episode of ``store`` from its manifest, in one transaction.

        Committed, incomplete and interrupted (left in ``.incoming``) episodes are upserted with
        their local directory as location; index rows whose location lies under ``store.root`` but
        whose directory is gone are removed. Rows elsewhere (other stations, object storage) and
        quality scores not in the manifest are kept. A draft being recorded right now is indexed as
        ``interrupted`` until its commit is upserted. An episode in the failures partition is
        ``failed_qa``; gate verdicts and score come from each episode's ``qa.json`` (one that cannot
        be read is skipped with a warning, its stored verdicts kept).
        """
        root = store.root.expanduser().resolve()
        rows: list[dict[str, Any]] = []
        checks: list[QaRecord] = []
        skipped = 0
        for summary in store.list(include_unfinished=True):
            try:
                manifest = EpisodeManifest.model_validate_json((summary.path / "manifest.json").read_bytes())
            except (OSError, ValidationError) as exc:  # changed under us since list()
                _log.warning("rebuild: skipping %s: %s", summary.path, exc)
                skipped += 1
                continue
            status: IndexStatus = (
                "interrupted"
                if summary.status == "interrupted"
                else "failed_qa"
                if summary.partition == "failures"
                else _index_status(manifest)
            )
            row = self._manifest_row(manifest, location=summary.path, status=status)
            qa = _read_qa_or_warn(summary.path) if summary.partition in ("episodes", "failures") else None
            label = _read_label_or_warn(summary.path) if summary.partition != ".incoming" else None
            if label is not None:
                row["outcome"] = label.outcome
            if qa is not None:
                checks.append(qa)
                if status == "failed_qa":
                    row["reason"] = "; ".join(qa.reasons) or manifest.reason
            if not manifest.files:  # a draft: the manifest lists no files yet
                row["size_bytes"] = sum(
                    p.stat().st_size
                    for p in summary.path.rglob("*")
                    if p.is_file() and not p.name.startswith(".")
                )
            rows.append(row)
        found = {r["id"] for r in rows}
        prefix = str(root).rstrip("/") + "/"
        with self._write() as conn:
            self._upsert_episode_rows(conn, rows)
            for qa in checks:
                _replace_verdicts(conn, qa.episode_id, _verdict_rows(qa))
                quality = qa.score_total
                if quality is not None:
                    conn.execute(
                        sa.update(_episodes)
                        .where(_episodes.c.id == qa.episode_id, _episodes.c.quality.is_distinct_from(quality))
                        .values(quality=quality, updated_ns=time.time_ns())
                    )
            under_root = conn.execute(
                sa.select(_episodes.c.id).where(_episodes.c.location.startswith(prefix, autoescape=True))
            ).scalars()
            gone = sorted(set(under_root) - found)
            for i in range(0, len(gone), _DELETE_CHUNK):
                conn.execute(sa.delete(_episodes).where(_episodes.c.id.in_(gone[i : i + _DELETE_CHUNK])))
        _log.info("rebuilt index from %s: %d episodes, %d rows removed", root, len(found), len(gone))
        return RebuildResult(indexed=len(found), removed=len(gone), skipped=skipped)

    # -- internals -----------------------------------------------------------------------------

    @contextmanager
    def _read(self) -> Iterator[Connection]:
        self._check_open()
        with self._engine.connect() as conn, conn.begin():
            yield conn

    @contextmanager
    def _write(self) -> Iterator[Connection]:
        self._check_open()
        with self._engine.connect().execution_options(**{_IMMEDIATE: True}) as conn, conn.begin():
            yield conn

    def _check_open(self) -> None:
        if self._closed:
            raise RecordingError(f"episode index {self.url} is closed; open it again with EpisodeIndex.open")

    @staticmethod
    def _manifest_row(
        manifest: EpisodeManifest, *, location: str | Path | None, status: IndexStatus | None
    ) -> dict[str, Any]:
        extra = _typed_extra(manifest)
        quality = extra.quality
        return {
            "id": manifest.id,
            "task": manifest.task,
            "operator": manifest.operator,
            "rig": manifest.rig,
            "robots": list(extra.robots),
            "session": extra.session_id or None,
            "start_ns": manifest.start_ns,
            "end_ns": manifest.end_ns,
            "duration_s": manifest.duration_s,
            "size_bytes": sum(f.size for f in manifest.files),
            "quality": None if quality is None else _check_quality(quality),
            "status": _check_status(status) if status is not None else _index_status(manifest),
            "reason": manifest.reason,
            "location": None if location is None else _location(location),
            "fingerprint": None if extra.fingerprint is None else extra.fingerprint.digest,
            "outcome": extra.outcome,
            "instructions": _instruction_total(extra.instructions),
        }

    @staticmethod
    def _upsert_episode_rows(conn: Connection, rows: list[dict[str, Any]]) -> None:
        if not rows:
            return
        unique = list({r["id"]: r for r in rows}.values())  # one row per id per statement
        _ensure(conn, _operators, {r["operator"] for r in unique})
        sessions = {r["session"] for r in unique if r["session"] is not None}
        if sessions:
            _ensure(conn, _sessions, sessions)
        _upsert(conn, _episodes, unique, keep_if_null=("location", "quality", "outcome"))

    @staticmethod
    def _get_exact(conn: Connection, episode_id: str) -> EpisodeRecord:
        row = conn.execute(sa.select(_episodes).where(_episodes.c.id == episode_id)).mappings().one()
        return _episode(row)

    def _update(self, episode_id: str, **values: Any) -> EpisodeRecord:
        changed = sa.or_(*(_episodes.c[k].is_distinct_from(v) for k, v in values.items()))
        with self._write() as conn:
            exists = conn.execute(sa.select(_episodes.c.id).where(_episodes.c.id == episode_id)).first()
            if exists is None:
                raise RecordingError(
                    f"episode {episode_id!r} is not in the index {self.url}; upsert it (or rebuild) first"
                )
            conn.execute(
                sa.update(_episodes)
                .where(_episodes.c.id == episode_id, changed)
                .values(**values, updated_ns=time.time_ns())
            )
            return self._get_exact(conn, episode_id)


def _index_status(manifest: EpisodeManifest) -> IndexStatus:
    status: str = manifest.status
    if status == "recording":
        return "interrupted"
    if status not in _STATUSES:
        raise RecordingError(
            f"episode {manifest.id} has manifest status {status!r}, which the index does not know. "
            f"Available: {', '.join(_STATUSES)}"
        )
    return status  # type: ignore[return-value]


def _gate_filter(gate: str | None, passed: bool | None) -> sa.ColumnElement[bool]:
    """Episodes with a verdict of ``gate`` (any gate when ``None``) that passed/failed as asked; with
    ``gate`` None and ``passed`` True: checked, and no gate failed."""
    v = _gate_verdicts.c
    has = sa.select(v.episode_id).where(v.episode_id == _episodes.c.id)
    if gate is not None:
        has = has.where(v.gate == gate)
        if passed is not None:
            has = has.where(v.passed == passed)
        return has.exists()
    if passed is False:
        return has.where(v.passed == sa.false()).exists()
    return sa.and_(has.exists(), ~has.where(v.passed == sa.false()).exists())


def _robot_filter(robot: str, dialect: str) -> sa.ColumnElement[bool]:
    """Episodes whose ``robots`` JSON list holds ``robot`` (JSONB containment / SQLite json_each)."""
    if dialect == "postgresql":
        return sa.type_coerce(_episodes.c.robots, postgresql.JSONB).contains([robot])
    each = sa.func.json_each(_episodes.c.robots).table_valued("value")
    return sa.exists(sa.select(sa.literal(1)).select_from(each).where(each.c.value == robot))


def _verdict_rows(record: QaRecord) -> list[dict[str, Any]]:
    return [
        {
            "episode_id": record.episode_id,
            "gate": v.gate,
            "passed": v.passed,
            "value": _finite_or_none(v.value),
            "threshold": _finite_or_none(v.threshold),
            "unit": v.unit,
            "detail": v.detail,
            "checked_ns": record.checked_ns,
            "thresholds_hash": record.thresholds_hash,
        }
        for v in record.verdicts
    ]


def _replace_verdicts(conn: Connection, episode_id: str, rows: list[dict[str, Any]]) -> None:
    conn.execute(sa.delete(_gate_verdicts).where(_gate_verdicts.c.episode_id == episode_id))
    if rows:
        conn.execute(sa.insert(_gate_verdicts), rows)


def _finite_or_none(value: float | None) -> float | None:
    return value if value is not None and math.isfinite(value) else None


def _read_qa_or_warn(directory: Path) -> QaRecord | None:
    try:
        return read_qa(directory)
    except RecordingError as exc:
        _log.warning("rebuild: %s", exc)
        return None


def _read_label_or_warn(directory: Path) -> LabelRecord | None:
    try:
        return read_label(directory)
    except RecordingError as exc:
        _log.warning("rebuild: %s", exc)
        return None


def _verdict(row: sa.RowMapping) -> VerdictRecord:
    return VerdictRecord(
        episode_id=row["episode_id"],
        gate=row["gate"],
        passed=row["passed"],
        value=row["value"],
        threshold=row["threshold"],
        unit=row["unit"],
        detail=row["detail"],
        checked_ns=row["checked_ns"],
        thresholds_hash=row["thresholds_hash"],
    )


def _nonempty(name: str, value: str) -> str:
    if not value:
        raise ValueError(f"{name} must be a non-empty string")
    return value


def _extra(extra: Mapping[str, JsonValue] | None) -> dict[str, JsonValue] | None:
    return None if extra is None else dict(extra)


def _insert(conn: Connection, table: sa.Table) -> Any:
    """A dialect-specific INSERT with ``on_conflict_*`` (PostgreSQL and SQLite spell them alike)."""
    if conn.dialect.name == "postgresql":
        return postgresql.insert(table)
    return sqlite.insert(table)


def _ensure(conn: Connection, table: sa.Table, ids: set[str]) -> None:
    """Create bare rows for ``ids`` missing from ``table`` (foreign-key targets)."""
    now = time.time_ns()
    stmt = _insert(conn, table).on_conflict_do_nothing(index_elements=["id"])
    conn.execute(stmt, [{"id": i, "created_ns": now, "updated_ns": now} for i in sorted(ids)])


def _upsert(
    conn: Connection, table: sa.Table, rows: list[dict[str, Any]], *, keep_if_null: Collection[str]
) -> None:
    """``INSERT ... ON CONFLICT (id) DO UPDATE`` that touches the row only when a value differs.

    Columns in ``keep_if_null`` keep their stored value when the new one is NULL. ``created_ns`` is
    set on insert only; ``updated_ns`` on insert and on a real change.
    """
    now = time.time_ns()
    params = [{**r, "created_ns": now, "updated_ns": now} for r in rows]
    insert = _insert(conn, table)
    excluded = insert.excluded
    columns = [c for c in rows[0] if c != "id"]
    new = {
        c: sa.func.coalesce(excluded[c], table.c[c]) if c in keep_if_null else excluded[c] for c in columns
    }
    differs = sa.or_(*(table.c[c].is_distinct_from(new[c]) for c in columns))
    stmt = insert.on_conflict_do_update(
        index_elements=["id"], set_={**new, "updated_ns": excluded["updated_ns"]}, where=differs
    )
    conn.execute(stmt, params)


def _current_version(conn: Connection) -> int:
    version = conn.execute(sa.select(sa.func.max(_schema_version.c.version))).scalar_one_or_none()
    return int(version or 0)


def _migrate(engine: Engine, shown: str) -> None:
    """Create the schema on an empty database, or run the pending migrations, under an exclusive lock."""
    with engine.connect().execution_options(**{_IMMEDIATE: True}) as conn, conn.begin():
        if conn.dialect.name == "postgresql":
            conn.execute(sa.select(sa.func.pg_advisory_xact_lock(_PG_MIGRATION_LOCK)))
        inspector = sa.inspect(conn)
        if not inspector.has_table(_schema_version.name):
            if inspector.has_table(_episodes.name):
                raise RecordingError(
                    f"{shown} has an 'episodes' table but no schema_version table: it is not a telerig "
                    "index; point the index at an empty database"
                )
            _metadata.create_all(conn)
            conn.execute(sa.insert(_schema_version).values(version=SCHEMA_VERSION, applied_ns=time.time_ns()))
            _log.info("created episode index schema version %d in %s", SCHEMA_VERSION, shown)
            return
        current = _current_version(conn)
        if current > SCHEMA_VERSION:
            raise RecordingError(
                f"episode index {shown} has schema version {current}, newer than this telerig "
                f"supports ({SCHEMA_VERSION}); upgrade telerig"
            )
        for version in range(current + 1, SCHEMA_VERSION + 1):
            migration = _MIGRATIONS.get(version)
            if migration is None:
                raise RecordingError(
                    f"no migration to episode index schema version {version}; this is a telerig bug"
                )
            migration(conn)
            conn.execute(sa.insert(_schema_version).values(version=version, applied_ns=time.time_ns()))
            _log.info("migrated episode index %s to schema version %d", shown, version)
