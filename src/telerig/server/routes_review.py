"""Human review of the annotation pipeline's segments: list what there is to review, show one video's
segments (and the clips' annotation text), and write a reviewer's edits back with who made them.

What is reviewed: the ``segments.json`` sidecar of an episode in the data root (``episodes/`` or
``failures/``), and ``<processed>/items/<video item id>/segment/segments.json`` of a plain video the
pipeline processed. Ids come from the store's patterns (``ep-...``, ``video-<12 hex>``) and are
resolved through the store and the processed layout; no path from a request reaches the file system.
The video served is the one the record names, and only when it is the item's own: a camera file the
episode's manifest lists inside its directory, or for a plain video the file whose item id (a hash
of its absolute path) is the requested id.

A plain video's reviewed segments are kept in ``<processed>/items/<id>/review/segments.json``
(outside the segment stage's directory, which a re-run of that stage empties) and read merged over
the stage's latest proposals with the store's ``merge_machine``, as the stage itself does for an
episode's sidecar. Each edit also updates the segment stage's own copy where there is one, which
the clips stage reads when it next runs.

Edits (operator or admin; a viewer reads) go through :mod:`telerig.store.segments_file`: accept,
reject, rename, move a boundary, draw a new segment, and undo one's own last edit. Each is stamped
``human:<user>`` with ``edited_at`` and written atomically. Every write names the ``version`` it was
made against (a hash of the file's bytes, also the ``ETag``); a stale one is refused with 409, so
two reviewers never silently overwrite each other. Overlapping segments are allowed: two hands or two
robots act at once, and each segment says which (``actor``).

Undo is kept in memory per reviewer and video (the last :data:`UNDO_DEPTH` edits): a restart
forgets it, and an undo is refused (409) when someone changed that segment since.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import logging
import math
import threading
from collections import deque
from collections.abc import Callable, Coroutine
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Body, Depends, HTTPException, Request, Response, status
from fastapi import Path as PathParam
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse, RedirectResponse
from fastapi.routing import APIRoute
from pydantic import BaseModel, ConfigDict, Field, field_validator

from telerig.errors import ProcessError, RecordingError
from telerig.process.stage import record_edit, video_item_id
from telerig.server.accounts import AccountStore, LoginSession
from telerig.server.auth import COOKIE, PAGE_HEADERS, client_address, require
from telerig.store.episodes import EpisodeManifest, EpisodeStore
from telerig.store.segments_file import (
    SEGMENTS_FILE,
    Segment,
    SegmentsRecord,
    edit_segment,
    merge_machine,
    new_segment,
    parse_segments,
    write_episode_segments,
    write_segments,
)

__all__ = ["UNDO_DEPTH", "review_router"]

_log = logging.getLogger("telerig.server.review")
_STATIC = Path(__file__).parent / "static"

#: An item id: an episode id of the store, or a plain video's ``video-<sha1[:12]>``.
ITEM_ID = r"^(ep-\d{8}-\d{6}-[0-9a-f]{4}|video-[0-9a-f]{12})$"
_SEGMENT_ID = r"^[0-9a-f]{8}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{12}$"
_VERSION = r"^[0-9a-f]{16}$"
_LABEL = r"^[^\x00-\x1f\x7f]{1,64}$"
#: Edits one reviewer can undo per video.
UNDO_DEPTH = 100
#: Most items listed (a lab with more reviews them through ``telerig process`` queries first).
MAX_ITEMS = 5000
_MAX_SEGMENTS_BYTES = 8 << 20
_MAX_ANNOTATIONS_BYTES = 16 << 20
#: A plain video's reviewed segments: ``<processed>/items/<id>/review/segments.json`` (no stage's).
_REVIEW_DIR = "review"
_VIDEO_SUFFIXES = frozenset({".mp4", ".mov", ".mkv", ".webm"})
_MEDIA = {".mp4": "video/mp4", ".mov": "video/quicktime", ".mkv": "video/x-matroska", ".webm": "video/webm"}

Reviewer = Annotated[LoginSession, Depends(require("operator"))]
Viewer = Annotated[LoginSession, Depends(require("viewer"))]
ItemIdParam = Annotated[
    str, PathParam(pattern=ITEM_ID, description="episode id, or video-<12 hex> of a processed video")
]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class Problem(_Model):
    """An error: ``detail`` says in one line what is wrong and what to do."""

    detail: str


class ReviewItem(_Model):
    """A video with segments to review."""

    id: str
    kind: Literal["episode", "video"]
    title: str
    duration_s: float
    segments: int
    proposed: int
    accepted: int
    corrected: int
    rejected: int


class SegmentOut(_Model):
    """A segment as the review page shows it (the file's fields, plus the clip's annotation)."""

    id: str
    label: str
    confidence: float
    start_s: float
    end_s: float
    source: str
    status: str
    edited_at: dt.datetime | None
    actor: str | None
    origin: str | None
    annotation: str | None = Field(description="the clip's scene and action description, where annotated")


class ReviewDetail(_Model):
    """One video's segments, and the ``version`` an edit of them must name."""

    id: str
    kind: Literal["episode", "video"]
    title: str
    video: str
    duration_s: float
    version: str
    empty: bool
    segments: list[SegmentOut]


