"""``segments.json``: the actions found in one video, by a segmenter or a person, in one schema.

The annotation pipeline's segmentation stage (:mod:`telerig.process.segment`) writes it per item;
for an episode it also sits beside the episode's files (like ``qa.json`` and ``label.json``), so the
exports and ``telerig episodes show`` read it without importing the pipeline. A reviewer's edits
(accept, move a boundary, rename, reject) are written back into the same file with who made them:
machine proposals and human labels share one schema, told apart by ``source`` and ``status``.

Times are seconds on the video's own timeline (its first frame at 0), rounded to 0.01 s.
"""

from __future__ import annotations

import datetime as dt
import math
import uuid
from collections.abc import Iterable
from pathlib import Path
from typing import Literal

from pydantic import (
    AwareDatetime,
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

from telerig.errors import RecordingError
from telerig.store.sidecar import read_sidecar, write_sidecar

__all__ = [
    "MAX_SEGMENTS",
    "SEGMENTS_FILE",
    "SEGMENTS_SCHEMA",
    "Segment",
    "SegmentStatus",
    "SegmentsRecord",
    "edit_segment",
    "machine_source",
    "merge_machine",
    "new_segment",
    "parse_segments",
    "read_episode_segments",
    "read_segments",
    "write_episode_segments",
    "write_segments",
]

#: File name, in a stage's output directory and in the episode directory.
SEGMENTS_FILE = "segments.json"
#: Version of the layout.
SEGMENTS_SCHEMA = 1
#: Most segments one file holds: one per 0.5 s of a 1.4 h video; a segmenter that finds more is
#: broken, and a file with more is not ours.
MAX_SEGMENTS = 10_000
#: Larger is not a segments file (a segment is ~250 bytes of JSON); refuse before parsing it.
_MAX_BYTES = 8 << 20
#: ``end_s`` may pass ``duration_s`` by this much [s] (the last frame's length, rounding).
_SLACK_S = 0.5

SegmentStatus = Literal["proposed", "accepted", "corrected", "rejected"]
"""``proposed``: a segmenter's, unreviewed. ``accepted``: a person kept it as it was. ``corrected``:
a person moved a boundary or renamed it (or drew it). ``rejected``: a person said it is wrong (kept,
so the segmenter is not trusted with it again and the rejection can be counted)."""

#: Namespace of the name-based segment ids (:func:`new_segment` with a ``key``).
_NAMESPACE = uuid.UUID("5b0f3d1e-7c1a-4b7e-9a55-2f1d6c7e0a15")
_SOURCE = r"^(machine:[A-Za-z0-9_.\-]{1,64}@[A-Za-z0-9_.\-]{1,32}|human:[^\s\x00-\x1f]{1,64})$"
_LABEL = r"^[^\x00-\x1f]{1,64}$"


def _time(value: float) -> float:
    """Round to the file's resolution (0.01 s); ``round`` rather than truncation so a re-read is stable."""
    return round(value, 2) + 0.0  # + 0.0: no -0.0 in the file


class Segment(BaseModel):
    """One action on a video's timeline.

    Attributes:
        id: A UUID (name-based for a segmenter's, see :func:`new_segment`; random for a person's);
            also the clip file's name (``<id>.mp4``) in the later stages.
        label: What happens (``reach``, ``grasp``, ``transport``, ``manipulation``...), 1-64 chars.
        confidence: How sure the segmenter is, 0..1 (1.0 for a person's label).
        start_s: Start on the video's timeline [s], >= 0, 0.01 s resolution.
        end_s: End [s], > ``start_s``.
        source: Who proposed or last edited it: ``machine:<segmenter>@<version>`` or ``human:<user>``.
        status: Review state, see :data:`SegmentStatus`.
        edited_at: When a person last changed it (ISO 8601 with a time zone); ``None`` if nobody did.
        actor: Which robot (id) or hand did it, where the segmenter knows; ``None`` otherwise.
        origin: The machine ``source`` a person's edit replaced (what proposed it), else ``None``.
    """

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    id: str = Field(min_length=36, max_length=36)
    label: str = Field(pattern=_LABEL)
    confidence: float = Field(ge=0.0, le=1.0)
    start_s: float = Field(ge=0.0, le=1e7)
    end_s: float = Field(ge=0.0, le=1e7)
    source: str = Field(pattern=_SOURCE)
    status: SegmentStatus = "proposed"
    edited_at: AwareDatetime | None = None
    actor: str | None = Field(default=None, min_length=1, max_length=64)
    origin: str | None = Field(default=None, pattern=_SOURCE)

    @field_validator("id")
    @classmethod
    def _uuid(cls, value: str) -> str:
        try:
            parsed = uuid.UUID(value)
        except ValueError:
            raise ValueError(f"{value!r} is not a UUID") from None
        if str(parsed) != value:
            raise ValueError(f"{value!r} is not a lower-case hyphenated UUID")
        return value

    @field_validator("start_s", "end_s")
    @classmethod
    def _rounded(cls, value: float) -> float:
        return _time(value)

    @model_validator(mode="after")
    def _ordered(self) -> Segment:
        if not self.end_s > self.start_s:
            raise ValueError(f"end_s {self.end_s} is not after start_s {self.start_s}")
        return self

    @property
    def duration_s(self) -> float:
        """Length [s]."""
        return self.end_s - self.start_s


class SegmentsRecord(BaseModel):
    """The content of ``segments.json``.

    Attributes:
        schema_: Layout version (``"schema"`` in the file).
        video: The video the times refer to: relative to the episode directory for an episode's
            camera (``cameras/scene.mp4``), else a path (the pipeline writes it relative to its
            processed root where it lies inside it).
        duration_s: The video's length [s].
        segments: The actions, sorted by start.
        empty: The video has no action (``segments`` is then empty): kept and marked, not an error.
        episode_id: The episode, for the copy beside an episode's files (checked on reading it).
        video_offset_s: For an episode's camera, the episode time (seconds from the manifest's
            start) of the video's first frame: add it to a time here to find the recorded streams.
    """

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False, populate_by_name=True)

    schema_: Literal[1] = Field(default=1, alias="schema")
    video: str = Field(min_length=1, max_length=4096)
    duration_s: float = Field(ge=0.0, le=1e7)
    segments: tuple[Segment, ...] = Field(default=(), max_length=MAX_SEGMENTS)
    empty: bool = False
    episode_id: str | None = Field(default=None, min_length=1, max_length=64)
    video_offset_s: float | None = Field(default=None, ge=-1e6, le=1e6)

    @field_validator("duration_s")
    @classmethod
    def _rounded(cls, value: float) -> float:
        return _time(value)

    @model_validator(mode="after")
    def _consistent(self) -> SegmentsRecord:
        if self.empty and self.segments:
            raise ValueError(f"empty is true but it lists {len(self.segments)} segments")
        seen: set[str] = set()
        for i, seg in enumerate(self.segments):
            if seg.id in seen:
                raise ValueError(f"segments[{i}].id {seg.id} appears twice")
            seen.add(seg.id)
            if seg.end_s > self.duration_s + _SLACK_S:
                raise ValueError(
                    f"segments[{i}] ends at {seg.end_s} s, after the video's {self.duration_s} s"
                )
        return self

    def to_json(self) -> str:
        """The file's text (``schema`` spelled as in the file)."""
        return self.model_dump_json(by_alias=True, indent=2) + "\n"

    def active(self) -> tuple[Segment, ...]:
        """The segments nobody rejected."""
        return tuple(s for s in self.segments if s.status != "rejected")


