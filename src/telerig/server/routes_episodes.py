"""The episode browser's API: list and filter episodes, their detail, plot and videos, labels, the
failures partition, and background jobs (exports, quality checks).

No path from a request reaches the file system unchecked: an episode id must match the store's id
pattern and name an episode the store finds; a camera must be one the manifest lists, its video a
file of the manifest inside the episode directory; an export name is one path component. The web
process never writes into an episode directory except the label record (``label.json``, beside
``qa.json``; see :mod:`telerig.store.label_file`) and the failures moves of the store itself; plots
are cached under ``<data root>/.cache/plots``.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import logging
import os
import threading
import time
from collections.abc import AsyncIterator, Callable, Iterator
from contextlib import asynccontextmanager, contextmanager
from pathlib import Path
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Body, Depends, FastAPI, HTTPException, Query, Request, status
from fastapi import Path as PathParam
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, RedirectResponse, Response
from pydantic import BaseModel, ConfigDict, Field, JsonValue

from telerig.errors import DependencyError, RecordingError, TelerigError
from telerig.server.accounts import AccountStore, LoginSession
from telerig.server.auth import COOKIE, client_address, require
from telerig.server.jobs import ExportJobRequest, Job, JobRunner, JobState, QaJobRequest, render_plot
from telerig.store.episodes import EpisodeManifest, EpisodeStore
from telerig.store.index import EpisodeIndex, EpisodeOrder, EpisodeRecord, IndexStatus, VerdictRecord
from telerig.store.label_file import LabelRecord, Outcome, read_label, write_label
from telerig.store.manifest_extra import EpisodeExtra
from telerig.store.qa_file import read_qa

__all__ = ["EpisodeCatalog", "episodes_router"]

_log = logging.getLogger("telerig.server.episodes")
_STATIC = Path(__file__).parent / "static"

#: The store's episode id pattern (``telerig.store.episodes``), for path parameters.
EPISODE_ID = r"^ep-\d{8}-\d{6}-[0-9a-f]{4}$"
_CAMERA = r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}$"
_GATE = r"^[a-z][a-z0-9_]{0,63}$"
#: Largest page of the episode list.
MAX_PAGE = 200
#: The in-memory index is rebuilt from the manifests when an episode arrives, moves or goes (the
#: partition directories change), after a change made here, and at the latest when older than this
#: [s] (a station's quality gates rewrite an episode's qa.json in place).
INDEX_MAX_AGE_S = 10.0
_PARTITIONS = ("episodes", "failures", "incomplete", ".incoming")
_PLOT_WIDTH_PX = 1600
_COMMITTED: tuple[IndexStatus, ...] = ("complete", "repaired", "failed_qa")
_EPOCH = dt.datetime(1970, 1, 1, tzinfo=dt.UTC)
_PAGE_HEADERS = {
    "Content-Security-Policy": "default-src 'self'; img-src 'self' data: blob:; media-src 'self'; "
    "connect-src 'self'; frame-ancestors 'none'",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "same-origin",
    "Cache-Control": "no-store",
}

#: The session of a request by at least a viewer / an operator (module level: FastAPI resolves
#: annotations from the module's globals).
Viewer = Annotated[LoginSession, Depends(require("viewer"))]
Operator = Annotated[LoginSession, Depends(require("operator"))]
EpisodeIdParam = Annotated[
    str, PathParam(pattern=EPISODE_ID, description="episode id ep-YYYYMMDD-HHMMSS-xxxx")
]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Problem(_Model):
    """An error: ``detail`` says what is wrong and what to do."""

    detail: str


class EpisodeRow(_Model):
    """One episode in the list."""

    id: str
    task: str
    operator: str
    rig: str
    robots: list[str]
    start_ns: int
    duration_s: float | None
    size_bytes: int
    quality: float | None = Field(description="quality score in [0, 1]; null until scored")
    status: IndexStatus
    outcome: Outcome | None = Field(
        description="the success/failure label (label.json, else the recording's mark)"
    )
    gates_checked: bool
    gates_failed: list[str]


class EpisodePage(_Model):
    """A page of the episode list: ``total`` episodes match, these are from ``offset``."""

    total: int
    offset: int
    limit: int
    episodes: list[EpisodeRow]


class GateOut(_Model):
    """One quality gate's verdict."""

    gate: str
    passed: bool | None
    value: float | None
    threshold: float | None
    unit: str
    detail: str


