"""Sidecar files beside an episode's files (``qa.json``, ``label.json``): read bounded and validated,
written atomically.

A committed manifest is immutable (its files are hashed), so what is learned about an episode later
lives in small JSON files in its directory, which move with it between ``episodes`` and
``failures``. Writes go through a descriptor of the directory, so a concurrent move of the episode
(a rename of the directory) cannot lose them: the file lands wherever the directory is now.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import TypeVar

from pydantic import BaseModel, ValidationError

from telerig.errors import RecordingError

__all__ = ["read_sidecar", "write_sidecar"]

M = TypeVar("M", bound=BaseModel)


def read_sidecar(
    episode_dir: Path, name: str, model: type[M], *, what: str, max_bytes: int, redo: str
) -> M | None:
    """The sidecar ``name`` of an episode parsed as ``model``; ``None`` when there is none.

    Args:
        episode_dir: The episode directory; the record's ``episode_id`` must be its name.
        name: File name (``qa.json``).
        model: The record's pydantic model (with an ``episode_id`` field).
        what: What the record is, for the message (``a quality record``).
        max_bytes: Larger files are refused before parsing.
        redo: What writes it again, for the message (``re-run telerig qa on it``).

    Raises:
        RecordingError: The file is unreadable, too large, not a valid record, or another
            episode's (one line naming the file and the fix).
    """
    path = Path(episode_dir) / name
    try:
        if not path.is_file():
            return None
        if path.stat().st_size > max_bytes:
            raise RecordingError(f"{path} is larger than {max_bytes >> 10} kB; it is not {what}: {redo}")
        record = model.model_validate_json(path.read_bytes())
    except OSError as exc:
        raise RecordingError(f"cannot read {path}: {exc.strerror or exc}") from None
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"]) or "document"
        raise RecordingError(f"{path} is not {what} ({where}: {first['msg']}); {redo}") from None
    owner = getattr(record, "episode_id", None)
    if owner != Path(episode_dir).name:
        raise RecordingError(f"{path} belongs to episode {owner!r}; {redo}")
    return record


def write_sidecar(episode_dir: Path, name: str, text: str) -> Path:
    """Write the sidecar ``name`` atomically: temp file, fsync, rename, fsync of the directory.

    Returns:
        Its path as the directory was named when opened.

    Raises:
        RecordingError: It cannot be written (disk full, permissions, no such directory).
    """
    episode_dir = Path(episode_dir)
    tmp = name + ".tmp"
    try:
        dir_fd = os.open(episode_dir, os.O_RDONLY | os.O_DIRECTORY)
    except OSError as exc:
        raise RecordingError(f"cannot open {episode_dir}: {exc.strerror or exc}") from None
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644, dir_fd=dir_fd)
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, name, src_dir_fd=dir_fd, dst_dir_fd=dir_fd)
        os.fsync(dir_fd)
    except OSError as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp, dir_fd=dir_fd)
        raise RecordingError(f"cannot write {episode_dir / name}: {exc.strerror or exc}") from None
    finally:
        os.close(dir_fd)
    return episode_dir / name