def machine_source(segmenter: str, version: str) -> str:
    """``source`` of a segmenter's proposal: ``machine:<name>@<version>``."""
    return f"machine:{segmenter}@{version}"


def new_segment(
    label: str,
    start_s: float,
    end_s: float,
    *,
    confidence: float,
    source: str,
    actor: str | None = None,
    key: str | None = None,
) -> Segment:
    """A proposed segment, times rounded to 0.01 s and confidence clipped to 0..1.

    Args:
        key: What identifies the input (e.g. the item's source hash and video). Given, the id is a
            name-based UUID of the key and the segment (UUID5), so a re-run on the same input
            proposes the same ids (and the same clip names): stages stay idempotent and nothing
            downstream is redone. ``None``: a random UUID4 (a person drawing a new segment).

    Raises:
        ValueError: a time is not finite, negative, or the rounded end is not after the start.
    """
    conf = min(1.0, max(0.0, float(confidence))) if math.isfinite(confidence) else 0.0
    if key is None:
        ident = uuid.uuid4()
    else:
        name = f"{key}|{source}|{actor or ''}|{label}|{round(start_s, 2):.2f}|{round(end_s, 2):.2f}"
        ident = uuid.uuid5(_NAMESPACE, name)
    return Segment(
        id=str(ident),
        label=label,
        confidence=round(conf, 3),
        start_s=start_s,
        end_s=end_s,
        source=source,
        actor=actor,
    )


def _sorted(segments: Iterable[Segment]) -> tuple[Segment, ...]:
    return tuple(sorted(segments, key=lambda s: (s.start_s, s.end_s, s.id)))


def edit_segment(
    record: SegmentsRecord,
    segment_id: str,
    *,
    by: str,
    status: Literal["accepted", "corrected", "rejected"],
    label: str | None = None,
    start_s: float | None = None,
    end_s: float | None = None,
    now: dt.datetime | None = None,
) -> SegmentsRecord:
    """A person's review of one segment: the record with it accepted, corrected or rejected.

    The segment becomes ``human:<by>``'s (its machine ``source`` kept in ``origin``), ``confidence``
    1.0 unless rejected, ``edited_at`` now. Giving a new label or boundary makes it ``corrected``.

    Raises:
        KeyError: no segment has that id.
        ValueError: the edit is invalid (end not after start, ends after the video, bad label or user).
    """
    now = now or dt.datetime.now(dt.UTC)
    out: list[Segment] = []
    found = False
    for seg in record.segments:
        if seg.id != segment_id:
            out.append(seg)
            continue
        found = True
        changed = (label not in (None, seg.label)) or (start_s is not None) or (end_s is not None)
        final = "corrected" if changed and status == "accepted" else status
        origin = seg.origin if seg.source.startswith("human:") else seg.source
        data = seg.model_dump()
        data.update(
            label=seg.label if label is None else label,
            start_s=seg.start_s if start_s is None else start_s,
            end_s=seg.end_s if end_s is None else end_s,
            status=final,
            source=f"human:{by}",
            origin=origin,
            edited_at=now,
            confidence=seg.confidence if final == "rejected" else 1.0,
        )
        out.append(Segment.model_validate(data))
    if not found:
        raise KeyError(f"no segment {segment_id} in the segments of {record.video}")
    data = record.model_dump(by_alias=True)
    data["segments"] = [s.model_dump() for s in _sorted(out)]
    return SegmentsRecord.model_validate(data)


