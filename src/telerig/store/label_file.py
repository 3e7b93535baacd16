"""The ``label.json`` beside an episode's files: a person's success/failure label, set after recording.

A committed manifest is immutable (its files are hashed), and its ``extra.outcome`` holds only the
mark given while recording (``telerig session mark``). A label set later (the control center's
episode page) lives beside the manifest, like ``qa.json``: it moves with the episode between
``episodes`` and ``failures``, wins over the manifest's mark wherever an outcome is read
(:func:`episode_outcome`: the index, the exports, the quality score), and records who set it.
"""

from __future__ import annotations

import contextlib
import os
import time
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from telerig.errors import RecordingError
from telerig.store.episodes import EpisodeManifest
from telerig.store.manifest_extra import EpisodeExtra

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
    path = Path(episode_dir) / LABEL_FILE
    try:
        if not path.is_file():
            return None
        if path.stat().st_size > _MAX_BYTES:
            raise RecordingError(f"{path} is larger than {_MAX_BYTES >> 10} kB; it is not a label.json")
        record = LabelRecord.model_validate_json(path.read_bytes())
    except OSError as exc:
        raise RecordingError(f"cannot read {path}: {exc.strerror or exc}") from None
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"]) or "document"
        raise RecordingError(
            f"{path} is not a label ({where}: {first['msg']}); label the episode again"
        ) from None
    if record.episode_id != Path(episode_dir).name:
        raise RecordingError(f"{path} belongs to episode {record.episode_id!r}; label the episode again")
    return record


def write_label(episode_dir: Path, record: LabelRecord) -> Path:
    """Write ``label.json`` atomically (temp file, fsync, rename, fsync of the directory).

    Every step goes through a descriptor of the directory, so a concurrent move of the episode
    between ``episodes`` and ``failures`` (a rename of the directory) cannot lose the label: it lands
    in the directory wherever it is now. Returns the path it had when opened.

    Raises:
        RecordingError: it cannot be written (disk full, permissions, no such directory).
    """
    episode_dir = Path(episode_dir)
    if record.episode_id != episode_dir.name:
        raise ValueError(f"label of {record.episode_id} written into {episode_dir}")
    tmp = LABEL_FILE + ".tmp"
    try:
        dir_fd = os.open(episode_dir, os.O_RDONLY | os.O_DIRECTORY)
    except OSError as exc:
        raise RecordingError(f"cannot open {episode_dir}: {exc.strerror or exc}") from None
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644, dir_fd=dir_fd)
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(record.model_dump_json(indent=2))
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, LABEL_FILE, src_dir_fd=dir_fd, dst_dir_fd=dir_fd)
        os.fsync(dir_fd)
    except OSError as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp, dir_fd=dir_fd)
        raise RecordingError(f"cannot write {episode_dir / LABEL_FILE}: {exc.strerror or exc}") from None
    finally:
        os.close(dir_fd)
    return episode_dir / LABEL_FILE


def episode_outcome(episode_dir: Path, manifest: EpisodeManifest) -> Outcome | None:
    """The episode's outcome: its ``label.json`` when it has one, else the manifest's mark.

    Raises:
        RecordingError: ``label.json`` or the manifest's extra is unreadable (one line).
    """
    label = read_label(episode_dir)
    if label is not None:
        return label.outcome
    return EpisodeExtra.of(manifest).outcome
