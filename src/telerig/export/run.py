"""The one export run every format shares: select, refuse mixed rigs, resample, write, validate.

It picks the episodes (filters, failures partition), refuses to mix rigs or export settings in one
dataset, skips episodes the dataset already holds (re-running an export appends), reports progress,
and has the exporter re-read what it wrote before it reports success.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from telerig.errors import ExportError
from telerig.export.base import Exporter, ExportSummary
from telerig.export.config import (
    Hdf5ExportConfig,
    LeRobotExportConfig,
    RldsExportConfig,
    RobomimicExportConfig,
)
from telerig.export.frames import EpisodeFrames, load_episode
from telerig.export.schema import DatasetSchema
from telerig.record.align import Policy
from telerig.registry import EXPORTERS
from telerig.store.episodes import EpisodeStore, EpisodeSummary

__all__ = [
    "DEFAULT_KEEP_IDLE_TAIL_S",
    "EpisodeFilter",
    "build_exporter",
    "export",
    "keep_idle_tail",
    "select_episodes",
]

#: Seconds of an episode's idle tail ``telerig export --trim-idle`` keeps (:func:`keep_idle_tail`).
#: A policy trained on demonstrations cut where the operator stopped never saw the robot stand still
#: after the task: on the pick-and-place task (2026-11-27, 50 demonstrations, 50 held-out seeds)
#: rollouts placed the cube, opened the gripper and kept moving, failing the scene's "arm still"
#: check; with the first second kept the same demonstrations gave 50/50 instead of 40/50.
DEFAULT_KEEP_IDLE_TAIL_S = 1.0


def keep_idle_tail(
    spans: Sequence[tuple[float, float]], duration_s: float | None, keep_s: float
) -> tuple[tuple[float, float], ...]:
    """``spans`` with the first ``keep_s`` seconds of the idle tail (the span that ends where the
    episode of ``duration_s`` ends) left out of the cut; a tail shorter than that is not cut at all.
    Other spans (the idle head, pauses) are unchanged."""
    out: list[tuple[float, float]] = []
    for start, end in spans:
        is_tail = duration_s is not None and end >= duration_s - 1e-3
        cut_from = start + keep_s if is_tail else start
        if cut_from < end:
            out.append((cut_from, end))
    return tuple(out)


@dataclass(frozen=True, slots=True)
class EpisodeFilter:
    """Which committed episodes to export (every given field must match).

    Attributes:
        ids: Only these episode ids.
        task: Exact task.
        operator: Exact operator id.
        include_failures: Also episodes a quality gate moved to the failures partition.
    """

    ids: tuple[str, ...] = ()
    task: str | None = None
    operator: str | None = None
    include_failures: bool = False

    def matches(self, episode: EpisodeSummary) -> bool:
        return (
            (not self.ids or episode.id in self.ids)
            and (self.task is None or episode.task == self.task)
            and (self.operator is None or episode.operator == self.operator)
        )


def build_exporter(fmt: str, options: Mapping[str, Any] | None = None) -> Exporter:
    """The exporter registered as ``fmt``, built from its config.

    Raises:
        ExportError: Unknown format (the message lists the registered ones) or bad options.
    """
    try:
        config = EXPORTERS.parse_config({"type": fmt, **(options or {})}, "export")
    except ValueError as exc:
        raise ExportError(str(exc)) from None
    builder = _BUILTIN.get(type(config))
    exporter: Exporter = builder(config) if builder is not None else config.build()
    return exporter


def _lerobot(config: LeRobotExportConfig) -> Exporter:
    from telerig.export.lerobot import LeRobotExporter

    return LeRobotExporter(config)


def _hdf5(config: Hdf5ExportConfig) -> Exporter:
    from telerig.export.hdf5 import Hdf5Exporter

    return Hdf5Exporter(config)


def _robomimic(config: RobomimicExportConfig) -> Exporter:
    from telerig.export.robomimic import RobomimicExporter

    return RobomimicExporter(config)


def _rlds(config: RldsExportConfig) -> Exporter:
    from telerig.export.rlds import RldsExporter

    return RldsExporter(config)


#: Built-in config type → its exporter (writers load only when built; plug-ins have ``build()``).
_BUILTIN: dict[type, Callable[[Any], Exporter]] = {
    LeRobotExportConfig: _lerobot,
    Hdf5ExportConfig: _hdf5,
    RobomimicExportConfig: _robomimic,
    RldsExportConfig: _rlds,
}


def select_episodes(store: EpisodeStore, selection: EpisodeFilter) -> list[EpisodeSummary]:
    """Committed episodes matching ``selection``, oldest first.

    Raises:
        ExportError: An id in ``selection.ids`` is not a committed episode.
    """
    found = [e for e in store.list(include_failures=selection.include_failures) if selection.matches(e)]
    missing = sorted(set(selection.ids) - {e.id for e in found})
    if missing:
        raise ExportError(
            f"episode {missing[0]} is not a committed episode in {store.root}"
            + ("" if selection.include_failures else " (pass --include-failures for rejected ones)")
        )
    return found


def export(
    store_root: Path,
    fmt: str,
    out: Path,
    *,
    selection: EpisodeFilter | None = None,
    fps: int | None = None,
    normalize: bool = False,
    policies: Mapping[str, Policy] | None = None,
    trim: Callable[[Path], Sequence[tuple[float, float]]] | None = None,
    options: Mapping[str, Any] | None = None,
    progress: Callable[[int, int, str], None] | None = None,
) -> ExportSummary:
    """Export committed episodes of a data root into a dataset, appending to an existing one.

    Args:
        store_root: The data root (``telerig-data``).
        fmt: Exporter name (``lerobot``, ``hdf5``, ``robomimic``, ``rlds``).
        out: Dataset directory (created, or appended to).
        selection: Which episodes; every committed episode outside the failures partition when
            ``None``.
        fps: Dataset rate [Hz]; the anchor camera's rate when ``None``.
        normalize: Map state and action to [-1, 1] from the robot's limits.
        policies: Stream name → resampling policy over the defaults.
        trim: Episode directory → idle spans to cut ([start, end) s from its start); nothing cut
            when ``None``. The quality gates' idle spans through :func:`keep_idle_tail` are what
            ``telerig export --trim-idle`` cuts.
        options: Format options (the exporter's config fields).
        progress: Called with (episodes done, episodes to write, episode id) after each episode.

    Raises:
        ExportError: One line: nothing to export, mixed rigs, a dataset of other settings at
            ``out``, an unreadable episode, or a dataset that does not validate after writing.
    """
    started = time.perf_counter()
    exporter = build_exporter(fmt, options)
    store = EpisodeStore(store_root)
    chosen = select_episodes(store, selection or EpisodeFilter())
    if not chosen:
        raise ExportError(f"no committed episode in {store.root} matches; record some or relax the filters")
    out = Path(out)
    existing = exporter.existing_episodes(out)
    todo = [e for e in chosen if e.id not in existing]
    skipped = tuple(e.id for e in chosen if e.id in existing)
    if not todo:
        report = exporter.validate(out)
        report.raise_if_invalid(out)
        return ExportSummary(fmt, out, (), skipped, 0, report.episodes, time.perf_counter() - started)

    def load(summary: EpisodeSummary, rate: int | None) -> EpisodeFrames:
        cut = trim(summary.path) if trim is not None else ()
        return load_episode(summary.path, fps=rate, normalized=normalize, policies=policies, trim_s=cut)

    # The first episode is loaded once: its schema is the dataset's (decoding a log twice was 40 %
    # of a copied LeRobot export's time, benchmarks/export.py).
    first = load(todo[0], fps)
    dataset = _existing_schema(exporter, out)
    if dataset is not None and fps is None and dataset.fps != first.schema.fps:
        first = load(todo[0], dataset.fps)  # appending keeps the dataset's rate
    schema = first.schema
    if dataset is not None:
        dataset.check_compatible(schema)
    added: list[str] = []

    def frames() -> Iterator[EpisodeFrames]:
        yield first
        for summary in todo[1:]:
            yield load(summary, schema.fps)

    def done(episode: EpisodeFrames) -> None:
        added.append(episode.episode_id)
        if progress is not None:
            progress(len(added), len(todo), episode.episode_id)

    out.mkdir(parents=True, exist_ok=True)
    written = exporter.write(out, schema, _same_schema(frames(), schema), done)
    report = exporter.validate(out)
    report.raise_if_invalid(out)
    return ExportSummary(
        fmt, out, tuple(added), skipped, written, report.episodes, time.perf_counter() - started
    )


def _existing_schema(exporter: Exporter, out: Path) -> DatasetSchema | None:
    """The schema of the dataset already at ``out``; ``None`` when there is none."""
    path = exporter.schema_path(out)
    return DatasetSchema.loads(path.read_bytes()) if path.is_file() else None


def _same_schema(episodes: Iterable[EpisodeFrames], schema: DatasetSchema) -> Iterator[EpisodeFrames]:
    """Refuse, before writing it, an episode whose schema differs from the dataset's."""
    for episode in episodes:
        try:
            schema.check_compatible(episode.schema)
        except ExportError as exc:
            raise ExportError(f"episode {episode.episode_id}: {exc}") from None
        yield episode
