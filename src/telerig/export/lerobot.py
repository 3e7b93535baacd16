"""LeRobot dataset format v3.0, written with pyarrow and PyAV (``lerobot`` itself is not needed).

Layout (paths relative to the dataset root, as ``lerobot.datasets`` 0.4 reads them)::

    meta/info.json                                  codebase_version "v3.0", fps, features, totals
    meta/stats.json                                 per feature: min max mean std count q01..q99
    meta/tasks.parquet                              task string (pandas index) -> task_index
    meta/subtasks.parquet                           subtask label (pandas index) -> subtask_index,
                                                    only in datasets with segments (see below)
    meta/episodes/chunk-XXX/file-XXX.parquet        one row per episode: where its rows and video
                                                    frames are, its tasks, its stats, telerig/*
    meta/robot_schema.json                          telerig's joint order and limits (DatasetSchema)
    data/chunk-XXX/file-XXX.parquet                 one row per frame, several episodes per file
    videos/<key>/chunk-XXX/file-XXX.mp4             several episodes per file, back to back

Frame columns: ``observation.state`` and ``action`` (names: the schema's joint names),
``telerig.alignment_error_ms`` (per source, the distance [ms] from the frame's grid time to the
sample used; :data:`NO_SAMPLE` where a stream had none, not NaN: LeRobot's dataset aggregation
turns NaN into nulls that its loader cannot make tensors of; outside the ``observation.`` and
``action`` namespaces so no LeRobot policy takes it as an input), ``timestamp`` (``k / fps``,
float32), ``frame_index``, ``episode_index``, ``index``, ``task_index``. Each camera is a video feature
``observation.images.<camera>`` (see :mod:`telerig.export._lerobot_video`). The episodes table adds
``telerig/episode_id``, ``telerig/quality``, ``telerig/outcome``, ``telerig/gates`` (JSON),
``telerig/valid_fraction`` and ``telerig/trimmed_s`` (JSON) to LeRobot's columns.

Segments (issue 15): a dataset created from an episode with a ``segments.json`` sidecar adds, as
LeRobot 0.4's subtask support reads them (``item["subtask"]`` looked up through
``meta/subtasks.parquet``), a ``subtask_index`` frame column (the active segment's label; the
subtask ``""`` where none is active) and a ``language_instruction`` string column (the segment's
description, else ``label: task``; the task where none is active, see
:mod:`telerig.export.language`). ``task_index`` stays the episode's task. A dataset created without
segments is written byte for byte as before; an episode with segments appended to it keeps its
frames but loses its labels, with a warning (export into a new ``--out`` to keep them).

Appending: a run writes its frames, videos and episode rows to new files only (the next
``(chunk, file)`` after the dataset's last, as LeRobot does when it resumes a recording), all
under ``.tmp-<pid>`` first; it then moves them into place and replaces ``tasks.parquet``,
``stats.json`` (old and new stats aggregated as LeRobot aggregates datasets) and last
``info.json``, each by an atomic rename. ``info.json``'s ``total_episodes`` is the commit point:
files past it are left over from an interrupted run and the next run deletes them.
"""

from __future__ import annotations

import fcntl
import json
import logging
import math
import os
import shutil
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import av
import numpy as np
import numpy.typing as npt
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from telerig.errors import ExportError
from telerig.export._lerobot_stats import (
    STAT_KEYS,
    ImageStats,
    Stats,
    aggregate,
    stats_to_json,
    vector_stats,
)
from telerig.export._lerobot_video import VIDEO_PATH, VideoFileWriter, VideoSpan, remuxable
from telerig.export.base import ValidationReport, write_atomic
from telerig.export.config import LeRobotExportConfig
from telerig.export.frames import EpisodeFrames
from telerig.export.schema import SCHEMA_FILE, DatasetSchema

__all__ = ["CODEBASE_VERSION", "LeRobotExporter", "Timings"]

_log = logging.getLogger("telerig.export.lerobot")

#: The LeRobot dataset format this module writes.
CODEBASE_VERSION = "v3.0"
#: LeRobot's files per chunk directory (file sizes: :class:`LeRobotExportConfig`, LeRobot's defaults).
CHUNKS_SIZE = 1000

DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
EPISODES_PATH = "meta/episodes/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
INFO_PATH = "meta/info.json"
STATS_PATH = "meta/stats.json"
TASKS_PATH = "meta/tasks.parquet"
SUBTASKS_PATH = "meta/subtasks.parquet"
SUBTASK = "subtask_index"
LANGUAGE = "language_instruction"
SCHEMA_PATH = f"meta/{SCHEMA_FILE}"

STATE = "observation.state"
ACTION = "action"
ALIGNMENT = "telerig.alignment_error_ms"
IMAGES = "observation.images."
_INDEX_FEATURES = ("frame_index", "episode_index", "index", "task_index")

#: ``telerig.alignment_error_ms`` of a frame whose stream had no sample [ms].
NO_SAMPLE = -1.0

#: LeRobot's tolerance between a frame's timestamp and its video frame's [s].
TOLERANCE_S = 1e-4

_Index = tuple[int, int]


def _advance(index: _Index) -> _Index:
    chunk, file = index
    return (chunk + 1, 0) if file == CHUNKS_SIZE - 1 else (chunk, file + 1)