def _overlap(a: Segment, b: Segment) -> float:
    """Intersection over union of two segments' spans (0..1)."""
    inter = min(a.end_s, b.end_s) - max(a.start_s, b.start_s)
    if inter <= 0:
        return 0.0
    return inter / (max(a.end_s, b.end_s) - min(a.start_s, b.start_s))


def merge_machine(existing: SegmentsRecord | None, fresh: SegmentsRecord) -> SegmentsRecord:
    """``fresh`` (a segmenter's new proposals) merged into what is on disk without losing reviews.

    Segments a person touched (any status but ``proposed``, or a ``human:`` source) are kept as they
    are; the old machine proposals are replaced by the fresh ones, except a fresh one with a
    reviewed one's id or mostly covering it (intersection over union > 0.5): the review settled it.
    """
    if existing is None:
        return fresh
    reviewed = [s for s in existing.segments if s.status != "proposed" or s.source.startswith("human:")]
    if not reviewed:
        return fresh
    ids = {r.id for r in reviewed}
    kept = [s for s in fresh.segments if s.id not in ids and all(_overlap(s, r) <= 0.5 for r in reviewed)]
    segments = _sorted([*reviewed, *kept])[:MAX_SEGMENTS]
    return SegmentsRecord(
        video=fresh.video,
        duration_s=max(fresh.duration_s, existing.duration_s),
        segments=segments,
        empty=not segments,
        episode_id=fresh.episode_id,
        video_offset_s=fresh.video_offset_s,
    )


_FIX = "re-run `telerig process` on its input, or fix it by hand"


def parse_segments(raw: bytes | str, *, where: str = "segments file") -> SegmentsRecord:
    """Validate the text of a segments file.

    Raises:
        RecordingError: too large, not JSON, or not the schema (one line: field path and reason).
    """
    if len(raw) > _MAX_BYTES:
        raise RecordingError(f"{where} is larger than {_MAX_BYTES >> 20} MiB; it is not a segments file")
    try:
        return SegmentsRecord.model_validate_json(raw)
    except ValidationError as exc:
        first = exc.errors(include_url=False)[0]
        loc = ".".join(str(p) for p in first["loc"]) or "document"
        msg = str(first["msg"]).removeprefix("Value error, ")
        raise RecordingError(f"{where} is not a segments file ({loc}: {msg}); {_FIX}") from None


def read_segments(path: Path) -> SegmentsRecord:
    """Read and validate a ``segments.json`` anywhere (a stage's output directory).

    Raises:
        RecordingError: missing, unreadable, too large or invalid (one line naming the file).
    """
    path = Path(path)
    try:
        if path.stat().st_size > _MAX_BYTES:
            raise RecordingError(f"{path} is larger than {_MAX_BYTES >> 20} MiB; it is not a segments file")
        with open(path, "rb") as f:
            raw = f.read(_MAX_BYTES + 1)
    except OSError as exc:
        raise RecordingError(f"cannot read {path}: {exc.strerror or exc}") from None
    return parse_segments(raw, where=str(path))


def write_segments(path: Path, record: SegmentsRecord) -> Path:
    """Write ``record`` to ``path`` atomically (temp file, fsync, rename).

    Raises:
        RecordingError: it cannot be written.
    """
    path = Path(path)
    return write_sidecar(path.parent, path.name, record.to_json())


def read_episode_segments(episode_dir: Path) -> SegmentsRecord | None:
    """The ``segments.json`` beside an episode's files; ``None`` when it has none.

    Raises:
        RecordingError: unreadable, too large, invalid, or another episode's (one line).
    """
    return read_sidecar(
        episode_dir,
        SEGMENTS_FILE,
        SegmentsRecord,
        what="a segments file",
        max_bytes=_MAX_BYTES,
        redo=f"re-run `telerig process` on the episode (or delete {SEGMENTS_FILE})",
    )


def write_episode_segments(episode_dir: Path, record: SegmentsRecord) -> Path:
    """Write ``segments.json`` beside an episode's files, atomically, wherever a move put the directory.

    Raises:
        ValueError: ``record.episode_id`` is not this episode's.
        RecordingError: it cannot be written.
    """
    if record.episode_id != Path(episode_dir).name:
        raise ValueError(f"segments of {record.episode_id} written into {episode_dir}")
    return write_sidecar(episode_dir, SEGMENTS_FILE, record.to_json())
