"""``segment_annotations.json`` beside an episode's files: the language of its segments.

The annotation pipeline's stage 4 describes each clip (one clip per segment, named by the
segment's id) with a vision-language model, or offline from the episode's metadata. Its full answer
lives in the processed root (``items/<id>/annotate/annotations.json``); the part the exports need
(a sentence per segment, the scene, which model said it) is copied here so that
:mod:`telerig.export` reads it without importing the pipeline (the two are sibling layers).

Keys are segment ids of the episode's ``segments.json``; an id no longer there (the segment was
re-drawn) is ignored by the readers.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from telerig.store.sidecar import read_sidecar, write_sidecar

__all__ = [
    "ANNOTATIONS_FILE",
    "EpisodeAnnotations",
    "SegmentAnnotation",
    "read_episode_annotations",
    "write_episode_annotations",
]

#: File name, in the episode directory (not ``annotations.json``: that is the stage's own file).
ANNOTATIONS_FILE = "segment_annotations.json"
#: Larger is not this file (a few hundred bytes per segment, at most 10 000 segments).
_MAX_BYTES = 16 << 20
_REDO = f"re-run `telerig process` on the episode (or delete {ANNOTATIONS_FILE})"


class SegmentAnnotation(BaseModel):
    """The language of one segment.

    Attributes:
        description: What happens, one sentence (the model's action description), 1-1000 chars.
        scene: Scene type (``kitchen``, ``assembly_station``...), ``None`` when unknown.
        model: The model that wrote it; ``None`` for the offline annotator.
        offline: Filled from metadata without a model.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    description: str = Field(min_length=1, max_length=1000, pattern=r"^[^\x00]*$")
    scene: str | None = Field(default=None, max_length=64)
    model: str | None = Field(default=None, max_length=200)
    offline: bool = False


class EpisodeAnnotations(BaseModel):
    """The content of ``segment_annotations.json``."""

    model_config = ConfigDict(frozen=True, extra="forbid", populate_by_name=True)

    schema_: Literal[1] = Field(default=1, alias="schema")
    episode_id: str = Field(min_length=1, max_length=64)
    segments: Mapping[str, SegmentAnnotation] = Field(default_factory=dict, max_length=10_000)


def read_episode_annotations(episode_dir: Path) -> EpisodeAnnotations | None:
    """The episode's ``segment_annotations.json``; ``None`` when it has none.

    Raises:
        RecordingError: unreadable, too large, invalid, or another episode's (one line).
    """
    return read_sidecar(
        episode_dir,
        ANNOTATIONS_FILE,
        EpisodeAnnotations,
        what="a segment annotations file",
        max_bytes=_MAX_BYTES,
        redo=_REDO,
    )


def write_episode_annotations(episode_dir: Path, record: EpisodeAnnotations) -> Path:
    """Write ``segment_annotations.json`` beside an episode's files, atomically.

    Raises:
        ValueError: ``record.episode_id`` is not this episode's.
        RecordingError: it cannot be written.
    """
    if record.episode_id != Path(episode_dir).name:
        raise ValueError(f"annotations of {record.episode_id} written into {episode_dir}")
    text = record.model_dump_json(by_alias=True, indent=2) + "\n"
    return write_sidecar(episode_dir, ANNOTATIONS_FILE, text)