@dataclass(slots=True)
class Timings:
    """Where a :meth:`LeRobotExporter.write` spent its time [s] (for benchmarks/export.py)."""

    total: float = 0.0
    video: float = 0.0
    episode_seconds: float = 0.0
    remuxed: int = 0
    encoded: int = 0


# -- features and arrow schemas -------------------------------------------------------------------


def _features(schema: DatasetSchema, sources: list[str], language: bool = False) -> dict[str, Any]:
    """LeRobot's ``info.json`` ``features``: cameras, state, action, telerig extras, index columns."""
    features: dict[str, Any] = {}
    for cam in schema.cameras:
        features[IMAGES + cam.key] = {
            "dtype": "video",
            "shape": [cam.height, cam.width, 3],
            "names": ["height", "width", "channels"],
            "info": {
                "video.height": cam.height,
                "video.width": cam.width,
                "video.codec": "h264",
                "video.pix_fmt": "yuv420p",
                "video.is_depth_map": False,
                "video.fps": schema.fps,
                "video.channels": 3,
                "has_audio": False,
            },
        }
    features[STATE] = {"dtype": "float32", "shape": [len(schema.state)], "names": list(schema.state_names)}
    features[ACTION] = {"dtype": "float32", "shape": [len(schema.action)], "names": list(schema.action_names)}
    features[ALIGNMENT] = {"dtype": "float32", "shape": [len(sources)], "names": sources}
    features["timestamp"] = {"dtype": "float32", "shape": [1], "names": None}
    for key in _INDEX_FEATURES:
        features[key] = {"dtype": "int64", "shape": [1], "names": None}
    if language:
        features[SUBTASK] = {"dtype": "int64", "shape": [1], "names": None}
        features[LANGUAGE] = {"dtype": "string", "shape": [1], "names": None}
    return features


def _stat_features(features: Mapping[str, Any]) -> list[str]:
    """Features with statistics (not the text column)."""
    return [key for key, ft in features.items() if ft["dtype"] != "string"]


def _arrow_type(ft: Mapping[str, Any]) -> pa.DataType:
    if ft["dtype"] == "string":
        return pa.string()
    scalar = pa.float32() if ft["dtype"] == "float32" else pa.int64()
    shape = list(ft["shape"])
    return scalar if shape == [1] else pa.list_(scalar, shape[0])


def _data_schema(features: Mapping[str, Any]) -> pa.Schema:
    return pa.schema([(key, _arrow_type(ft)) for key, ft in features.items() if ft["dtype"] != "video"])


def _video_keys(features: Mapping[str, Any]) -> list[str]:
    return [key for key, ft in features.items() if ft["dtype"] == "video"]


def _episodes_schema(features: Mapping[str, Any]) -> pa.Schema:
    """Columns of ``meta/episodes``: LeRobot's (position, tasks, stats) then telerig's."""
    floats = pa.list_(pa.float64())
    ints = pa.list_(pa.int64())
    cols: list[tuple[str, pa.DataType]] = [
        ("episode_index", pa.int64()),
        ("tasks", pa.list_(pa.string())),
        ("length", pa.int64()),
        ("data/chunk_index", pa.int64()),
        ("data/file_index", pa.int64()),
        ("dataset_from_index", pa.int64()),
        ("dataset_to_index", pa.int64()),
    ]
    for key in _video_keys(features):
        cols += [
            (f"videos/{key}/chunk_index", pa.int64()),
            (f"videos/{key}/file_index", pa.int64()),
            (f"videos/{key}/from_timestamp", pa.float64()),
            (f"videos/{key}/to_timestamp", pa.float64()),
        ]
    for key in _stat_features(features):
        ft = features[key]
        for stat in STAT_KEYS:
            if stat == "count":
                kind = ints
            elif ft["dtype"] == "video":
                kind = pa.list_(pa.list_(floats))
            elif ft["dtype"] == "int64" and stat in ("min", "max"):
                kind = ints
            else:
                kind = floats
            cols.append((f"stats/{key}/{stat}", kind))
    cols += [
        ("telerig/episode_id", pa.string()),
        ("telerig/quality", pa.float64()),
        ("telerig/outcome", pa.string()),
        ("telerig/gates", pa.string()),
        ("telerig/valid_fraction", pa.float64()),
        ("telerig/trimmed_s", pa.string()),
        ("meta/episodes/chunk_index", pa.int64()),
        ("meta/episodes/file_index", pa.int64()),
    ]
    return pa.schema(cols)


def _tasks_table(tasks: Mapping[str, int], name: str = "task") -> pa.Table:
    """``meta/tasks.parquet``: pandas reads it as LeRobot wrote it (index: the task string).

    ``name="subtask"``: ``meta/subtasks.parquet`` in the same layout.
    """
    names = sorted(tasks, key=lambda t: tasks[t])
    index_name = f"{name}_index"
    table = pa.table(
        {index_name: pa.array([tasks[n] for n in names], pa.int64()), name: pa.array(names, pa.string())}
    )
    pandas_meta = {
        "index_columns": [name],
        "column_indexes": [
            {
                "name": None,
                "field_name": None,
                "pandas_type": "unicode",
                "numpy_type": "object",
                "metadata": {"encoding": "UTF-8"},
            }
        ],
        "columns": [
            {
                "name": index_name,
                "field_name": index_name,
                "pandas_type": "int64",
                "numpy_type": "int64",
                "metadata": None,
            },
            {
                "name": name,
                "field_name": name,
                "pandas_type": "unicode",
                "numpy_type": "object",
                "metadata": None,
            },
        ],
        "creator": {"library": "pyarrow", "version": pa.__version__},
        "pandas_version": "2.2.3",
    }
    return table.replace_schema_metadata({b"pandas": json.dumps(pandas_meta).encode()})


