"""Stage 5, the dataset layout: clips by scene type, each with its annotation and its recorded streams.

Per item (:class:`LayoutStage`), every clip of the ``clips`` stage lands in the processed root as::

    dataset/<scene>/<uuid>.mp4            the clip (a hard link to the clips stage's file when the
                                          filesystem allows, else a copy)
    dataset/<scene>/<uuid>.json           its annotation file: source, span, fps, label, annotation
    dataset/<scene>/<uuid>.streams/       an episode's recorded streams cut to the clip's span, one
        <node>.<stream>.jsonl             JSON line per sample (``t_s`` from the clip's first frame,
        streams.json                      ``capture_ns`` and the numeric fields), and what they are

``<scene>`` is the annotation's scene type (``unknown`` when the clip was not annotated). The item's
``layout.json`` lists what it placed. Once every item ran, :meth:`LayoutStage.finish` writes the
global ``index.json`` (raw recording -> its clips, with frame rate, duration, device id and date)
from every item's ``layout.json`` in the processed root and removes dataset files no item lists any
more (a clip whose segment changed); :func:`index_clips` puts the same rows in the index database.

Streams are read with :func:`telerig.record.align.load_streams` (the episode's MCAP log); the clip's
span on the camera video's timeline is moved to the common clock by the camera's recorded frame
capture times (``<camera>/frames``): the median of capture time minus presentation time.
"""

from __future__ import annotations

import contextlib
import datetime
import json
import logging
import os
import re
import shutil
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from telerig.bus.catalogue import CAMERA_FRAMES
from telerig.bus.topics import Topic
from telerig.config.process import LayoutSettings
from telerig.errors import ProcessError, RecordingError, WireError
from telerig.process.annotate import ClipEntry, read_annotations, read_clips
from telerig.process.stage import (
    Item,
    StageContext,
    StageResult,
    read_json,
    read_provenance,
    write_atomic,
    write_json_atomic,
)
from telerig.record.align import StreamData, load_streams
from telerig.store.index import EpisodeIndex, ProcessedClipRecord

__all__ = ["DATASET_DIR", "INDEX_FILE", "LAYOUT_FILE", "LayoutStage", "index_clips", "read_index"]

_log = logging.getLogger("telerig.process.layout")

DATASET_DIR = "dataset"
INDEX_FILE = "index.json"
LAYOUT_FILE = "layout.json"
INDEX_SCHEMA = 1
UNKNOWN_SCENE = "unknown"
_SCENE = re.compile(r"^[a-z0-9][a-z0-9_-]{0,63}$")
_MAX_LAYOUT_BYTES = 16 << 20
_MAX_INDEX_BYTES = 256 << 20


def _scene_of(record: Mapping[str, Any] | None) -> str:
    """A directory-safe scene name from an annotation record; ``unknown`` when absent or odd."""
    scene = record.get("scene") if record is not None else None
    if not isinstance(scene, str):
        return UNKNOWN_SCENE
    name = re.sub(r"[^a-z0-9_-]+", "_", scene.strip().lower()).strip("_")
    return name if _SCENE.match(name) else UNKNOWN_SCENE


def _place(src: Path, dest: Path) -> None:
    """Put ``src`` at ``dest`` atomically: a hard link (no copy of the bytes) or, across filesystems,
    a copy; an existing ``dest`` is replaced."""
    tmp = dest.with_name(f".{dest.name}.tmp")
    with contextlib.suppress(FileNotFoundError):
        tmp.unlink()
    try:
        os.link(src, tmp)
    except OSError:
        shutil.copyfile(src, tmp)
    os.replace(tmp, dest)


@dataclass(frozen=True)
class _Clock:
    """Video time [s] -> common clock [ns] for one camera: ``clock = offset_ns + video_s * 1e9``."""

    offset_ns: int

    def at(self, video_s: float) -> int:
        return self.offset_ns + round(video_s * 1e9)


def _frame_pts_s(video: Path) -> np.ndarray:
    """Presentation times [s] of the video's frames, in order, from the container (no decoding)."""
    import av

    times: list[float] = []
    with av.open(str(video)) as container:
        stream = container.streams.video[0]
        base = float(stream.time_base) if stream.time_base else 0.0
        for packet in container.demux(stream):
            if packet.pts is not None:
                times.append(packet.pts * base)
    return np.sort(np.asarray(times, dtype=np.float64))


def _camera_clock(streams: Mapping[str, StreamData], video: Path) -> _Clock | None:
    camera = video.stem.split(".")[0]
    for topic, data in streams.items():
        parsed = Topic.try_parse(topic)
        if parsed is None or parsed.stream != CAMERA_FRAMES or parsed.node != camera:
            continue
        pts = _frame_pts_s(video)
        n = min(pts.size, data.time_ns.size)
        if n == 0:
            return None
        offsets = data.time_ns[:n].astype(np.float64) - pts[:n] * 1e9
        return _Clock(int(np.median(offsets)))
    return None


