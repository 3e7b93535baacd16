"""The ``qa.json`` beside an episode's files: its quality gates' verdicts and score, written atomically.

A committed manifest is immutable (its files are hashed), so the verdicts of the quality gates
(:mod:`telerig.qa`), which change when a rig's thresholds do, live beside it: in this file, which
moves with the episode between ``episodes`` and ``failures``, and in the index (rebuilt from it).
The report and score are stored as :mod:`telerig.qa` writes them; this module reads the parts the
store needs (verdicts, pass/fail, total score) without importing the layer above.
"""

from __future__ import annotations

import math
from pathlib import Path

from pydantic import BaseModel, ConfigDict, JsonValue, model_validator

from telerig.store.sidecar import read_sidecar, write_sidecar

__all__ = ["QA_FILE", "QA_FORMAT", "GateRow", "QaRecord", "read_qa", "write_qa"]

#: File name, in the episode directory.
QA_FILE = "qa.json"
#: Version of the ``qa.json`` layout.
QA_FORMAT = 1
#: Larger is not a qa.json (a few kB per episode); refuse before parsing it.
_MAX_BYTES = 16 << 20


class GateRow(BaseModel):
    """One gate's verdict as the index stores it (see :class:`telerig.qa.report.GateVerdict`).

    Attributes:
        gate: Gate name, e.g. ``joint_limits``.
        passed: True passed, False failed, ``None`` not applicable.
        value: Measured value in ``unit``; ``None`` when nothing was measured (or not finite).
        threshold: The threshold it was held to, in ``unit``.
        unit: Unit of value and threshold (``s``, ``rad``, ``N``, ``ms``, ``fraction``...).
        detail: One line a person understands.
    """

    model_config = ConfigDict(frozen=True, extra="ignore")

    gate: str
    passed: bool | None
    value: float | None = None
    threshold: float | None = None
    unit: str = ""
    detail: str = ""


class QaRecord(BaseModel):
    """The content of ``qa.json``.

    Attributes:
        episode_id: The episode.
        checked_ns: When the gates ran, wall clock [ns].
        thresholds_hash: Digest of the thresholds they ran with (the rig's ``qa:`` section), so a
            recheck can tell which verdicts a threshold change may flip.
        report: The quality report, :meth:`telerig.qa.report.QaReport.to_json` (verdicts with their
            events, idle fraction and segments).
        score: The quality score, :meth:`telerig.qa.score.QualityScore.to_json`; ``None`` when it
            was not computed.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    format: int = QA_FORMAT
    episode_id: str
    checked_ns: int
    thresholds_hash: str
    report: dict[str, JsonValue]
    score: dict[str, JsonValue] | None = None

    @model_validator(mode="after")
    def _readable(self) -> QaRecord:
        if self.format != QA_FORMAT:
            raise ValueError(f"format {self.format} is not {QA_FORMAT}")
        self.verdicts  # noqa: B018 - parsed here so a malformed report fails on read, not later
        total = self.score_total
        if total is not None and not 0.0 <= total <= 1.0:
            raise ValueError(f"score total {total} is not in [0, 1]")
        return self

    @property
    def verdicts(self) -> tuple[GateRow, ...]:
        """The gates' verdicts, in the order they ran."""
        rows = self.report.get("verdicts")
        if not isinstance(rows, list):
            raise ValueError("report.verdicts is not a list")
        return tuple(GateRow.model_validate(row) for row in rows)

    @property
    def passed(self) -> bool:
        """No gate failed (a not-applicable gate does not fail an episode)."""
        return all(v.passed is not False for v in self.verdicts)

    @property
    def reasons(self) -> tuple[str, ...]:
        """One ``"<gate>: <detail>"`` line per failed gate; empty when it passed."""
        return tuple(f"{v.gate}: {v.detail}" for v in self.verdicts if v.passed is False)

    @property
    def score_total(self) -> float | None:
        """The total quality score in [0, 1]; ``None`` when not scored."""
        if self.score is None:
            return None
        total = self.score.get("total")
        if isinstance(total, bool) or not isinstance(total, int | float) or not math.isfinite(total):
            raise ValueError(f"score.total {total!r} is not a number")
        return float(total)


def read_qa(episode_dir: Path) -> QaRecord | None:
    """The episode's ``qa.json``; ``None`` when it has none (its gates have not run).

    Raises:
        RecordingError: the file is unreadable, too large, or not a qa record of this episode
            (one line naming the file and the first problem; re-run ``telerig qa --recheck``).
    """
    redo = "re-run telerig qa on it"
    return read_sidecar(
        episode_dir, QA_FILE, QaRecord, what="a quality record", max_bytes=_MAX_BYTES, redo=redo
    )


def write_qa(episode_dir: Path, record: QaRecord) -> Path:
    """Write ``qa.json`` atomically, into the directory wherever a concurrent move put it.

    Raises:
        RecordingError: it cannot be written (disk full, permissions).
    """
    return write_sidecar(episode_dir, QA_FILE, record.model_dump_json(indent=2))