class CameraOut(_Model):
    """A camera video of the episode (``GET .../video/{name}``)."""

    name: str
    frames: int
    dropped: int
    width: int | None
    height: int | None
    fps: float | None
    codec: str | None
    size_bytes: int


class LabelOut(_Model):
    """An episode's success/failure label as set after recording."""

    episode_id: str
    outcome: Outcome
    by: str
    labelled_ns: int


class EpisodeDetail(_Model):
    """Everything the detail page shows of an episode."""

    id: str
    task: str
    operator: str
    rig: str
    robots: list[str]
    status: str
    partition: Literal["episodes", "failures", "incomplete"]
    start_ns: int
    end_ns: int | None
    duration_s: float | None
    size_bytes: int
    reason: str | None
    outcome: Outcome | None
    label: LabelOut | None
    failure_reasons: list[str]
    cameras: list[CameraOut]
    checked_ns: int | None
    gates_passed: bool | None
    gates: list[GateOut]
    score: float | None
    score_detail: dict[str, JsonValue] | None


class LabelRequest(_Model):
    """Label an episode a success or a failure."""

    outcome: Outcome


class MoveOut(_Model):
    """Where an episode lies after a move."""

    episode_id: str
    partition: Literal["episodes", "failures"]


_ERRORS: dict[int | str, dict[str, Any]] = {
    401: {"model": Problem, "description": "not logged in"},
    403: {"model": Problem, "description": "missing role or CSRF token"},
}
_NOT_FOUND: dict[int | str, dict[str, Any]] = {
    **_ERRORS,
    404: {"model": Problem, "description": "no such episode"},
}
_CONFLICT: dict[int | str, dict[str, Any]] = {
    **_NOT_FOUND,
    409: {"model": Problem, "description": "the episode is not where this needs it"},
}


class EpisodeCatalog:
    """The data root's episodes as the web server reads them: the store, and an in-memory index
    rebuilt from the manifests, ``qa.json`` and ``label.json`` files when a partition directory
    changed, after a change made here, or when older than ``max_age_s``. Never written to disk, so
    the server cannot race a station's index; the station's ``index.sqlite``, when there is one,
    gets the server's changes too.
    """

    def __init__(self, data_root: Path, *, max_age_s: float = INDEX_MAX_AGE_S) -> None:
        self.root = Path(data_root)
        self.store = EpisodeStore(self.root)
        self._max_age_s = max_age_s
        self._lock = threading.Lock()
        self._index: EpisodeIndex | None = None
        self._built = -1e9
        self._seen: tuple[int, ...] = ()

    def invalidate(self) -> None:
        with self._lock:
            self._built = -1e9

    @contextmanager
    def index(self) -> Iterator[EpisodeIndex]:
        """The in-memory index, fresh (held under the catalog's lock)."""
        with self._lock:
            seen = self._partitions()
            stale = time.monotonic() - self._built > self._max_age_s or seen != self._seen
            if self._index is None or stale:
                fresh = EpisodeIndex.open("sqlite://")
                if self.root.is_dir():
                    fresh.rebuild(self.store)
                if self._index is not None:
                    self._index.close()
                self._index, self._built, self._seen = fresh, time.monotonic(), seen
            yield self._index

    def _partitions(self) -> tuple[int, ...]:
        """Modification times of the partition directories (an episode added, moved or removed)."""
        out = []
        for name in _PARTITIONS:
            try:
                out.append((self.root / name).stat().st_mtime_ns)
            except OSError:
                out.append(0)
        return tuple(out)

    def close(self) -> None:
        with self._lock:
            if self._index is not None:
                self._index.close()
                self._index = None

    def committed_dir(self, episode_id: str, *, unfinished: bool = False) -> Path:
        """The directory of a committed episode (``episodes`` or ``failures``; ``incomplete`` too with
        ``unfinished``); 404 otherwise. ``episode_id`` was checked against the id pattern."""
        directory = self.store.locate(episode_id)
        allowed = ("episodes", "failures", "incomplete") if unfinished else ("episodes", "failures")
        if directory is None or directory.parent.name not in allowed or directory.parent.parent != self.root:
            raise HTTPException(status.HTTP_404_NOT_FOUND, f"no episode {episode_id} in this data root")
        return directory

    def sync_station_index(self, action: Callable[[EpisodeIndex], object]) -> None:
        """Apply a change to the data root's own ``index.sqlite`` too, when it has one (best effort:
        a station's index is a cache that ``telerig qa``/rebuild brings back in line)."""
        path = self.root / "index.sqlite"
        if not path.is_file():
            return
        try:
            with EpisodeIndex.open(path) as index:
                action(index)
        except TelerigError as exc:
            _log.warning("the station index %s was not updated: %s", path, exc)