def _read_tasks(path: Path, name: str = "task") -> dict[str, int]:
    table = pq.read_table(path)
    index_name = f"{name}_index"
    meta = table.schema.metadata or {}
    if name not in table.column_names and b"pandas" in meta:
        index_cols = json.loads(meta[b"pandas"]).get("index_columns", [])
        name = next((c for c in index_cols if isinstance(c, str)), name)
    if name not in table.column_names:
        raise ExportError(f"{path} has no {name} column; it was not written by LeRobot or telerig")
    return {
        str(t): int(i) for t, i in zip(table[name].to_pylist(), table[index_name].to_pylist(), strict=True)
    }


def _table_bytes(table: pa.Table) -> bytes:
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink, compression="snappy")
    return bytes(sink.getvalue().to_pybytes())


# -- the dataset already on disk -------------------------------------------------------------------


@dataclass(slots=True)
class _Existing:
    """What a dataset directory holds, as far as its ``info.json`` commits it."""

    info: dict[str, Any] | None = None
    episodes: list[dict[str, Any]] = field(default_factory=list)  # committed rows, by episode_index
    tasks: dict[str, int] = field(default_factory=dict)
    subtasks: dict[str, int] = field(default_factory=dict)

    @property
    def total_episodes(self) -> int:
        return int(self.info["total_episodes"]) if self.info else 0

    @property
    def total_frames(self) -> int:
        return int(self.info["total_frames"]) if self.info else 0

    def last(self, prefix: str) -> _Index | None:
        """Highest (chunk, file) the committed episodes use for ``prefix`` (``data``, ``videos/k``)."""
        pairs = [(int(e[f"{prefix}/chunk_index"]), int(e[f"{prefix}/file_index"])) for e in self.episodes]
        return max(pairs) if pairs else None


def _load_existing(out: Path) -> _Existing:
    info_path = out / INFO_PATH
    if not info_path.is_file():
        return _Existing()
    try:
        info = json.loads(info_path.read_text())
    except (OSError, ValueError) as exc:
        raise ExportError(f"{info_path} is unreadable ({exc}); export into another --out directory") from None
    if info.get("codebase_version") != CODEBASE_VERSION:
        raise ExportError(
            f"{out} is a LeRobot {info.get('codebase_version')} dataset; telerig appends only to "
            f"{CODEBASE_VERSION}: export into another --out directory"
        )
    existing = _Existing(info=info)
    total = existing.total_episodes
    wanted = [
        "episode_index",
        "telerig/episode_id",
        "dataset_to_index",
        "data/chunk_index",
        "data/file_index",
    ]
    wanted += ["meta/episodes/chunk_index", "meta/episodes/file_index"]
    for key in _video_keys(info["features"]):
        wanted += [f"videos/{key}/chunk_index", f"videos/{key}/file_index"]
    rows: list[dict[str, Any]] = []
    for path in sorted(out.glob("meta/episodes/chunk-*/file-*.parquet")):
        rows += pq.read_table(path, columns=wanted).to_pylist()
    existing.episodes = sorted(
        (r for r in rows if int(r["episode_index"]) < total), key=lambda r: r["episode_index"]
    )
    if [r["episode_index"] for r in existing.episodes] != list(range(total)):
        raise ExportError(
            f"{out}/meta/episodes does not hold episodes 0..{total - 1}; export into another --out"
        )
    if (out / TASKS_PATH).is_file():
        existing.tasks = _read_tasks(out / TASKS_PATH)
    if (out / SUBTASKS_PATH).is_file():
        existing.subtasks = _read_tasks(out / SUBTASKS_PATH, "subtask")
    return existing


def _committed_stats(out: Path, total: int, features: Mapping[str, Any]) -> dict[str, list[Stats]]:
    """Per-episode stats of the committed episodes (their ``stats/...`` columns), per feature.

    The dataset's ``stats.json`` is re-aggregated from these on every run rather than merged into,
    so stats an interrupted run wrote for episodes it never committed do not count.
    """
    per_feature: dict[str, list[Stats]] = {key: [] for key in _stat_features(features)}
    for path in sorted(out.glob("meta/episodes/chunk-*/file-*.parquet")):
        table = pq.read_table(path)
        committed = table.filter(pc.less(table["episode_index"], total))
        for key, found in per_feature.items():
            columns = {stat: committed[f"stats/{key}/{stat}"].to_pylist() for stat in STAT_KEYS}
            for i in range(committed.num_rows):
                found.append({stat: np.asarray(columns[stat][i]) for stat in STAT_KEYS})
    return per_feature


def _file_index(path: Path) -> _Index | None:
    """(chunk, file) of ``.../chunk-XXX/file-XXX.ext``."""
    try:
        return (int(path.parent.name.removeprefix("chunk-")), int(path.stem.removeprefix("file-")))
    except ValueError:
        return None