class _Edit(_Model):
    version: str = Field(pattern=_VERSION, description="the version the edit was made against")


class _OnSegment(_Edit):
    segment_id: str = Field(pattern=_SEGMENT_ID)


class AcceptEdit(_OnSegment):
    """Keep a segment as it is."""

    op: Literal["accept"]


class RejectEdit(_OnSegment):
    """Mark a segment wrong (kept in the file, marked rejected)."""

    op: Literal["reject"]


class _Labelled(BaseModel):
    @field_validator("label", mode="before", check_fields=False)
    @classmethod
    def _strip(cls, value: Any) -> Any:
        return value.strip() if isinstance(value, str) else value


class RenameEdit(_OnSegment, _Labelled):
    """Give a segment another label."""

    op: Literal["rename"]
    label: str = Field(pattern=_LABEL, description="1-64 characters, no control characters")


class BoundsEdit(_OnSegment):
    """Move a segment's start and/or end [s, 0.01 s resolution, within the video]."""

    op: Literal["bounds"]
    start_s: float | None = Field(default=None, ge=0.0, le=1e7)
    end_s: float | None = Field(default=None, ge=0.0, le=1e7)


class AddEdit(_Edit, _Labelled):
    """Draw a new segment [s, within the video, start before end]."""

    op: Literal["add"]
    label: str = Field(pattern=_LABEL, description="1-64 characters, no control characters")
    start_s: float = Field(ge=0.0, le=1e7)
    end_s: float = Field(ge=0.0, le=1e7)
    actor: str | None = Field(default=None, min_length=1, max_length=64)


class UndoEdit(_Edit):
    """Undo this reviewer's last edit of this video."""

    op: Literal["undo"]


Edit = AcceptEdit | RejectEdit | RenameEdit | BoundsEdit | AddEdit | UndoEdit

_ERRORS: dict[int | str, dict[str, Any]] = {
    401: {"model": Problem, "description": "not logged in"},
    403: {"model": Problem, "description": "missing role or CSRF token"},
    404: {"model": Problem, "description": "no such item, or it has no segments"},
    422: {"model": Problem, "description": "invalid request (one line)"},
}
_WRITE_ERRORS: dict[int | str, dict[str, Any]] = {
    **_ERRORS,
    409: {"model": Problem, "description": "stale version, or nothing to undo"},
}


class _OneLineErrors(APIRoute):
    """422 answers as one line (``field: reason``) instead of FastAPI's error list."""

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handler = super().get_route_handler()

        async def wrapped(request: Request) -> Response:
            try:
                return await handler(request)
            except RequestValidationError as exc:
                return JSONResponse({"detail": _one_line(exc)}, status_code=422)

        return wrapped


def _one_line(exc: RequestValidationError) -> str:
    errors = list(exc.errors())
    if not errors:
        return "invalid request"
    first = errors[0]
    loc = ".".join(str(p) for p in first.get("loc", ()) if p not in ("body",)) or "body"
    msg = " ".join(str(first.get("msg", "invalid")).split())
    more = f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""
    return f"{loc}: {msg}{more}"[:300]


