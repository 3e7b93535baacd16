"""Check committed episodes: run the gates and the score, keep the verdicts, move rejected episodes.

One function, :func:`check_episode`, used by ``telerig qa`` and by the station's background worker
(:mod:`telerig.runtime.qa_worker`) after each commit:

1. the gates (:func:`telerig.qa.gates.evaluate`) and the score (:func:`telerig.qa.score.score`)
   run on the episode's directory, from one read of its log;
2. ``qa.json`` is written beside its files, atomically (:mod:`telerig.store.qa_file`): a committed
   manifest never changes;
3. a rejected episode moves to the failures partition with its reasons, a passing one in failures
   (a threshold was relaxed) moves back (:meth:`~telerig.store.episodes.EpisodeStore.move_to_failures`);
4. the index gets every verdict, the score and the status (``failed_qa`` or the manifest's).

A kill between the steps is safe: the moves are atomic, and an episode whose ``qa.json`` disagrees
with its partition (or has none, or an unreadable one) is what :func:`unchecked` returns, so the
next ``telerig qa`` finishes the job.
"""

from __future__ import annotations

import hashlib
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from telerig.config.qa import QaThresholds
from telerig.errors import RecordingError
from telerig.qa.episode import load_episode
from telerig.qa.gates import evaluate_loaded
from telerig.qa.report import QaReport
from telerig.qa.score import score, task_medians
from telerig.store.episodes import EpisodeStore, EpisodeSummary
from telerig.store.index import EpisodeIndex, IndexStatus
from telerig.store.qa_file import QaRecord, read_qa, write_qa

__all__ = ["QaOutcome", "check_episode", "task_median", "thresholds_hash", "unchecked"]

_log = logging.getLogger("telerig.qa.checker")


@dataclass(frozen=True, slots=True)
class QaOutcome:
    """What checking one episode did.

    Attributes:
        episode_id: The episode.
        report: The gates' verdicts.
        score: Its quality score in [0, 1]; ``None`` when the score could not be computed.
        partition: Where it lies now: ``episodes`` (passed) or ``failures`` (rejected).
        moved: Whether this check moved it (to ``partition``).
        path: Its directory now.
    """

    episode_id: str
    report: QaReport
    score: float | None
    partition: Literal["episodes", "failures"]
    moved: bool
    path: Path

    @property
    def passed(self) -> bool:
        """No gate failed."""
        return self.report.passed


def thresholds_hash(thresholds: QaThresholds) -> str:
    """16 hex chars identifying ``thresholds`` (the rig's ``qa:`` section, defaults included)."""
    text = thresholds.model_dump_json(exclude={"after_commit"})  # when gates run is no threshold
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def task_median(index: EpisodeIndex | None, task: str) -> float | None:
    """Median duration [s] of the task's complete episodes in the index; ``None`` without an index or
    with none (the score then leaves completion time out)."""
    if index is None:
        return None
    return task_medians(index.list_episodes(task=task, status="complete")).get(task)


def check_episode(
    store: EpisodeStore,
    episode_id: str,
    thresholds: QaThresholds,
    *,
    index: EpisodeIndex | None = None,
    task_median_s: float | None = None,
) -> QaOutcome:
    """Run the gates and the score on a committed episode and act on the verdict (see the module doc).

    Args:
        store: The episode store.
        episode_id: Full id or unique prefix of an episode in ``episodes`` or ``failures``.
        thresholds: The gates' thresholds (the rig's ``qa:``).
        index: Where verdicts, score and status go; ``None`` leaves the index alone (``qa.json`` and
            the partition still say everything, and ``EpisodeIndex.rebuild`` reads them).
        task_median_s: The task's median duration [s] for the score; from ``index`` when ``None``.

    Raises:
        RecordingError: no such committed episode, or it cannot be read or moved (one line).
    """
    found = store.find(episode_id)
    if found.partition not in ("episodes", "failures"):  # pragma: no cover - find() sees only those
        raise RecordingError(f"episode {found.id} is {found.status}; gates run on committed episodes")
    episode = load_episode(found.path)
    report = evaluate_loaded(episode, thresholds)
    median = task_median_s if task_median_s is not None else task_median(index, found.task)
    try:
        # From the gates' read of the log: a second read was most of the score's time (on a fleet
        # episode 1.6 s of CPU, more than the gates' own 1.0 s).
        quality = score(
            found.path,
            report,
            task_median_s=median,
            weights=thresholds.score_weights,
            streams=episode.streams,
            residual_errors=episode.residual_errors,
        )
        score_json = quality.to_json()
        total: float | None = quality.total
    except RecordingError as exc:  # the verdicts stand without a score
        _log.warning("episode %s: no quality score: %s", found.id, exc)
        score_json, total = None, None
    record = QaRecord(
        episode_id=found.id,
        checked_ns=time.time_ns(),
        thresholds_hash=thresholds_hash(thresholds),
        report=report.to_json(),
        score=score_json,
    )
    write_qa(found.path, record)
    path, partition = _act(store, found, report)
    if index is not None:
        _index(index, store, found, record, partition, path)
    return QaOutcome(found.id, report, total, partition, partition != found.partition, path)


def _act(
    store: EpisodeStore, found: EpisodeSummary, report: QaReport
) -> tuple[Path, Literal["episodes", "failures"]]:
    if not report.passed:
        return store.move_to_failures(found.id, report.reasons), "failures"
    if found.partition == "failures":
        return store.restore_from_failures(found.id), "episodes"
    return found.path, "episodes"


def _index(
    index: EpisodeIndex,
    store: EpisodeStore,
    found: EpisodeSummary,
    record: QaRecord,
    partition: str,
    path: Path,
) -> None:
    manifest = store.get(found.id)
    status: IndexStatus
    reason: str | None
    if partition == "failures":
        status, reason = "failed_qa", "; ".join(record.reasons)
    else:
        status = "repaired" if manifest.status == "repaired" else "complete"
        reason = manifest.reason
    try:
        index.record_qa(record, status=status, reason=reason, location=path)
    except RecordingError:  # not indexed yet (e.g. recorded without an index): add it, then again
        index.upsert_episode(manifest, location=path, status=status)
        index.record_qa(record, status=status, reason=reason, location=path)


def unchecked(store: EpisodeStore) -> list[EpisodeSummary]:
    """Committed episodes whose gates have not run, or whose check did not finish: no ``qa.json``,
    an unreadable one, or one whose verdict disagrees with the partition the episode lies in."""
    out: list[EpisodeSummary] = []
    for summary in store.list(include_failures=True):
        try:
            record = read_qa(summary.path)
        except RecordingError as exc:
            _log.warning("%s; checking it again", exc)
            out.append(summary)
            continue
        if record is None or record.passed != (summary.partition == "episodes"):
            out.append(summary)
    return out