def _remove_uncommitted(out: Path, existing: _Existing) -> None:
    """Delete what an interrupted run left: staging directories and files past the commit point."""
    for stale in out.glob(".tmp-*"):
        shutil.rmtree(stale, ignore_errors=True)
    video_keys = _video_keys(existing.info["features"]) if existing.info else []
    groups = [("data", out / "data", "parquet"), ("meta/episodes", out / "meta" / "episodes", "parquet")]
    groups += [(f"videos/{k}", out / "videos" / k, "mp4") for k in video_keys]
    for prefix, folder, ext in groups:
        last = existing.last(prefix)
        for path in folder.glob(f"chunk-*/file-*.{ext}"):
            index = _file_index(path)
            if index is not None and (last is None or index > last):
                _log.warning("removing %s, left over from an interrupted export", path)
                path.unlink()


@contextmanager
def _locked(out: Path) -> Iterator[None]:
    """One export at a time into a dataset directory."""
    out.mkdir(parents=True, exist_ok=True)
    with open(out / ".telerig-export.lock", "w") as lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise ExportError(f"another export is writing {out}; wait for it to finish") from None
        yield


# -- writing ----------------------------------------------------------------------------------------


class _ParquetFiles:
    """Appends tables to rolling parquet files under a staging root, as LeRobot sizes data files."""

    def __init__(self, stage: Path, template: str, schema: pa.Schema, start: _Index, max_mb: float) -> None:
        self._stage = stage
        self._template = template
        self._schema = schema
        self._index = start
        self._max_bytes = max_mb * 1024 * 1024
        self._writer: pq.ParquetWriter | None = None
        self._path: Path | None = None
        self._rows = 0
        self.written: list[str] = []

    def add(self, table: pa.Table) -> _Index:
        """Write ``table``; returns the (chunk, file) it went to."""
        if self._writer is not None and self._path is not None and self._rows:
            size = self._path.stat().st_size
            if size + size / self._rows * table.num_rows >= self._max_bytes:
                self.close()
                self._index = _advance(self._index)
        if self._writer is None:
            rel = self._template.format(chunk_index=self._index[0], file_index=self._index[1])
            self._path = self._stage / rel
            self._path.parent.mkdir(parents=True, exist_ok=True)
            self._writer = pq.ParquetWriter(
                self._path, self._schema, compression="snappy", use_dictionary=True
            )
            self._rows = 0
            self.written.append(rel)
        self._writer.write_table(table)
        self._rows += table.num_rows
        return self._index

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None


def _episode_columns(
    episode: EpisodeFrames,
    sources: list[str],
    episode_index: int,
    first_index: int,
    task_index: int,
    subtasks: dict[str, int] | None = None,
) -> dict[str, npt.NDArray[Any]]:
    """The frame columns of one episode (video features excluded)."""
    length = episode.length
    missing = [s for s in sources if s not in episode.alignment_error_ms]
    extra = sorted(set(episode.alignment_error_ms) - set(sources))
    if missing or extra:
        raise ExportError(
            f"episode {episode.episode_id}: its streams ({', '.join(sorted(episode.alignment_error_ms))}) "
            f"differ from the dataset's ({', '.join(sources)}); export it into another --out directory"
        )
    alignment = (
        np.stack([episode.alignment_error_ms[s] for s in sources], axis=1)
        if sources
        else np.zeros((length, 0))
    )
    columns: dict[str, npt.NDArray[Any]] = {
        STATE: np.asarray(episode.state, dtype=np.float32),
        ACTION: np.asarray(episode.action, dtype=np.float32),
        ALIGNMENT: np.where(np.isnan(alignment), NO_SAMPLE, alignment).astype(np.float32),
        "timestamp": episode.timestamp.astype(np.float32),
        "frame_index": np.arange(length, dtype=np.int64),
        "episode_index": np.full(length, episode_index, dtype=np.int64),
        "index": np.arange(first_index, first_index + length, dtype=np.int64),
        "task_index": np.full(length, task_index, dtype=np.int64),
    }
    if subtasks is not None:  # the dataset has the subtask columns
        lang = episode.language
        labels = lang.subtask if lang is not None else ("",) * length
        columns[SUBTASK] = np.array([subtasks.setdefault(t, len(subtasks)) for t in labels], dtype=np.int64)
        words = lang.instruction if lang is not None else (episode.task,) * length
        columns[LANGUAGE] = np.array(words, dtype=object)
    return columns


def _arrow_table(columns: Mapping[str, npt.NDArray[Any]], schema: pa.Schema) -> pa.Table:
    arrays: list[pa.Array] = []
    for name in schema.names:
        values = columns[name]
        kind = schema.field(name).type
        if pa.types.is_fixed_size_list(kind):
            flat = pa.array(np.ascontiguousarray(values).reshape(-1), type=kind.value_type)
            arrays.append(pa.FixedSizeListArray.from_arrays(flat, kind.list_size))
        else:
            arrays.append(pa.array(values, type=kind))
    return pa.Table.from_arrays(arrays, schema=schema)