def _manifest(directory: Path) -> EpisodeManifest:
    try:
        return EpisodeManifest.model_validate_json((directory / "manifest.json").read_bytes())
    except (OSError, ValueError):
        raise HTTPException(
            status.HTTP_404_NOT_FOUND, f"episode {directory.name} has no readable manifest"
        ) from None


def _row(record: EpisodeRecord, verdicts: list[VerdictRecord]) -> EpisodeRow:
    return EpisodeRow(
        id=record.id,
        task=record.task,
        operator=record.operator,
        rig=record.rig,
        robots=list(record.robots),
        start_ns=record.start_ns,
        duration_s=record.duration_s,
        size_bytes=record.size_bytes,
        quality=record.quality,
        status=record.status,
        outcome=record.outcome,
        gates_checked=bool(verdicts),
        gates_failed=[v.gate for v in verdicts if v.passed is False],
    )


def _utc_ns(moment: dt.datetime | None) -> int | None:
    """Nanoseconds since the epoch, clamped to the index's 64-bit integers."""
    if moment is None:
        return None
    if moment.tzinfo is None:
        moment = moment.replace(tzinfo=dt.UTC)
    try:
        ns = (moment - _EPOCH) // dt.timedelta(microseconds=1) * 1000
    except OverflowError:  # an offset that moves year 1 or 9999 out of range
        ns = -(2**63) if moment.year < 1970 else 2**63 - 1
    return max(-(2**63), min(2**63 - 1, ns))


def _camera_file(directory: Path, manifest: EpisodeManifest, camera: str) -> tuple[Path, int]:
    """The video of ``camera``: a file the manifest lists, inside the episode directory."""
    try:
        cameras = EpisodeExtra.of(manifest).cameras
    except RecordingError:
        cameras = {}
    listed = {f.path: f.size for f in manifest.files}
    record = cameras.get(camera)
    relative = record.file if record is not None else f"cameras/{camera}.mp4"
    if relative not in listed:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"episode {manifest.id} has no camera {camera!r}")
    path = directory / relative
    root = directory.resolve()
    resolved = path.resolve()
    if not resolved.is_relative_to(root) or path.is_symlink() or not resolved.is_file():
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"episode {manifest.id} has no camera {camera!r}")
    return resolved, listed[relative]


def _cameras(directory: Path, manifest: EpisodeManifest) -> list[CameraOut]:
    try:
        cameras = EpisodeExtra.of(manifest).cameras
    except RecordingError:
        return []
    sizes = {f.path: f.size for f in manifest.files}
    return [
        CameraOut(
            name=name,
            frames=c.frames,
            dropped=c.dropped,
            width=c.width,
            height=c.height,
            fps=c.fps,
            codec=c.codec,
            size_bytes=sizes[c.file],
        )
        for name, c in sorted(cameras.items())
        if c.file in sizes
    ]


def _audit(request: Request, session: LoginSession, action: str, target: str, detail: str = "") -> None:
    accounts: AccountStore = request.app.state.accounts
    accounts.audit(
        action, user=session.user.name, target=target, detail=detail, client=client_address(request)
    )


