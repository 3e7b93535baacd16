"""What an exporter is: the :class:`Exporter` protocol, its reports, and the atomic file write.

An exporter writes :class:`~telerig.export.frames.EpisodeFrames` in its format;
:func:`telerig.export.run.export` does the rest, identically for every format.

Crash safety is each exporter's job and follows one rule: new data files are written under new
names, and the files that make them part of the dataset (metadata, indices) are replaced last by an
atomic rename, so an export killed at any point leaves the previous dataset readable.
"""

from __future__ import annotations

import logging
import os
import tempfile
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar, Protocol

from telerig.errors import ExportError
from telerig.export.frames import EpisodeFrames
from telerig.export.schema import DatasetSchema

__all__ = ["ExportSummary", "Exporter", "ValidationReport", "write_atomic"]

_log = logging.getLogger("telerig.export")


@dataclass(frozen=True, slots=True)
class ExportSummary:
    """What one export run did.

    Attributes:
        format: Exporter name.
        out: Dataset directory.
        added: Telerig episode ids written by this run, in order.
        skipped: Episode ids the dataset already held (not rewritten).
        frames: Frames written by this run.
        episodes_total: Episodes in the dataset after the run.
        seconds: Wall time of the run [s].
    """

    format: str
    out: Path
    added: tuple[str, ...]
    skipped: tuple[str, ...]
    frames: int
    episodes_total: int
    seconds: float = 0.0


@dataclass(frozen=True, slots=True)
class ValidationReport:
    """The result of re-reading a dataset.

    Attributes:
        episodes: Episodes found.
        frames: Frames found.
        problems: One line per problem; empty when the dataset is valid.
    """

    episodes: int
    frames: int
    problems: tuple[str, ...] = ()

    @property
    def ok(self) -> bool:
        return not self.problems

    def raise_if_invalid(self, out: Path) -> None:
        """Raise :class:`ExportError` with the first problem (and how many more)."""
        if self.problems:
            more = f" (and {len(self.problems) - 1} more)" if len(self.problems) > 1 else ""
            raise ExportError(f"{out}: {self.problems[0]}{more}")


class Exporter(Protocol):
    """One dataset format. Built from its config in the ``EXPORTERS`` registry."""

    format: ClassVar[str]

    def schema_path(self, out: Path) -> Path:
        """Where the dataset keeps its :class:`DatasetSchema` JSON."""
        ...

    def existing_episodes(self, out: Path) -> set[str]:
        """Telerig episode ids the dataset at ``out`` holds (empty when there is none)."""
        ...

    def write(
        self,
        out: Path,
        schema: DatasetSchema,
        episodes: Iterable[EpisodeFrames],
        progress: Callable[[EpisodeFrames], None],
    ) -> int:
        """Write (or append) the episodes; call ``progress`` after each; return the frames written.

        The schema JSON goes to :meth:`schema_path`. The previous dataset stays readable if the
        process dies at any point.
        """
        ...

    def validate(self, out: Path) -> ValidationReport:
        """Re-read the dataset: action dimension, image shapes and channel order, episode
        lengths, monotonic timestamps, statistics present."""
        ...


def write_atomic(path: Path, data: bytes | str) -> None:
    """Write a file so a reader sees the old content or the new, never a torn one (temp + rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = data.encode() if isinstance(data, str) else data
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.fchmod(fd, 0o666 & ~_umask())  # mkstemp makes 0600; a dataset is read by the whole lab
        with os.fdopen(fd, "wb") as f:
            f.write(payload)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    _fsync_dir(path.parent)


def _umask() -> int:
    """The process umask, read without setting it (os.umask would race other threads' file creation)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    return 0o022


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