class LeRobotExporter:
    """Writes and appends LeRobot v3.0 datasets (see the module docstring for the layout)."""

    format: ClassVar[str] = "lerobot"

    def __init__(self, config: LeRobotExportConfig | None = None) -> None:
        self.config = config if config is not None else LeRobotExportConfig()
        #: Timings of the last :meth:`write`.
        self.timings = Timings()

    def schema_path(self, out: Path) -> Path:
        return Path(out) / SCHEMA_PATH

    def existing_episodes(self, out: Path) -> set[str]:
        existing = _load_existing(Path(out))
        return {str(e["telerig/episode_id"]) for e in existing.episodes if e["telerig/episode_id"]}

    def write(
        self,
        out: Path,
        schema: DatasetSchema,
        episodes: Iterable[EpisodeFrames],
        progress: Callable[[EpisodeFrames], None],
    ) -> int:
        """Append ``episodes`` to the dataset at ``out`` (created when absent); returns frames written.

        Raises:
            ExportError: The dataset at ``out`` has other features, or an episode does not fit it.
        """
        out = Path(out)
        started = time.perf_counter()
        self.timings = Timings()
        with _locked(out):
            existing = _load_existing(out)
            _remove_uncommitted(out, existing)
            stage = out / f".tmp-{os.getpid()}"
            shutil.rmtree(stage, ignore_errors=True)
            stage.mkdir()
            try:
                written = self._write(out, stage, schema, episodes, progress, existing)
            finally:
                shutil.rmtree(stage, ignore_errors=True)
        self.timings.total = time.perf_counter() - started
        return written

    def _write(
        self,
        out: Path,
        stage: Path,
        schema: DatasetSchema,
        episodes: Iterable[EpisodeFrames],
        progress: Callable[[EpisodeFrames], None],
        existing: _Existing,
    ) -> int:
        done_ids = {str(e["telerig/episode_id"]) for e in existing.episodes}
        episodes_iter = iter(episodes)
        first = next(episodes_iter, None)
        if first is None:
            return 0
        if existing.info is not None:
            features = existing.info["features"]
            sources = list(features[ALIGNMENT]["names"])
            expected = _features(schema, sources, SUBTASK in features)
            if _strip_info(expected) != _strip_info(features):
                raise ExportError(
                    f"{out} holds a LeRobot dataset with other features; "
                    "export these episodes into another --out directory"
                )
        else:
            sources = sorted(first.alignment_error_ms)
            features = _features(schema, sources, first.language is not None)
        data_schema = _data_schema(features)
        video_keys = _video_keys(features)
        tasks = dict(existing.tasks)
        subtasks = dict(existing.subtasks) if SUBTASK in features else None
        data = _ParquetFiles(
            stage, DATA_PATH, data_schema, _next(existing.last("data")), self.config.data_files_size_in_mb
        )
        videos = {
            key: VideoFileWriter(
                stage,
                key,
                schema.fps,
                _next(existing.last(f"videos/{key}")),
                chunks_size=CHUNKS_SIZE,
                max_mb=self.config.video_files_size_in_mb,
            )
            for key in video_keys
        }
        meta_index = _next(existing.last("meta/episodes"))
        rows: list[dict[str, Any]] = []
        run_stats = _committed_stats(out, existing.total_episodes, features)
        next_frame = existing.total_frames
        try:
            for episode in _chain(first, episodes_iter):
                if episode.episode_id in done_ids:
                    continue
                done_ids.add(episode.episode_id)
                episode_index = existing.total_episodes + len(rows)
                task_index = tasks.setdefault(episode.task, len(tasks))
                if subtasks is None and episode.language is not None:
                    _log.warning(
                        "episode %s: its segments are left out: %s was created without subtask "
                        "columns; export into a new --out directory to keep them",
                        episode.episode_id,
                        out,
                    )
                columns = _episode_columns(episode, sources, episode_index, next_frame, task_index, subtasks)
                data_at = data.add(_arrow_table(columns, data_schema))
                ep_stats = {key: vector_stats(values) for key, values in columns.items() if key != LANGUAGE}
                spans: dict[str, VideoSpan] = {}
                video_started = time.perf_counter()
                for key in video_keys:
                    spans[key], ep_stats[key] = self._add_video(
                        videos[key], episode, key.removeprefix(IMAGES)
                    )
                self.timings.video += time.perf_counter() - video_started
                rows.append(
                    _episode_row(episode, episode_index, next_frame, data_at, spans, ep_stats, meta_index)
                )
                for key, st in ep_stats.items():
                    run_stats[key].append(st)
                next_frame += episode.length
                self.timings.episode_seconds += episode.length / schema.fps
                progress(episode)
        finally:
            data.close()
            for writer in videos.values():
                writer.close()
        if not rows:
            return 0
        meta_rel = EPISODES_PATH.format(chunk_index=meta_index[0], file_index=meta_index[1])
        (stage / meta_rel).parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(
            pa.Table.from_pylist(rows, schema=_episodes_schema(features)),
            stage / meta_rel,
            compression="snappy",
        )
        staged = [rel for w in videos.values() for rel in w.written] + data.written + [meta_rel]
        stats = {key: aggregate(values) for key, values in run_stats.items() if values}
        info = _info(schema, features, existing.total_episodes + len(rows), next_frame, len(tasks))
        info["data_files_size_in_mb"] = _number(self.config.data_files_size_in_mb)
        info["video_files_size_in_mb"] = _number(self.config.video_files_size_in_mb)
        _commit(out, stage, staged, tasks, stats, schema, info, subtasks)
        return next_frame - existing.total_frames

    def _add_video(
        self, writer: VideoFileWriter, episode: EpisodeFrames, camera: str
    ) -> tuple[VideoSpan, Stats]:
        track = episode.cameras.get(camera)
        if track is None:
            raise ExportError(
                f"episode {episode.episode_id} has no camera {camera!r}, which the dataset needs"
            )
        spec = track.spec
        image_stats = ImageStats(spec.height, spec.width)
        if self.config.copy_video and track.one_to_one and remuxable(track.path):
            span = writer.add_remux(track.path, episode.length, image_stats)
            self.timings.remuxed += 1
        else:
            span = writer.add_encoded(track.frames(), episode.length, spec.height, spec.width, image_stats)
            self.timings.encoded += 1
        return span, image_stats.result()

    def validate(self, out: Path) -> ValidationReport:
        """Re-read the dataset; one line per problem (see :func:`_validate`)."""
        problems: list[str] = []
        episodes, frames = _validate(Path(out), problems)
        return ValidationReport(episodes, frames, tuple(problems))


