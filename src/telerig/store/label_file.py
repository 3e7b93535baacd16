"""The ``label.json`` beside an episode's files: a person's success/failure label, set after recording.

A committed manifest is immutable (its files are hashed), and its ``extra.outcome`` holds only the
mark given while recording (``telerig session mark``). A label set later (the control center's
episode page) lives beside the manifest, like ``qa.json``: it moves with the episode between
``episodes`` and ``failures``, wins over the manifest's mark wherever an outcome is read
(:func:`episode_outcome`: the index, the exports, the quality score), and records who set it.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from telerig.store.episodes import EpisodeManifest
from telerig.store.manifest_extra import EpisodeExtra
from telerig.store.sidecar import read_sidecar, write_sidecar

__all__ = ["LABEL_FILE", "LabelRecord", "Outcome", "episode_outcome", "read_label", "write_label"]

#: File name, in the episode directory.
LABEL_FILE = "label.json"
#: Larger is not a label.json; refuse before parsing it.
_MAX_BYTES = 64 << 10

Outcome = Literal["success", "failure"]


class LabelRecord(BaseModel):
    """The content of ``label.json``.

    Attributes:
        episode_id: The episode.
        outcome: ``success`` or ``failure``.
        by: Who set it (a control-center user name, or ``cli``).
        labelled_ns: When, wall clock [ns].
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    format: Literal[1] = 1
    episode_id: str = Field(max_length=64)
    outcome: Outcome
    by: str = Field(default="", max_length=64)
    labelled_ns: int = Field(default_factory=time.time_ns)


def read_label(episode_dir: Path) -> LabelRecord | None:
    """The episode's ``label.json``; ``None`` when it has none.

    Raises:
        RecordingError: the file is unreadable, too large, or not a label of this episode (one line).
    """
    redo = "label the episode again"
    return read_sidecar(episode_dir, LABEL_FILE, LabelRecord, what="a label", max_bytes=_MAX_BYTES, redo=redo)


def write_label(episode_dir: Path, record: LabelRecord) -> Path:
    """Write ``label.json`` atomically, into the directory wherever a concurrent move put it.

    Raises:
        RecordingError: it cannot be written (disk full, permissions, no such directory).
    """
    if record.episode_id != Path(episode_dir).name:
        raise ValueError(f"label of {record.episode_id} written into {episode_dir}")
    return write_sidecar(episode_dir, LABEL_FILE, record.model_dump_json(indent=2))


def episode_outcome(episode_dir: Path, manifest: EpisodeManifest) -> Outcome | None:
    """The episode's outcome: its ``label.json`` when it has one, else the manifest's mark.

    Raises:
        RecordingError: ``label.json`` or the manifest's extra is unreadable (one line).
    """
    label = read_label(episode_dir)
    if label is not None:
        return label.outcome
    return EpisodeExtra.of(manifest).outcome