def _jsonable(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return [_jsonable(v) for v in value.tolist()] if value.ndim else _jsonable(value.item())
    if isinstance(value, float):
        return value if np.isfinite(value) else None  # JSON has no NaN
    if isinstance(value, list):
        return [_jsonable(v) for v in value]
    return value


def _write_streams(
    streams: Mapping[str, StreamData], clock: _Clock, clip: ClipEntry, dest: Path, margin_s: float
) -> dict[str, Any]:
    """Every stream's samples within the clip's span (+ margin) as JSON lines under ``dest``."""
    start_ns, end_ns = clock.at(clip.start_s), clock.at(clip.end_s)
    lo, hi = start_ns - round(margin_s * 1e9), end_ns + round(margin_s * 1e9)
    tmp = dest.with_name(f".{dest.name}.tmp")
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    listing: dict[str, Any] = {}
    for topic, data in streams.items():
        parsed = Topic.try_parse(topic)
        name = f"{parsed.node}.{parsed.stream}" if parsed is not None else re.sub(r"\W+", "_", topic)
        keep = np.flatnonzero((data.time_ns >= lo) & (data.time_ns <= hi))
        lines = []
        for i in keep:
            row: dict[str, Any] = {"t_s": round((int(data.time_ns[i]) - start_ns) / 1e9, 6)}
            row["capture_ns"] = int(data.time_ns[i])
            for field, values in data.fields.items():
                row[field] = _jsonable(values[i])
            lines.append(json.dumps(row, separators=(",", ":")))
        (tmp / f"{name}.jsonl").write_text("\n".join(lines) + ("\n" if lines else ""))
        listing[name] = {
            "topic": topic,
            "sample_type": data.sample_type,
            "samples": len(lines),
            "names": list(data.names),
            "file": f"{name}.jsonl",
        }
    meta = {
        "clip": clip.uuid,
        "start_ns": start_ns,
        "end_ns": end_ns,
        "margin_s": margin_s,
        "streams": listing,
    }
    (tmp / "streams.json").write_text(json.dumps(meta, indent=2, sort_keys=True) + "\n")
    if dest.exists():
        shutil.rmtree(dest)
    os.replace(tmp, dest)
    return listing


class _EpisodeStreams:
    """An episode's streams, loaded once per item when the first clip needs them."""

    def __init__(self, item: Item) -> None:
        self._item = item
        self._streams: dict[str, StreamData] | None = None
        self._clocks: dict[str, _Clock | None] = {}
        self.error = ""

    def clock_and_streams(self, video: Path) -> tuple[_Clock, Mapping[str, StreamData]] | None:
        if self._item.episode_dir is None or self.error:
            return None
        if self._streams is None:
            try:
                self._streams = load_streams(Path(self._item.episode_dir) / "episode.mcap")
            except (RecordingError, WireError, OSError) as exc:
                self.error = f"streams not written: {exc}"
                _log.warning("%s: %s", self._item.id, self.error)
                return None
        key = str(video)
        if key not in self._clocks:
            try:
                self._clocks[key] = _camera_clock(self._streams, video)
            except (OSError, ValueError, IndexError) as exc:
                _log.warning("%s: cannot read frame times of %s: %s", self._item.id, video, exc)
                self._clocks[key] = None
        clock = self._clocks[key]
        return None if clock is None else (clock, self._streams)


def _source(item: Item) -> dict[str, Any]:
    meta = item.meta
    return {
        "id": item.id,
        "kind": item.kind,
        "path": str(item.episode_dir or (item.videos[0] if item.videos else "")),
        "hash": item.source_hash,
        "device_id": meta.get("device_id"),
        "date": meta.get("date"),
        "task": meta.get("task"),
        "fps": meta.get("fps"),
        "duration_s": meta.get("duration_s"),
    }


class LayoutStage:
    """Stage 5 (see the module docstring)."""

    name = "layout"
    version = "1"

    def run(self, item: Item, ctx: StageContext) -> StageResult:
        """Place the item's clips under ``<processed>/dataset/<scene>/`` and list them in ``layout.json``.

        Raises:
            ProcessError: The clips stage's output is unreadable, or a clip file is missing.
        """
        settings = ctx.settings if isinstance(ctx.settings, LayoutSettings) else LayoutSettings()
        clips_dir = ctx.upstream.get("clips")
        if clips_dir is None:
            write_json_atomic(ctx.out_dir / LAYOUT_FILE, {"source": _source(item), "clips": []})
            return StageResult("empty", (LAYOUT_FILE,), {"clips_laid_out": 0.0}, "no clips stage ran")
        clips, _dropped = read_clips(clips_dir)
        annotations = read_annotations(ctx.upstream["annotate"]) if "annotate" in ctx.upstream else {}
        episode = _EpisodeStreams(item) if settings.streams and item.kind == "episode" else None
        dataset = ctx.work_root / DATASET_DIR
        entries: list[dict[str, Any]] = []
        for n, clip in enumerate(clips):
            entries.append(
                self._one(item, clip, Path(clips_dir), annotations.get(clip.uuid), dataset, episode, settings)
            )
            ctx.progress((n + 1) / len(clips))
        write_json_atomic(ctx.out_dir / LAYOUT_FILE, {"source": _source(item), "clips": entries})
        outputs = [LAYOUT_FILE]
        for e in entries:  # the placed files, so a re-run redoes the item when one was deleted
            outputs += [
                os.path.relpath(ctx.work_root / e[k], ctx.out_dir) for k in ("path", "annotation_file")
            ]
        metrics = {"clips_laid_out": float(len(entries))}
        if not entries:
            return StageResult("empty", tuple(outputs), metrics, "the item has no clips")
        message = episode.error if episode is not None else ""
        return StageResult("ok", tuple(outputs), metrics, message)

    @staticmethod
    def _one(
        item: Item,
        clip: ClipEntry,
        clips_dir: Path,
        annotation: Mapping[str, Any] | None,
        dataset: Path,
        episode: _EpisodeStreams | None,
        settings: LayoutSettings,
    ) -> dict[str, Any]:
        src = clips_dir / clip.file
        if not src.is_file():
            raise ProcessError(
                f"clip {clip.uuid} of item {item.id}: {src} is missing; re-run the clips stage"
            )
        scene = _scene_of(annotation)
        folder = dataset / scene
        folder.mkdir(parents=True, exist_ok=True)
        _place(src, folder / f"{clip.uuid}.mp4")
        fps, duration = _clip_rate(src, clip)
        streams_rel: str | None = None
        if episode is not None:
            video = _video_path(item, clip.video, dataset.parent)
            # Frame stamps map a recorded camera file's timeline only (not a processed file's).
            recorded = {v.resolve() for v in item.videos}
            if video is not None and video.resolve() not in recorded:
                video = None
            loaded = episode.clock_and_streams(video) if video is not None else None
            if loaded is not None:
                clock, streams = loaded
                _write_streams(
                    streams, clock, clip, folder / f"{clip.uuid}.streams", settings.stream_margin_s
                )
                streams_rel = f"{DATASET_DIR}/{scene}/{clip.uuid}.streams"
        entry = {
            "id": clip.uuid,
            "scene": scene,
            "path": f"{DATASET_DIR}/{scene}/{clip.uuid}.mp4",
            "annotation_file": f"{DATASET_DIR}/{scene}/{clip.uuid}.json",
            "streams": streams_rel,
            "video": clip.video,
            "start_s": clip.start_s,
            "end_s": clip.end_s,
            "duration_s": duration,
            "fps": fps,
            "label": clip.label,
        }
        record = {**entry, "source": _source(item), "annotation": dict(annotation) if annotation else None}
        write_atomic(folder / f"{clip.uuid}.json", json.dumps(record, indent=2, sort_keys=True) + "\n")
        return entry

    def finish(self, work_root: Path, item_ids: Sequence[str], settings: Any) -> None:
        """Write ``index.json`` over every item's layout in ``work_root`` and prune stale dataset files."""
        del item_ids, settings  # the index covers the whole processed root, not only this run's items
        write_index(work_root)


def _video_path(item: Item, video: str, work_root: Path) -> Path | None:
    """The clip's source video: absolute, or relative to the episode or to the processed root (as
    the segment stage names it)."""
    path = Path(video)
    if path.is_absolute():
        return path if path.is_file() else None
    for base in (item.episode_dir, work_root):
        if base is not None and (Path(base) / path).is_file():
            return Path(base) / path
    return None


def _clip_rate(path: Path, clip: ClipEntry) -> tuple[float | None, float]:
    """The clip file's frame rate [Hz] and duration [s] (its span when the container has none)."""
    import av

    span = max(0.0, clip.end_s - clip.start_s)
    try:
        with av.open(str(path)) as container:
            stream = container.streams.video[0]
            fps = float(stream.average_rate) if stream.average_rate else None
            duration = container.duration / 1e6 if container.duration else span
    except (OSError, av.FFmpegError, IndexError, ValueError):
        return None, span
    return (round(fps, 3) if fps else None), round(duration, 3)


def write_index(work_root: Path) -> dict[str, Any]:
    """``<work_root>/index.json`` from every finished item layout; stale dataset files removed.

    An item whose layout provenance is missing, failed or damaged is left out (and logged).
    """
    work_root = Path(work_root)
    sources: dict[str, Any] = {}
    clips: list[dict[str, Any]] = []
    for layout_dir in sorted((work_root / "items").glob(f"*/{LayoutStage.name}")):
        try:
            prov = read_provenance(layout_dir)
            if prov is None or prov.status == "failed":
                continue
            doc = read_json(layout_dir / LAYOUT_FILE, max_bytes=_MAX_LAYOUT_BYTES, what="a layout file")
            source, entries = _layout_doc(doc, layout_dir / LAYOUT_FILE)
        except ProcessError as exc:
            _log.warning("%s left out of the index: %s", layout_dir.parent.name, exc)
            continue
        ids = []
        for entry in entries:
            clips.append({**entry, "source_id": source["id"]})
            ids.append(entry["id"])
        sources[source["id"]] = {**source, "clips": ids}
    index = {
        "schema": INDEX_SCHEMA,
        "generated": datetime.datetime.now(tz=datetime.UTC).isoformat(timespec="seconds"),
        "sources": sources,
        "clips": clips,
    }
    write_json_atomic(work_root / INDEX_FILE, index)
    _prune(work_root / DATASET_DIR, clips)
    return index


_ENTRY_KEYS = ("id", "scene", "path", "annotation_file", "start_s", "end_s", "duration_s")


def _layout_doc(doc: Any, path: Path) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """The source and clip entries of a ``layout.json``, checked enough to index them.

    Raises:
        ProcessError: It is not a layout file (one line).
    """
    what = f"{path} is not a layout file (source with an id, clips with {', '.join(_ENTRY_KEYS)})"
    if not isinstance(doc, dict):
        raise ProcessError(what)
    source, entries = doc.get("source"), doc.get("clips")
    if not (isinstance(source, dict) and isinstance(source.get("id"), str) and isinstance(entries, list)):
        raise ProcessError(what)
    if not all(isinstance(e, dict) and all(k in e for k in _ENTRY_KEYS) for e in entries):
        raise ProcessError(what)
    return source, entries


def _prune(dataset: Path, clips: Sequence[Mapping[str, Any]]) -> None:
    """Remove clip files, annotation files and stream folders no item lists (a redone segmentation's
    old clips); anything else in the dataset folder is left alone."""
    if not dataset.is_dir():
        return
    wanted = {(c["scene"], c["id"]) for c in clips}
    for folder in dataset.iterdir():
        if not folder.is_dir() or folder.is_symlink():
            continue
        for path in folder.iterdir():
            uuid = path.name.split(".")[0]
            if not re.fullmatch(r"[0-9a-fA-F-]{8,64}", uuid) or (folder.name, uuid) in wanted:
                continue
            if path.name.endswith(".streams") and path.is_dir() and not path.is_symlink():
                shutil.rmtree(path)
            elif path.suffix in (".mp4", ".json") and path.is_file():
                path.unlink()


def read_index(work_root: Path) -> dict[str, Any]:
    """The processed root's ``index.json``.

    Raises:
        ProcessError: Missing, unreadable or not an index.
    """
    path = Path(work_root) / INDEX_FILE
    doc = read_json(path, max_bytes=_MAX_INDEX_BYTES, what="a processed index")
    if (
        not isinstance(doc, dict)
        or doc.get("schema") != INDEX_SCHEMA
        or not isinstance(doc.get("clips"), list)
    ):
        raise ProcessError(f"{path} is not a processed index (schema {INDEX_SCHEMA}); re-run telerig process")
    return doc


def index_clips(work_root: Path, index: EpisodeIndex) -> int:
    """Put the processed root's ``index.json`` in the index database (its rows replaced as a whole).

    Returns:
        How many clips the database holds for this root.
    """
    doc = read_index(work_root)
    try:
        rows = _clip_rows(doc)
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise ProcessError(
            f"{Path(work_root) / INDEX_FILE}: a clip entry is malformed ({type(exc).__name__}: {exc}); "
            "re-run telerig process to write it again"
        ) from None
    return index.replace_processed_clips(Path(work_root), rows)


def _clip_rows(doc: Mapping[str, Any]) -> list[ProcessedClipRecord]:
    sources = doc.get("sources", {})
    rows = []
    for clip in doc["clips"]:
        source = sources.get(clip.get("source_id"), {})
        rows.append(
            ProcessedClipRecord(
                id=str(clip["id"]),
                processed_root="",
                source_id=str(clip["source_id"]),
                source_kind=str(source.get("kind", "")),
                source_path=str(source.get("path", "")),
                source_hash=str(source.get("hash", "")),
                path=str(clip["path"]),
                scene=str(clip["scene"]),
                label=clip.get("label"),
                start_s=float(clip["start_s"]),
                end_s=float(clip["end_s"]),
                duration_s=float(clip["duration_s"]),
                fps=float(clip["fps"]) if clip.get("fps") is not None else None,
                device_id=source.get("device_id"),
                date=source.get("date"),
            )
        )
    return rows