@dataclass(frozen=True)
class _Target:
    """Where one item's segments and video are."""

    id: str
    kind: Literal["episode", "video"]
    path: Path  # the segments.json
    episode_dir: Path | None
    review: Path | None = None  # a plain video's reviewed copy, outside the stage's directory


@dataclass(frozen=True)
class _Undo:
    before: Segment | None  # None: the edit drew it
    after: Segment


def _version(raw: bytes) -> str:
    return hashlib.sha256(raw).hexdigest()[:16]


def review_router(data_root: Path, processed_root: Path | None = None) -> APIRouter:
    """The review routes and page over ``data_root`` (episodes) and ``processed_root`` (default
    ``<data_root>/processed``, where ``telerig process`` writes by default)."""
    root = Path(data_root)
    processed = Path(processed_root) if processed_root is not None else root / "processed"
    store = EpisodeStore(root)
    lock = threading.Lock()  # one read-check-write at a time (the version check is then exact)
    undo: dict[tuple[str, str], deque[_Undo]] = {}
    router = APIRouter(route_class=_OneLineErrors)

    def target(item_id: str) -> _Target:
        if item_id.startswith("ep-"):
            directory = store.locate(item_id)
            if (
                directory is None
                or directory.parent.name not in ("episodes", "failures")
                or directory.parent.parent != root
            ):
                raise HTTPException(status.HTTP_404_NOT_FOUND, f"no episode {item_id} in this data root")
            return _Target(item_id, "episode", directory / SEGMENTS_FILE, directory)
        folder = processed / "items" / item_id
        return _Target(
            item_id, "video", folder / "segment" / SEGMENTS_FILE, None, folder / _REVIEW_DIR / SEGMENTS_FILE
        )

    def read(t: _Target, path: Path) -> SegmentsRecord | None:
        try:
            if path.is_symlink() or not path.is_file():
                return None
            if path.stat().st_size > _MAX_SEGMENTS_BYTES:
                raise HTTPException(status.HTTP_409_CONFLICT, f"{path.name} of {t.id} is too large")
            raw = path.read_bytes()
        except OSError as exc:
            raise HTTPException(
                status.HTTP_404_NOT_FOUND, f"cannot read the segments of {t.id}: {exc.strerror or exc}"
            ) from None
        try:
            return parse_segments(raw, where=f"the segments of {t.id}")
        except RecordingError as exc:
            raise HTTPException(status.HTTP_409_CONFLICT, str(exc)) from None

    def load(t: _Target) -> tuple[SegmentsRecord, str]:
        """The segments of ``t`` and their version. A plain video's: the stage's latest proposals
        merged under its reviewed copy (a stage re-run empties its own directory; the review stays)."""
        record = read(t, t.path)
        if t.review is not None:
            reviewed = read(t, t.review)
            if reviewed is not None:
                record = reviewed if record is None else merge_machine(reviewed, record)
        if record is None:
            raise HTTPException(status.HTTP_404_NOT_FOUND, f"{t.id} has no segments to review yet")
        if t.kind == "episode" and record.episode_id != t.id:
            raise HTTPException(
                status.HTTP_409_CONFLICT,
                f"the segments beside {t.id} are another episode's; re-run telerig process",
            )
        return record, _version(record.to_json().encode())

    def video_file(t: _Target, record: SegmentsRecord) -> Path:
        missing = HTTPException(status.HTTP_404_NOT_FOUND, f"the video of {t.id} is not available")
        if t.episode_dir is not None:
            manifest = _manifest(t.episode_dir)
            if record.video not in {f.path for f in manifest.files}:
                raise missing
            path = t.episode_dir / record.video
            base = t.episode_dir.resolve()
        else:
            named = Path(record.video)
            path = named if named.is_absolute() else processed / named
            base = None
        try:
            resolved = path.resolve()
        except (OSError, RuntimeError):
            raise missing from None
        if base is not None and not resolved.is_relative_to(base):
            raise missing
        if base is None and video_item_id(path) != t.id and video_item_id(resolved) != t.id:
            raise missing  # a plain video is served only when it is the file the item id hashes
        if path.is_symlink() or resolved.suffix.lower() not in _VIDEO_SUFFIXES or not resolved.is_file():
            raise missing
        return resolved

    def title(t: _Target, record: SegmentsRecord) -> str:
        if t.episode_dir is not None:
            try:
                return f"{t.id} · {_manifest(t.episode_dir).task}"
            except HTTPException:
                return t.id
        return Path(record.video).name

    def annotations(item_id: str) -> dict[str, str]:
        """Clip id -> "scene: action description" from the annotate stage, where it ran."""
        path = processed / "items" / item_id / "annotate" / "annotations.json"
        try:
            if not path.is_file() or path.stat().st_size > _MAX_ANNOTATIONS_BYTES:
                return {}
            data = json.loads(path.read_bytes())
        except (OSError, ValueError) as exc:
            _log.warning("annotations of %s unreadable: %s", item_id, exc)
            return {}
        out: dict[str, str] = {}
        if not isinstance(data, dict):
            return out
        for key, value in data.items():
            if not isinstance(value, dict):
                continue
            action = value.get("action")
            text = action.get("description") if isinstance(action, dict) else None
            scene = value.get("scene")
            parts = [p for p in (scene, text) if isinstance(p, str) and p]
            if parts:
                out[str(key)] = ": ".join(parts)[:2000]
        return out

    def detail(t: _Target, record: SegmentsRecord, version: str) -> ReviewDetail:
        notes = annotations(t.id)
        return ReviewDetail(
            id=t.id,
            kind=t.kind,
            title=title(t, record),
            video=record.video if t.kind == "episode" else Path(record.video).name,
            duration_s=record.duration_s,
            version=version,
            empty=record.empty,
            segments=[SegmentOut(**s.model_dump(), annotation=notes.get(s.id)) for s in record.segments],
        )

    def row(t: _Target) -> ReviewItem | None:
        try:
            record, _ = load(t)
        except HTTPException:
            return None
        counts = dict.fromkeys(("proposed", "accepted", "corrected", "rejected"), 0)
        for s in record.segments:
            counts[s.status] += 1
        return ReviewItem(
            id=t.id,
            kind=t.kind,
            title=title(t, record),
            duration_s=record.duration_s,
            segments=len(record.segments),
            **counts,
        )

    @router.get("/api/review", response_model=list[ReviewItem], responses=_ERRORS, tags=["review"])
    def items(_: Viewer) -> list[ReviewItem]:
        """Videos with segments to review: episodes with a segments sidecar, then processed videos."""
        targets: list[_Target] = []
        for summary in store.list(include_failures=True):
            if summary.partition in ("episodes", "failures") and (summary.path / SEGMENTS_FILE).is_file():
                targets.append(_Target(summary.id, "episode", summary.path / SEGMENTS_FILE, summary.path))
        folder = processed / "items"
        if folder.is_dir():
            for entry in sorted(folder.iterdir()):
                named = entry / "segment" / SEGMENTS_FILE, entry / _REVIEW_DIR / SEGMENTS_FILE
                if entry.name.startswith("video-") and any(p.is_file() for p in named):
                    targets.append(target(entry.name))
        out = []
        for t in targets[:MAX_ITEMS]:
            r = row(t)
            if r is not None:
                out.append(r)
        return out

    @router.get(
        "/api/review/{item_id}", response_model=ReviewDetail, responses=_WRITE_ERRORS, tags=["review"]
    )
    def segments(item_id: ItemIdParam, response: Response, _: Viewer) -> ReviewDetail:
        """One video's segments with their annotation text, and the version to edit them against
        (also the ``ETag``)."""
        t = target(item_id)
        record, version = load(t)
        response.headers["ETag"] = f'"{version}"'
        return detail(t, record, version)

    @router.get(
        "/api/review/{item_id}/video",
        response_class=FileResponse,
        responses={
            **_ERRORS,
            200: {"content": {"video/mp4": {}}, "description": "the video the segments are on"},
            206: {"content": {"video/mp4": {}}, "description": "the requested byte range (Range header)"},
            409: {"model": Problem, "description": "the segments file is unreadable"},
            416: {"description": "the range is outside the file"},
        },
        tags=["review"],
    )
    def video(item_id: ItemIdParam, _: Viewer) -> FileResponse:
        """The video the segments are on; honours ``Range`` so the page can seek."""
        t = target(item_id)
        record = load(t)[0]
        path = video_file(t, record)
        return FileResponse(
            path,
            media_type=_MEDIA.get(path.suffix.lower(), "application/octet-stream"),
            headers={"Cache-Control": "private, max-age=3600"},
        )

    @router.post(
        "/api/review/{item_id}/edits", response_model=ReviewDetail, responses=_WRITE_ERRORS, tags=["review"]
    )
    def edit(
        item_id: ItemIdParam,
        body: Annotated[Edit, Body(discriminator="op")],
        request: Request,
        response: Response,
        session: Reviewer,
    ) -> ReviewDetail:
        """Apply one reviewer edit (accept, reject, rename, bounds, add, undo) made against
        ``version``; answers the segments after it and their new version."""
        user = session.user.name
        t = target(item_id)
        with lock:
            record, version = load(t)
            if body.version != version:
                raise HTTPException(
                    status.HTTP_409_CONFLICT,
                    f"the segments of {item_id} changed since version {body.version} "
                    "(someone else edited them); reload and redo the edit",
                )
            stack = undo.setdefault((user, item_id), deque(maxlen=UNDO_DEPTH))
            updated, change, what = _apply(record, body, user, stack)
            try:
                stage_copy = processed / "items" / t.id / "segment" / SEGMENTS_FILE
                if t.episode_dir is not None:
                    write_episode_segments(t.episode_dir, updated)
                elif t.review is not None:
                    t.review.parent.mkdir(exist_ok=True)
                    write_segments(t.review, updated)
                if stage_copy.is_file() and not stage_copy.is_symlink():
                    write_segments(stage_copy, updated)  # what the clips stage reads on its next run
                    _note_edit(stage_copy)
            except (RecordingError, ValueError) as exc:
                raise HTTPException(status.HTTP_409_CONFLICT, str(exc)) from None
            if change is not None:
                stack.append(change)
            else:
                stack.pop()
            record, new_version = load(t)
        accounts: AccountStore = request.app.state.accounts
        accounts.audit(
            "segments_edited", user=user, target=item_id, detail=what, client=client_address(request)
        )
        response.headers["ETag"] = f'"{new_version}"'
        return detail(t, record, new_version)

    @router.get("/review", include_in_schema=False, response_model=None)
    def page(request: Request) -> Response:
        accounts: AccountStore = request.app.state.accounts
        if accounts.session(request.cookies.get(COOKIE, "")) is None:
            return RedirectResponse("/login", status_code=303)
        return FileResponse(_STATIC / "review.html", headers=PAGE_HEADERS)

    @router.get("/assets/review.js", include_in_schema=False)
    def script() -> FileResponse:
        return FileResponse(_STATIC / "review.js", media_type="text/javascript", headers=PAGE_HEADERS)

    @router.get("/assets/review.css", include_in_schema=False)
    def style() -> FileResponse:
        return FileResponse(_STATIC / "review.css", media_type="text/css", headers=PAGE_HEADERS)

    return router