def _number(value: float) -> float | int:
    return int(value) if float(value).is_integer() else value


def _next(last: _Index | None) -> _Index:
    return (0, 0) if last is None else _advance(last)


def _chain(first: EpisodeFrames, rest: Iterator[EpisodeFrames]) -> Iterator[EpisodeFrames]:
    yield first
    yield from rest


def _strip_info(features: Mapping[str, Any]) -> dict[str, Any]:
    """Features without the video ``info`` block (its codec details may differ between runs)."""
    return {k: {f: v for f, v in ft.items() if f != "info"} for k, ft in features.items()}


def _episode_row(
    episode: EpisodeFrames,
    episode_index: int,
    first_index: int,
    data_at: _Index,
    spans: Mapping[str, VideoSpan],
    ep_stats: Mapping[str, Stats],
    meta_index: _Index,
) -> dict[str, Any]:
    row: dict[str, Any] = {
        "episode_index": episode_index,
        "tasks": [episode.task],
        "length": episode.length,
        "data/chunk_index": data_at[0],
        "data/file_index": data_at[1],
        "dataset_from_index": first_index,
        "dataset_to_index": first_index + episode.length,
    }
    for key, span in spans.items():
        row[f"videos/{key}/chunk_index"] = span.chunk
        row[f"videos/{key}/file_index"] = span.file
        row[f"videos/{key}/from_timestamp"] = span.from_s
        row[f"videos/{key}/to_timestamp"] = span.to_s
    for key, st in ep_stats.items():
        for stat in STAT_KEYS:
            row[f"stats/{key}/{stat}"] = np.asarray(st[stat]).tolist()
    quality = episode.quality if episode.quality is not None else episode.extra.quality
    row.update(
        {
            "telerig/episode_id": episode.episode_id,
            "telerig/quality": quality,
            "telerig/outcome": episode.outcome,
            "telerig/gates": json.dumps(episode.gates),
            "telerig/valid_fraction": float(np.mean(episode.valid)) if episode.length else 0.0,
            "telerig/trimmed_s": json.dumps([list(span) for span in episode.trimmed_s]),
            "meta/episodes/chunk_index": meta_index[0],
            "meta/episodes/file_index": meta_index[1],
        }
    )
    return row


def _info(
    schema: DatasetSchema, features: Mapping[str, Any], episodes: int, frames: int, tasks: int
) -> dict[str, Any]:
    robots = sorted(set(schema.robots.values()))
    return {
        "codebase_version": CODEBASE_VERSION,
        "robot_type": robots[0] if len(robots) == 1 else schema.rig,
        "total_episodes": episodes,
        "total_frames": frames,
        "total_tasks": tasks,
        "chunks_size": CHUNKS_SIZE,
        "data_files_size_in_mb": 100,
        "video_files_size_in_mb": 200,
        "fps": schema.fps,
        "splits": {"train": f"0:{episodes}"},
        "data_path": DATA_PATH,
        "video_path": VIDEO_PATH if _video_keys(features) else None,
        "features": dict(features),
        "telerig": {"rig": schema.rig, "fingerprint": schema.fingerprint, "schema": SCHEMA_PATH},
    }


def _commit(
    out: Path,
    stage: Path,
    staged: list[str],
    tasks: Mapping[str, int],
    stats: Mapping[str, Stats],
    schema: DatasetSchema,
    info: Mapping[str, Any],
    subtasks: Mapping[str, int] | None = None,
) -> None:
    """Move the new files into place, then replace the metadata; ``info.json`` last."""
    for rel in staged:
        with open(stage / rel, "rb") as f:
            os.fsync(f.fileno())
    for rel in staged:
        target = out / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        os.replace(stage / rel, target)
    write_atomic(out / TASKS_PATH, _table_bytes(_tasks_table(tasks)))
    if subtasks is not None:
        write_atomic(out / SUBTASKS_PATH, _table_bytes(_tasks_table(subtasks, "subtask")))
    write_atomic(out / STATS_PATH, json.dumps(stats_to_json(stats), indent=2) + "\n")
    write_atomic(out / SCHEMA_PATH, schema.dumps())
    write_atomic(out / INFO_PATH, json.dumps(info, indent=2) + "\n")


# -- validation --------------------------------------------------------------------------------------


