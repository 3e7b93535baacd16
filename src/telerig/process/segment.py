"""Stage 2, temporal action segmentation: one ``segments.json`` per item, on its video's timeline.

Which segmenter runs (both from :mod:`telerig.config.process`'s ``SegmentSettings``):

* an episode whose robots recorded joint states or a gripper: ``settings.robot`` (default
  ``robot_streams``), on the recorded streams; its times are moved onto the anchor camera's
  timeline by that camera's recorded frame times (``<camera>/frames`` in ``episode.mcap``);
* a plain video, or an episode without robot streams: ``settings.video`` (default
  ``motion_energy``) on the item's first video, within the spans the filter stage kept and with the
  hand boxes it recorded (``filter.json`` and its ``samples.json``). A video the filter marked empty
  (no hands) has no action: it is marked ``empty`` without being decoded.

The file goes through :mod:`telerig.store.segments_file` (the one schema for machine and human
labels); an episode also gets it beside its files, where a person's reviewed segments already in
it are kept and only the machine proposals are replaced.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from telerig.bus.catalogue import CAMERA_FRAMES
from telerig.bus.topics import Topic
from telerig.config.process import SegmentSettings
from telerig.errors import ProcessError, RecordingError
from telerig.process.segmenters import (
    HandTrack,
    Proposal,
    Segmenter,
    SegmentInput,
    VideoInfo,
    build_segmenter,
    probe_video,
)
from telerig.process.stage import Item, StageContext, StageResult, read_json
from telerig.store.segments_file import (
    SEGMENTS_FILE,
    SegmentsRecord,
    machine_source,
    merge_machine,
    new_segment,
    read_episode_segments,
    write_episode_segments,
    write_segments,
)

__all__ = ["SegmentStage", "resolve_video", "segment_item", "video_offset_s"]

_log = logging.getLogger("telerig.process.segment")

_FILTER_FILE = "filter.json"
#: filter.json lists a few entries per video; samples.json one per sampled frame (2 Hz: 7200 per hour).
_MAX_FILTER_BYTES = 4 << 20
_MAX_SAMPLES_BYTES = 64 << 20
#: Hands per sample kept from the filter's detections (two hands; more are other people's).
_MAX_HANDS = 4


class SegmentStage:
    """Stage 2 of the pipeline (see the module docstring)."""

    name = "segment"
    version = "1"

    def run(self, item: Item, ctx: StageContext) -> StageResult:
        """Segment ``item`` into ``ctx.out_dir/segments.json`` (and the episode's sidecar).

        Raises:
            ProcessError: the item has no video, or its inputs cannot be read (one line).
        """
        settings = ctx.settings if isinstance(ctx.settings, SegmentSettings) else SegmentSettings()
        record, source = segment_item(item, ctx.upstream, settings, ctx.work_root, ctx.progress)
        if item.kind == "episode" and item.episode_dir is not None and settings.episode_sidecar:
            try:
                existing = read_episode_segments(item.episode_dir)
            except RecordingError as exc:  # a damaged sidecar is replaced; the machine's part is redone
                _log.warning("%s; replacing it", exc)
                existing = None
            record = merge_machine(existing, record)
            write_episode_segments(item.episode_dir, record)
        write_segments(ctx.out_dir / SEGMENTS_FILE, record)
        active = record.active()
        metrics = {
            "seconds_in": record.duration_s,
            "segments": float(len(active)),
            "seconds_segmented": float(round(sum(s.duration_s for s in active), 2)),
        }
        if record.empty:
            return StageResult("empty", (SEGMENTS_FILE,), metrics, f"no action found by {source}")
        return StageResult("ok", (SEGMENTS_FILE,), metrics)


def segment_item(
    item: Item,
    upstream: Mapping[str, Path],
    settings: SegmentSettings,
    work_root: Path,
    progress: Any = None,
) -> tuple[SegmentsRecord, str]:
    """The segments of ``item`` (not written) and the ``source`` of the segmenter that found them.

    Raises:
        ProcessError: no video, unreadable inputs, or the segmenter failed (one line).
    """
    report = progress if callable(progress) else (lambda _f: None)
    if not item.videos:
        raise ProcessError(f"item {item.id} has no video to segment")
    video = Path(item.videos[0])
    info = probe_video(video)
    filtered = _filter_entry(upstream.get("filter"), video)
    episode = None
    segmenter: Segmenter
    if item.kind == "episode" and item.episode_dir is not None:
        from telerig.qa.episode import load_episode

        try:
            episode = load_episode(item.episode_dir)
        except RecordingError as exc:
            raise ProcessError(f"item {item.id}: {exc}") from None
        has_streams = any(
            s in r.streams for r in episode.robots.values() for s in ("joint_state", "gripper_state")
        )
        if not has_streams:
            episode = None
    offset: float | None = None
    if episode is not None:
        segmenter = build_segmenter(settings.robot)
        offset = video_offset_s(episode, video, info)
        inp = SegmentInput(video, info, episode=episode, video_offset_s=offset)
    else:
        segmenter = build_segmenter(settings.video)
        kept, hands, empty = _filter_view(filtered, upstream.get("filter"))
        if empty:
            report(1.0)
            return _record(item, video, work_root, info, [], segmenter), _source(segmenter)
        inp = SegmentInput(video, info, kept=kept, hands=hands)
    proposals = segmenter.segment(inp, report)
    if all(p.label == "idle" for p in proposals):
        proposals = []  # standing still the whole time: no action
    record = _record(item, video, work_root, info, proposals, segmenter)
    if offset is not None:
        record = record.model_copy(update={"video_offset_s": round(offset, 4)})
    return record, _source(segmenter)


def _source(segmenter: Segmenter) -> str:
    return machine_source(segmenter.name, segmenter.version)


def _record(
    item: Item,
    video: Path,
    work_root: Path,
    info: VideoInfo,
    proposals: Sequence[Proposal],
    segmenter: Segmenter,
) -> SegmentsRecord:
    source = _source(segmenter)
    key = f"{item.source_hash}|{Path(video).name}"  # same input, same ids: re-runs change nothing
    segments = []
    for p in proposals:
        start = max(0.0, p.start_s)
        end = min(p.end_s, info.duration_s)
        if not (math.isfinite(start) and math.isfinite(end)) or round(end, 2) <= round(start, 2):
            continue  # shorter than the file's resolution, or out of the video
        segments.append(
            new_segment(p.label, start, end, confidence=p.confidence, source=source, actor=p.actor, key=key)
        )
    segments.sort(key=lambda s: (s.start_s, s.end_s))
    return SegmentsRecord(
        video=_video_name(item, video, work_root),
        duration_s=info.duration_s,
        segments=tuple(segments),
        empty=not segments,
        episode_id=item.id if item.kind == "episode" else None,
    )


def _video_name(item: Item, video: Path, work_root: Path) -> str:
    """The ``video`` of the record: relative to the episode directory for an episode's camera, to the
    processed root for a file inside it, else absolute."""
    for base in (item.episode_dir, work_root):
        if base is None:
            continue
        try:
            return Path(video).resolve().relative_to(Path(base).resolve()).as_posix()
        except ValueError:
            continue
    return str(Path(video).resolve())


def resolve_video(record: SegmentsRecord, item: Item, work_root: Path) -> Path:
    """The file a record's ``video`` names (see :func:`_video_name`).

    Raises:
        ProcessError: it names no existing file.
    """
    name = Path(record.video)
    candidates = [name] if name.is_absolute() else []
    if not name.is_absolute():
        if item.episode_dir is not None:
            candidates.append(Path(item.episode_dir) / name)
        candidates.append(Path(work_root) / name)
    for path in candidates:
        if path.is_file():
            return path
    raise ProcessError(f"segments of item {item.id} name video {record.video!r}, which does not exist")


def video_offset_s(episode: Any, video: Path, info: VideoInfo) -> float:
    """Episode time [s] of the video's first frame: the median difference between the camera's
    recorded frame capture times (``<camera>/frames`` in the log, one per frame, in frame order) and
    the frames' presentation times. 0 when the log has no frame times for this camera."""
    camera = Path(video).stem.split(".")[0]
    for topic, times in episode.capture_times.items():
        parsed = Topic.try_parse(topic)
        if parsed is None or parsed.stream != CAMERA_FRAMES or parsed.node != camera:
            continue
        captured = episode.seconds(times)
        n = min(captured.size, info.frame_times.size)
        if n == 0:
            break
        return float(np.median(captured[:n] - info.frame_times[:n]))
    _log.warning(
        "%s: no recorded frame times for camera %s; assuming it starts with the episode", video, camera
    )
    return 0.0


def _filter_entry(filter_dir: Path | None, video: Path) -> dict[str, Any] | None:
    """The filter stage's ``filter.json`` entry for ``video``; ``None`` when the filter did not run."""
    if filter_dir is None or not (Path(filter_dir) / _FILTER_FILE).is_file():
        return None
    doc = read_json(Path(filter_dir) / _FILTER_FILE, max_bytes=_MAX_FILTER_BYTES, what="a filter record")
    entries = doc.get("videos") if isinstance(doc, dict) else None
    if not isinstance(entries, list):
        raise ProcessError(f"{filter_dir / _FILTER_FILE} has no videos list; re-run the filter stage")
    for entry in entries:
        if isinstance(entry, dict) and Path(str(entry.get("video", ""))).name == video.name:
            return entry
    return None


def _filter_view(
    entry: dict[str, Any] | None, filter_dir: Path | None
) -> tuple[tuple[tuple[float, float], ...] | None, HandTrack | None, bool]:
    """(kept spans or ``None``, hand boxes or ``None``, empty) from a filter entry."""
    if entry is None or filter_dir is None:
        return None, None, False
    if entry.get("empty") is True:
        return (), None, True
    kept: list[tuple[float, float]] = []
    for span in entry.get("kept") or []:
        if (
            isinstance(span, list)
            and len(span) == 2
            and all(isinstance(v, int | float) and math.isfinite(v) for v in span)
            and span[1] > span[0]
        ):
            kept.append((float(span[0]), float(span[1])))
    hands = _hand_track(Path(filter_dir), entry)
    return tuple(kept), hands, False


def _hand_track(filter_dir: Path, entry: dict[str, Any]) -> HandTrack | None:
    """Hand boxes per sample from the filter's ``samples.json``; ``None`` when it has none. Malformed
    samples are counted and left out."""
    name = entry.get("samples_file")
    if not isinstance(name, str) or "/" in name or not (filter_dir / name).is_file():
        return None
    samples = read_json(filter_dir / name, max_bytes=_MAX_SAMPLES_BYTES, what="a filter samples file")
    if not isinstance(samples, list):
        return None
    times: list[float] = []
    boxes: list[list[list[float]]] = []
    bad = 0
    for sample in samples:
        t = sample.get("t") if isinstance(sample, dict) else None
        hands = sample.get("hands") if isinstance(sample, dict) else None
        if not isinstance(t, int | float) or not math.isfinite(t) or not isinstance(hands, list):
            bad += 1
            continue
        row = [[math.nan] * 4 for _ in range(_MAX_HANDS)]
        for k, hand in enumerate(hands[:_MAX_HANDS]):
            box = hand.get("box") if isinstance(hand, dict) else None
            if (
                isinstance(box, list)
                and len(box) == 4
                and all(isinstance(v, int | float) and math.isfinite(v) for v in box)
            ):
                row[k] = [float(v) for v in box]
        times.append(float(t))
        boxes.append(row)
    if bad:
        _log.warning("%s: %d malformed samples left out", filter_dir / name, bad)
    if len(times) < 2:
        return None
    order = np.argsort(times, kind="stable")
    t_arr = np.asarray(times)[order]
    period = float(np.median(np.diff(t_arr))) if t_arr.size > 1 else 0.5
    return HandTrack(t_arr, np.asarray(boxes, dtype=np.float64)[order], max(period, 1e-3))