def _manifest(directory: Path) -> EpisodeManifest:
    try:
        return EpisodeManifest.model_validate_json((directory / "manifest.json").read_bytes())
    except (OSError, ValueError):
        raise HTTPException(
            status.HTTP_404_NOT_FOUND, f"episode {directory.name} has no readable manifest"
        ) from None


def _replace(record: SegmentsRecord, segments: list[Segment]) -> SegmentsRecord:
    data = record.model_dump(by_alias=True)
    data["segments"] = [s.model_dump() for s in sorted(segments, key=lambda s: (s.start_s, s.end_s, s.id))]
    data["empty"] = not segments
    return SegmentsRecord.model_validate(data)


def _unprocessable(message: str) -> HTTPException:
    return HTTPException(422, message)


def _check_times(record: SegmentsRecord, start: float | None, end: float | None) -> None:
    for name, value in (("start_s", start), ("end_s", end)):
        if value is None:
            continue
        if not math.isfinite(value) or value < 0:
            raise _unprocessable(f"{name}: {value} is not a time in the video")
        if round(value, 2) > record.duration_s:
            raise _unprocessable(f"{name}: {value} s is after the video's end ({record.duration_s} s)")


def _apply(
    record: SegmentsRecord, body: Edit, user: str, stack: deque[_Undo]
) -> tuple[SegmentsRecord, _Undo | None, str]:
    """The record after ``body``, the undo entry it leaves (``None``: it was an undo), and a line
    for the audit log.

    Raises:
        HTTPException: 404 no such segment, 409 nothing to undo / changed since, 422 invalid edit.
    """
    now = dt.datetime.now(dt.UTC)
    by = {s.id: s for s in record.segments}
    if isinstance(body, UndoEdit):
        if not stack:
            raise HTTPException(status.HTTP_409_CONFLICT, "nothing of yours to undo on this video")
        last = stack[-1]
        if by.get(last.after.id) != last.after:
            stack.clear()
            raise HTTPException(
                status.HTTP_409_CONFLICT, "that segment changed since your edit; undo is not possible"
            )
        rest = [s for s in record.segments if s.id != last.after.id]
        if last.before is not None:
            rest.append(last.before)
        return _replace(record, rest), None, f"undo {last.after.id}"
    if isinstance(body, AddEdit):
        _check_times(record, body.start_s, body.end_s)
        try:
            drawn = new_segment(
                body.label, body.start_s, body.end_s, confidence=1.0, source=f"human:{user}", actor=body.actor
            )
        except ValueError as exc:
            raise _unprocessable(_first_line(exc)) from None
        drawn = Segment.model_validate({**drawn.model_dump(), "status": "corrected", "edited_at": now})
        return (
            _replace(record, [*record.segments, drawn]),
            _Undo(None, drawn),
            f"add {drawn.id} {drawn.label!r} {drawn.start_s}-{drawn.end_s}",
        )
    before = by.get(body.segment_id)
    if before is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"no segment {body.segment_id} in this video")
    kwargs: dict[str, Any] = {}
    if isinstance(body, AcceptEdit):
        state: Literal["accepted", "corrected", "rejected"] = "accepted"
        what = "accept"
    elif isinstance(body, RejectEdit):
        state, what = "rejected", "reject"
    elif isinstance(body, RenameEdit):
        state, what = "corrected", f"rename {before.label!r} -> {body.label!r}"
        kwargs["label"] = body.label
    else:
        if body.start_s is None and body.end_s is None:
            raise _unprocessable("bounds: give start_s, end_s or both")
        _check_times(record, body.start_s, body.end_s)
        state = "corrected"
        what = f"bounds {before.start_s}-{before.end_s} -> {body.start_s}-{body.end_s}"
        kwargs.update(start_s=body.start_s, end_s=body.end_s)
    try:
        updated = edit_segment(record, before.id, by=user, status=state, now=now, **kwargs)
    except ValueError as exc:
        raise _unprocessable(_first_line(exc)) from None
    after = next(s for s in updated.segments if s.id == before.id)
    return updated, _Undo(before, after), f"{what} {before.id}"


def _first_line(exc: Exception) -> str:
    text = str(exc)
    if "validation error" in text:  # pydantic: "1 validation error for Segment\n<field>\n  <msg>"
        lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
        text = ": ".join(lines[1:3]) if len(lines) >= 3 else lines[-1]
    return " ".join(text.split())[:300]


def _note_edit(stage_copy: Path) -> None:
    """Mark the segment stage's output as edited, so the next ``telerig process`` cuts, annotates
    and lays out the clips again from the edit (the segment stage itself is kept)."""
    try:
        record_edit(stage_copy.parent, stage_copy.read_bytes())
    except (ProcessError, OSError) as exc:  # the runner redoes a stage with unreadable provenance
        _log.warning("review edit of %s not noted in its provenance: %s", stage_copy, exc)