def _validate(out: Path, problems: list[str]) -> tuple[int, int]:
    """Check what :class:`LeRobotExporter` wrote; appends one line per problem; returns (episodes, frames)."""
    try:
        existing = _load_existing(out)
    except (ExportError, OSError, pa.ArrowException, KeyError) as exc:
        problems.append(f"unreadable LeRobot metadata: {exc}")
        return 0, 0
    info = existing.info
    if info is None:
        problems.append(f"no {INFO_PATH}")
        return 0, 0
    features = info["features"]
    try:
        schema = DatasetSchema.loads((out / SCHEMA_PATH).read_bytes())
    except (OSError, ExportError, ValueError) as exc:
        problems.append(f"{SCHEMA_PATH} unreadable: {exc}")
        return existing.total_episodes, existing.total_frames
    _check_features(schema, features, problems)
    rows = _episode_rows(out, existing.total_episodes)
    _check_episodes(info, rows, existing.tasks, problems)
    if not problems:
        _check_data(out, info, rows, existing.tasks, problems)
    if not problems and SUBTASK in features:
        _check_subtasks(out, rows, existing.subtasks, problems)
    if not problems:
        for key in _video_keys(features):
            _check_video(out, key, info, rows, problems)
    _check_stats(out, features, existing.total_frames, problems)
    return existing.total_episodes, existing.total_frames


def _episode_rows(out: Path, total: int) -> list[dict[str, Any]]:
    rows: list[dict[str, Any]] = []
    for path in sorted(out.glob("meta/episodes/chunk-*/file-*.parquet")):
        table = pq.read_table(path)
        keep = [c for c in table.column_names if not c.startswith("stats/")]
        rows += table.select(keep).to_pylist()
    return sorted((r for r in rows if r["episode_index"] < total), key=lambda r: r["episode_index"])


def _check_features(schema: DatasetSchema, features: Mapping[str, Any], problems: list[str]) -> None:
    for key, names in ((STATE, schema.state_names), (ACTION, schema.action_names)):
        ft = features.get(key)
        if ft is None:
            problems.append(f"info.json has no {key} feature")
        elif list(ft["shape"]) != [len(names)] or list(ft["names"]) != list(names):
            problems.append(
                f"{key} has shape {ft['shape']}, the robots have {len(names)} entries ({SCHEMA_PATH})"
            )
    for cam in schema.cameras:
        ft = features.get(IMAGES + cam.key)
        if ft is None or ft["dtype"] != "video":
            problems.append(f"info.json has no video feature {IMAGES + cam.key}")
        elif list(ft["shape"]) != [cam.height, cam.width, 3] or list(ft["names"])[-1] != "channels":
            problems.append(
                f"{IMAGES + cam.key} has shape {ft['shape']}, the camera records {list(cam.shape)}"
            )


def _check_episodes(
    info: Mapping[str, Any], rows: list[dict[str, Any]], tasks: Mapping[str, int], problems: list[str]
) -> None:
    if len(tasks) < info["total_tasks"]:
        problems.append(f"tasks.parquet holds {len(tasks)} tasks, info.json says {info['total_tasks']}")
    start = 0
    for row in rows:
        ep = row["episode_index"]
        unknown = [t for t in row["tasks"] if t not in tasks]
        if unknown:
            problems.append(f"episode {ep}: task {unknown[0]!r} is not in {TASKS_PATH}")
        if row["dataset_from_index"] != start or row["dataset_to_index"] - start != row["length"]:
            problems.append(
                f"episode {ep}: rows [{row['dataset_from_index']}, {row['dataset_to_index']}) "
                f"do not follow row {start} with its length {row['length']}"
            )
            return
        if row["length"] <= 0:
            problems.append(f"episode {ep} has no frame")
        start = row["dataset_to_index"]
    if start != info["total_frames"]:
        problems.append(f"episodes hold {start} frames, info.json says {info['total_frames']}")


def _check_data(
    out: Path,
    info: Mapping[str, Any],
    rows: list[dict[str, Any]],
    tasks: Mapping[str, int],
    problems: list[str],
) -> None:
    fps = info["fps"]
    by_file: dict[_Index, list[dict[str, Any]]] = {}
    for row in rows:
        by_file.setdefault((row["data/chunk_index"], row["data/file_index"]), []).append(row)
    state_dim = info["features"][STATE]["shape"][0]
    action_dim = info["features"][ACTION]["shape"][0]
    for (chunk, file), eps in sorted(by_file.items()):
        rel = DATA_PATH.format(chunk_index=chunk, file_index=file)
        table = pq.read_table(out / rel)
        episode_index = table["episode_index"].to_numpy()
        for row in eps:
            ep = row["episode_index"]
            mask = episode_index == ep
            if int(mask.sum()) != row["length"]:
                problems.append(
                    f"episode {ep}: {rel} holds {int(mask.sum())} frames, its length is {row['length']}"
                )
                return
            sel = table.filter(pa.array(mask))
            index = sel["index"].to_numpy()
            frame_index = sel["frame_index"].to_numpy()
            ts = sel["timestamp"].to_numpy().astype(np.float64)
            task_index = {tasks[t] for t in row["tasks"]}
            if not set(sel["task_index"].to_numpy().tolist()) <= task_index:
                problems.append(f"episode {ep}: its task_index is not that of its tasks {row['tasks']}")
            if not np.array_equal(index, np.arange(row["dataset_from_index"], row["dataset_to_index"])):
                problems.append(
                    f"episode {ep}: its index column is not "
                    f"{row['dataset_from_index']}..{row['dataset_to_index'] - 1}"
                )
            if not np.array_equal(frame_index, np.arange(row["length"])):
                problems.append(f"episode {ep}: frame_index is not 0..{row['length'] - 1}")
            if np.any(np.diff(ts) <= 0):
                problems.append(f"episode {ep}: timestamps are not increasing")
            elif np.abs(ts - frame_index / fps).max() > max(
                TOLERANCE_S, float(np.spacing(np.float32(ts[-1])))
            ):
                problems.append(f"episode {ep}: timestamps are not frame_index / {fps} Hz")
            for key, dim in ((STATE, state_dim), (ACTION, action_dim)):
                values = sel[key]
                if values.type.list_size != dim:
                    problems.append(f"{rel}: {key} has {values.type.list_size} values per frame, not {dim}")
                    return
                flat = values.combine_chunks().flatten().to_numpy()
                if not np.isfinite(flat).all():
                    problems.append(f"episode {ep}: {key} holds non-finite values")
            if problems:
                return


