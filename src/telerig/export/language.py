"""Per-frame subtask labels and language instructions from an episode's segments.

The annotation pipeline (``telerig process``) and reviewers leave ``segments.json`` beside an
episode's files (:mod:`telerig.store.segments_file`) and, where clips were described,
``segment_annotations.json`` (:mod:`telerig.store.annotations_file`). Every export labels each
dataset frame with the segment active at its time:

- ``subtask``: the segment's label (``grasp``); ``""`` where no segment covers the frame;
- ``instruction``: the segment's description (the vision-language model's action description),
  else ``"<label>: <task>"``; the episode's task where no segment covers the frame.

Rejected segments are left out. Where segments overlap, a person's (accepted or corrected, or a
``human:`` source) wins over a machine proposal, then the more confident, then the later start.

Segment times are on the camera video's timeline; a frame's video time is its episode time
(from ``manifest.start_ns``) minus the record's ``video_offset_s``. Records written without the
offset take it from the recorded capture times of that camera's frames used at the grid.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from telerig.errors import ExportError, RecordingError
from telerig.store.annotations_file import EpisodeAnnotations, read_episode_annotations
from telerig.store.segments_file import Segment, SegmentsRecord, read_episode_segments

__all__ = ["FrameLanguage", "frame_language", "read_segments_of"]

_REVIEWED = ("accepted", "corrected")


@dataclass(frozen=True, slots=True)
class FrameLanguage:
    """The language of every frame of one exported episode.

    Attributes:
        segments: The segments used (rejected ones left out), sorted by start; times [s] on the
            video's timeline as in the file.
        subtask: Per frame, the active segment's label; ``""`` where none is active. Length F.
        instruction: Per frame, the active segment's description (else ``label: task``); the
            episode's task where none is active. Length F.
        segment_index: Per frame, the index in ``segments`` of the active segment, -1 where none.
        video_time_s: Per frame, its time on the segments' video timeline [s].
        descriptions: Segment id → description, for the segments the annotator described.
    """

    segments: tuple[Segment, ...]
    subtask: tuple[str, ...]
    instruction: tuple[str, ...]
    segment_index: npt.NDArray[np.int64]
    video_time_s: npt.NDArray[np.float64]
    descriptions: Mapping[str, str]


def read_segments_of(episode_dir: Path) -> tuple[SegmentsRecord | None, EpisodeAnnotations | None]:
    """The episode's segments and segment annotations sidecars (``None`` where absent).

    Raises:
        ExportError: a sidecar is unreadable or invalid (one line naming the file and the fix). A
            damaged label file stops the export rather than leaving the labels out silently: a
            dataset missing its subtasks looks complete and trains a different policy.
    """
    try:
        record = read_episode_segments(Path(episode_dir))
        notes = read_episode_annotations(Path(episode_dir)) if record is not None else None
    except RecordingError as exc:
        raise ExportError(str(exc)) from None
    return record, notes


def _priority(seg: Segment) -> tuple[int, float, float]:
    human = seg.status in _REVIEWED or seg.source.startswith("human:")
    return (1 if human else 0, seg.confidence, seg.start_s)


def _offset_s(
    record: SegmentsRecord,
    start_ns: int,
    source_index: Mapping[str, npt.NDArray[np.int64]],
    raw_time_ns: Mapping[str, npt.NDArray[np.int64]],
    camera_fps: Mapping[str, int],
) -> float:
    """Episode time [s] of the video's first frame."""
    if record.video_offset_s is not None:
        return record.video_offset_s
    camera = Path(record.video).stem.split(".")[0]
    idx = source_index.get(camera)
    raw = raw_time_ns.get(f"{camera}/frames")
    fps = camera_fps.get(camera)
    if idx is None or raw is None or not fps:
        return 0.0
    ok = raw >= 0
    if not ok.any():
        return 0.0
    return float(np.median((raw[ok] - start_ns) / 1e9 - idx[ok] / fps))


def frame_language(
    record: SegmentsRecord,
    notes: EpisodeAnnotations | None,
    *,
    task: str,
    frame_ns: npt.NDArray[np.int64],
    start_ns: int,
    source_index: Mapping[str, npt.NDArray[np.int64]],
    raw_time_ns: Mapping[str, npt.NDArray[np.int64]],
    camera_fps: Mapping[str, int],
) -> FrameLanguage:
    """Label each frame at ``frame_ns`` (common clock [ns]) with the segment active at its time.

    Args:
        record: The episode's segments.
        notes: Its segment descriptions, or ``None``.
        task: The episode's task (the instruction where no segment is active).
        frame_ns: The dataset frames' grid times [ns]. Shape (F,).
        start_ns: The episode's start (``manifest.start_ns``) [ns].
        source_index: Camera key → index of the recorded video frame used at each dataset frame.
        raw_time_ns: Source (``front/frames``) → capture time of the sample used [ns].
        camera_fps: Camera key → its frame rate [Hz].
    """
    segments = tuple(sorted(record.active(), key=lambda s: (s.start_s, s.end_s, s.id)))
    offset = _offset_s(record, start_ns, source_index, raw_time_ns, camera_fps)
    video_t = (frame_ns - start_ns) / 1e9 - offset
    index = np.full(frame_ns.size, -1, dtype=np.int64)
    order = sorted(range(len(segments)), key=lambda i: _priority(segments[i]))
    for i in order:  # lowest priority first: the winner paints last
        seg = segments[i]
        index[(video_t >= seg.start_s) & (video_t < seg.end_s)] = i
    known = {s.id for s in segments}
    given = {} if notes is None else notes.segments
    descriptions = {k: v.description for k, v in given.items() if k in known}
    labels = [s.label for s in segments]
    sentences = [descriptions.get(s.id) or f"{s.label}: {task}" for s in segments]
    subtask = tuple("" if i < 0 else labels[i] for i in index.tolist())
    instruction = tuple(task if i < 0 else sentences[i] for i in index.tolist())
    return FrameLanguage(segments, subtask, instruction, index, video_t, descriptions)