def episodes_router(data_root: Path, *, jobs: JobRunner | None = None) -> APIRouter:
    """The episode and job routes (and the episode browser page) over ``data_root``.

    Args:
        data_root: The data root (episodes, exports, ``control.sqlite`` with the jobs table).
        jobs: The job runner; one over ``data_root`` when ``None``.
    """
    catalog = EpisodeCatalog(data_root)
    runner = jobs if jobs is not None else JobRunner(data_root)
    plots = Path(data_root) / ".cache" / "plots"
    plot_lock = threading.Lock()

    @asynccontextmanager
    async def lifespan(_: FastAPI) -> AsyncIterator[None]:
        lost = runner.recover()
        if lost:
            _log.warning("jobs %s failed: their worker processes are gone", lost)
        yield
        runner.close()
        catalog.close()

    router = APIRouter(lifespan=lifespan)

    @router.get("/api/episodes", response_model=EpisodePage, responses=_ERRORS, tags=["episodes"])
    def list_episodes(
        _: Viewer,
        task: Annotated[str | None, Query(max_length=200)] = None,
        operator: Annotated[str | None, Query(max_length=200)] = None,
        robot: Annotated[str | None, Query(max_length=200)] = None,
        rig: Annotated[str | None, Query(max_length=200)] = None,
        status_: Annotated[
            list[IndexStatus] | None, Query(alias="status", max_length=5, description="default: committed")
        ] = None,
        gate: Annotated[str | None, Query(pattern=_GATE, description="only episodes with this gate")] = None,
        gate_passed: Annotated[bool | None, Query(description="with gate: it passed / failed")] = None,
        outcome: Annotated[Outcome | None, Query(description="only episodes labelled so")] = None,
        min_quality: Annotated[float | None, Query(ge=0.0, le=1.0)] = None,
        max_quality: Annotated[float | None, Query(ge=0.0, le=1.0)] = None,
        since: Annotated[
            dt.datetime | None, Query(description="start at or after (UTC unless offset)")
        ] = None,
        until: Annotated[dt.datetime | None, Query(description="start before (UTC unless offset)")] = None,
        sort: EpisodeOrder = "-start",
        limit: Annotated[int, Query(ge=1, le=MAX_PAGE)] = 50,
        offset: Annotated[int, Query(ge=0, le=10_000_000)] = 0,
    ) -> EpisodePage:
        """Episodes matching every given filter, newest first by default, a page at a time."""
        if min_quality is not None and max_quality is not None and min_quality > max_quality:
            raise RequestValidationError(
                [
                    {
                        "type": "value_error",
                        "loc": ("query", "min_quality"),
                        "msg": "min_quality is above max_quality",
                        "input": min_quality,
                    }
                ]
            )
        with catalog.index() as index:
            records = index.list_episodes(
                task=task,
                operator=operator,
                robot=robot,
                rig=rig,
                status=status_ or list(_COMMITTED),
                gate=gate,
                gate_passed=gate_passed,
                outcome=outcome,
                min_quality=min_quality,
                max_quality=max_quality,
                since_ns=_utc_ns(since),
                until_ns=_utc_ns(until),
                order=sort,
            )
            page = records[offset : offset + limit]
            verdicts = {r.id: index.verdicts(r.id) for r in page}
        return EpisodePage(
            total=len(records),
            offset=offset,
            limit=limit,
            episodes=[_row(r, verdicts.get(r.id, [])) for r in page],
        )

    @router.get(
        "/api/episodes/{episode_id}", response_model=EpisodeDetail, responses=_NOT_FOUND, tags=["episodes"]
    )
    def episode(episode_id: EpisodeIdParam, _: Viewer) -> EpisodeDetail:
        """An episode: manifest summary, cameras, label, gate verdicts and score."""
        directory = catalog.committed_dir(episode_id, unfinished=True)
        manifest = _manifest(directory)
        try:
            extra = EpisodeExtra.of(manifest)
        except RecordingError:
            extra = EpisodeExtra()
        try:
            qa = read_qa(directory)
        except RecordingError as exc:
            _log.warning("%s", exc)
            qa = None
        try:
            label = read_label(directory)
        except RecordingError as exc:
            _log.warning("%s", exc)
            label = None
        failure = catalog.store.failure(episode_id) if directory.parent.name == "failures" else None
        partition: Literal["episodes", "failures", "incomplete"] = directory.parent.name  # type: ignore[assignment]
        return EpisodeDetail(
            id=manifest.id,
            task=manifest.task,
            operator=manifest.operator,
            rig=manifest.rig,
            robots=list(extra.robots),
            status="failed_qa" if partition == "failures" else manifest.status,
            partition=partition,
            start_ns=manifest.start_ns,
            end_ns=manifest.end_ns,
            duration_s=manifest.duration_s,
            size_bytes=sum(f.size for f in manifest.files),
            reason=manifest.reason,
            outcome=label.outcome if label is not None else extra.outcome,
            label=None if label is None else LabelOut(**label.model_dump(exclude={"format"})),
            failure_reasons=[] if failure is None else list(failure.reasons),
            cameras=_cameras(directory, manifest),
            checked_ns=None if qa is None else qa.checked_ns,
            gates_passed=None if qa is None else qa.passed,
            gates=[] if qa is None else [GateOut(**v.model_dump()) for v in qa.verdicts],
            score=None if qa is None else qa.score_total,
            score_detail=None if qa is None else qa.score,
        )

    @router.get(
        "/api/episodes/{episode_id}/plot.png",
        response_class=FileResponse,
        responses={
            **_NOT_FOUND,
            200: {
                "content": {"image/png": {}},
                "description": "joints requested/sent/measured, gate markers",
            },
            503: {"model": Problem, "description": "matplotlib is not installed"},
        },
        tags=["episodes"],
    )
    def plot(episode_id: EpisodeIdParam, _: Viewer) -> FileResponse:
        """The episode's plot (PNG): joint trajectories, grippers, IK residuals, quality-gate markers.
        Rendered once per episode and ``qa.json`` version (in a worker process), cached under
        ``<data root>/.cache/plots``."""
        directory = catalog.committed_dir(episode_id, unfinished=True)
        manifest = _manifest(directory)
        key = hashlib.sha256(manifest.model_dump_json().encode())
        qa = directory / "qa.json"
        if qa.is_file():
            st = qa.stat()
            key.update(f"{st.st_mtime_ns}:{st.st_size}".encode())
        cached = plots / f"{episode_id}-{key.hexdigest()[:16]}.png"
        with plot_lock:
            if not cached.is_file():
                plots.mkdir(parents=True, exist_ok=True)
                for old in plots.glob(f"{episode_id}-*.png"):
                    old.unlink(missing_ok=True)
                tmp = cached.with_name(f".{cached.name}.{os.getpid()}.tmp.png")
                try:
                    render_plot(directory, tmp, _PLOT_WIDTH_PX)  # in a worker process at nice 10
                    os.replace(tmp, cached)
                except DependencyError as exc:
                    raise HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE, str(exc)) from None
                except RecordingError as exc:
                    raise HTTPException(status.HTTP_404_NOT_FOUND, str(exc)) from None
                finally:
                    tmp.unlink(missing_ok=True)
        return FileResponse(cached, media_type="image/png", headers={"Cache-Control": "private, max-age=60"})

    @router.get(
        "/api/episodes/{episode_id}/video/{camera}",
        response_class=FileResponse,
        responses={
            **_NOT_FOUND,
            200: {"content": {"video/mp4": {}}, "description": "the camera's MP4"},
            206: {"content": {"video/mp4": {}}, "description": "the requested byte range (Range header)"},
            416: {"description": "the range is outside the file"},
        },
        tags=["episodes"],
    )
    def video(
        episode_id: EpisodeIdParam,
        camera: Annotated[str, PathParam(pattern=_CAMERA, description="a camera of the manifest")],
        _: Viewer,
    ) -> FileResponse:
        """A camera's MP4; honours ``Range`` (206 Partial Content) so a ``<video>`` can seek."""
        directory = catalog.committed_dir(episode_id, unfinished=True)
        path, _size = _camera_file(directory, _manifest(directory), camera)
        return FileResponse(path, media_type="video/mp4", headers={"Cache-Control": "private, max-age=3600"})

    @router.post(
        "/api/episodes/{episode_id}/label", response_model=LabelOut, responses=_CONFLICT, tags=["episodes"]
    )
    def label(
        episode_id: EpisodeIdParam,
        body: Annotated[LabelRequest, Body()],
        request: Request,
        session: Operator,
    ) -> LabelOut:
        """Label an episode a success or a failure (``label.json`` beside its files; the index and the
        exports read it before the manifest's mark)."""
        directory = catalog.committed_dir(episode_id)
        record = LabelRecord(episode_id=episode_id, outcome=body.outcome, by=session.user.name)
        try:
            write_label(directory, record)
        except RecordingError as exc:
            raise HTTPException(status.HTTP_409_CONFLICT, str(exc)) from None
        catalog.invalidate()
        catalog.sync_station_index(lambda index: index.set_outcome(episode_id, body.outcome))
        _audit(request, session, "episode_labelled", episode_id, body.outcome)
        return LabelOut(**record.model_dump(exclude={"format"}))

    @router.post(
        "/api/episodes/{episode_id}/failures", response_model=MoveOut, responses=_CONFLICT, tags=["episodes"]
    )
    def to_failures(episode_id: EpisodeIdParam, request: Request, session: Operator) -> MoveOut:
        """Move an episode to the failures partition (exports leave it out)."""
        if catalog.committed_dir(episode_id).parent.name == "failures":
            raise HTTPException(status.HTTP_409_CONFLICT, f"episode {episode_id} is in failures already")
        reason = f"moved by {session.user.name}"
        try:
            path = catalog.store.move_to_failures(episode_id, [reason])
        except RecordingError as exc:
            raise HTTPException(status.HTTP_409_CONFLICT, str(exc)) from None
        catalog.invalidate()

        def station(index: EpisodeIndex) -> None:
            index.set_status(episode_id, "failed_qa", reason=reason)
            index.set_location(episode_id, path)

        catalog.sync_station_index(station)
        _audit(request, session, "episode_to_failures", episode_id, reason)
        return MoveOut(episode_id=episode_id, partition="failures")

    @router.post(
        "/api/episodes/{episode_id}/restore", response_model=MoveOut, responses=_CONFLICT, tags=["episodes"]
    )
    def restore(episode_id: EpisodeIdParam, request: Request, session: Operator) -> MoveOut:
        """Move an episode back from the failures partition."""
        if catalog.committed_dir(episode_id).parent.name != "failures":
            raise HTTPException(status.HTTP_409_CONFLICT, f"episode {episode_id} is not in failures")
        try:
            path = catalog.store.restore_from_failures(episode_id)
        except RecordingError as exc:
            raise HTTPException(status.HTTP_409_CONFLICT, str(exc)) from None
        catalog.invalidate()
        manifest = _manifest(path)

        def station(index: EpisodeIndex) -> None:
            index.upsert_episode(manifest, location=path)

        catalog.sync_station_index(station)
        _audit(request, session, "episode_restored", episode_id)
        return MoveOut(episode_id=episode_id, partition="episodes")

    # -- jobs ------------------------------------------------------------------------------------

    @router.post(
        "/api/jobs",
        response_model=Job,
        status_code=202,
        responses={**_ERRORS, 409: {"model": Problem, "description": "it cannot be started"}},
        tags=["jobs"],
    )
    def start_job(
        body: Annotated[ExportJobRequest | QaJobRequest, Body(discriminator="kind")],
        request: Request,
        session: Operator,
    ) -> Job:
        """Start an export or a quality check in a worker process; poll ``GET /api/jobs/{id}``."""
        job = runner.submit(body, session.user.name)
        _audit(
            request, session, "job_started", f"job {job.id}", f"{body.kind} {body.params.model_dump_json()}"
        )
        return job

    @router.get("/api/jobs", response_model=list[Job], responses=_ERRORS, tags=["jobs"])
    def jobs_list(
        _: Viewer,
        state: JobState | None = None,
        limit: Annotated[int, Query(ge=1, le=500)] = 50,
    ) -> list[Job]:
        """Jobs, newest first (every client sees every job)."""
        runner.recover()
        return runner.store.jobs(limit=limit, state=state)

    @router.get(
        "/api/jobs/{job_id}",
        response_model=Job,
        responses={**_ERRORS, 404: {"model": Problem, "description": "no such job"}},
        tags=["jobs"],
    )
    def job(job_id: Annotated[int, PathParam(ge=1, le=2**62)], _: Viewer) -> Job:
        """One job: state, progress (done/total, message), error or result."""
        try:
            return runner.store.get(job_id)
        except KeyError:
            raise HTTPException(status.HTTP_404_NOT_FOUND, f"no job {job_id}") from None

    # -- the page ----------------------------------------------------------------------------------

    @router.get("/episodes", include_in_schema=False, response_model=None)
    def page(request: Request) -> Response:
        accounts: AccountStore = request.app.state.accounts
        if accounts.session(request.cookies.get(COOKIE, "")) is None:
            return RedirectResponse("/login", status_code=303)
        return FileResponse(_STATIC / "episodes.html", headers=_PAGE_HEADERS)

    @router.get("/assets/episodes.js", include_in_schema=False)
    def script() -> FileResponse:
        return FileResponse(_STATIC / "episodes.js", media_type="text/javascript", headers=_PAGE_HEADERS)

    return router