def _check_subtasks(
    out: Path, rows: list[dict[str, Any]], subtasks: Mapping[str, int], problems: list[str]
) -> None:
    """Every frame's ``subtask_index`` names a subtask of ``meta/subtasks.parquet``."""
    known = set(subtasks.values())
    for chunk, file in sorted({(r["data/chunk_index"], r["data/file_index"]) for r in rows}):
        rel = DATA_PATH.format(chunk_index=chunk, file_index=file)
        used = set(pq.read_table(out / rel, columns=[SUBTASK])[SUBTASK].to_pylist())
        if not used <= known:
            problems.append(f"{rel}: subtask_index {sorted(used - known)[0]} is not in {SUBTASKS_PATH}")
            return


def _check_video(
    out: Path, key: str, info: Mapping[str, Any], rows: list[dict[str, Any]], problems: list[str]
) -> None:
    fps = info["fps"]
    height, width, _ = info["features"][key]["shape"]
    by_file: dict[_Index, list[dict[str, Any]]] = {}
    for row in rows:
        by_file.setdefault((row[f"videos/{key}/chunk_index"], row[f"videos/{key}/file_index"]), []).append(
            row
        )
    for (chunk, file), eps in sorted(by_file.items()):
        rel = VIDEO_PATH.format(video_key=key, chunk_index=chunk, file_index=file)
        try:
            with av.open(str(out / rel)) as container:
                stream = container.streams.video[0]
                if (stream.height, stream.width) != (height, width):
                    problems.append(
                        f"{rel} is {stream.width}x{stream.height}, info.json says {width}x{height}"
                    )
                    return
                packets = [
                    (p.pts, p.is_keyframe) for p in container.demux(stream) if p.size and p.pts is not None
                ]
                tb = float(stream.time_base)
                container.seek(0)
                first = next(container.decode(stream)).to_ndarray(format="rgb24")
        except (av.FFmpegError, OSError, StopIteration, IndexError) as exc:
            problems.append(f"{rel} is unreadable: {exc}")
            return
        if first.shape != (height, width, 3):
            problems.append(
                f"{rel} decodes to frames of shape {first.shape}, info.json says {(height, width, 3)}"
            )
        times = np.array([p[0] for p in packets], dtype=np.float64) * tb
        keys = np.array([p[1] for p in packets], dtype=bool)
        for row in eps:
            ep = row["episode_index"]
            start = row[f"videos/{key}/from_timestamp"]
            want = start + np.arange(row["length"]) / fps
            at = np.searchsorted(times, start - TOLERANCE_S)
            got = times[at : at + row["length"]]
            if got.size != want.size or np.abs(got - want).max() > TOLERANCE_S:
                problems.append(f"episode {ep}: {rel} has no frame within {TOLERANCE_S} s of every timestamp")
                return
            if not keys[at]:
                problems.append(f"episode {ep}: its video in {rel} does not start on a keyframe")


def _check_stats(out: Path, features: Mapping[str, Any], frames: int, problems: list[str]) -> None:
    try:
        stats = json.loads((out / STATS_PATH).read_text())
    except (OSError, ValueError) as exc:
        problems.append(f"{STATS_PATH} unreadable: {exc}")
        return
    for key in _stat_features(features):
        ft = features[key]
        st = stats.get(key)
        if st is None or any(s not in st for s in STAT_KEYS):
            problems.append(f"{STATS_PATH} lacks {key} or one of {', '.join(STAT_KEYS)}")
            return
        shape = (3, 1, 1) if ft["dtype"] == "video" else tuple(ft["shape"])
        if np.asarray(st["mean"]).shape != shape:
            problems.append(f"{STATS_PATH}: {key} mean has shape {np.asarray(st['mean']).shape}, not {shape}")
        elif ft["dtype"] != "video" and st["count"] != [frames]:
            problems.append(f"{STATS_PATH}: {key} counts {st['count']} frames, the dataset has {frames}")
        elif ft["dtype"] != "video" and not all(math.isfinite(v) for v in np.ravel(st["mean"])):
            problems.append(f"{STATS_PATH}: {key} mean is not finite")
