"""Stage 3, clip extraction: each segment becomes its own MP4, named by the segment's UUID.

How a clip is cut (``method`` in ``clips.json``, with the ``reason``):

* ``copy``: the segment starts at most ``keyframe_tolerance_s`` after a keyframe. The packets from
  that keyframe to the segment's end are copied as they are (no re-encode: the original encoding,
  bit for bit, and fast); the clip starts up to the tolerance early. Its end is exact to the frame
  (a source with B-frames may carry the few frames that later-shown frames before the end need).
* ``reencode``: the nearest keyframe before the start is farther. The whole clip is decoded from
  that keyframe and re-encoded (libx264, ``crf``/``preset``) from the frame on screen at the
  segment's start (a variable-rate recording may show one frame through a whole short segment). Why the
  whole clip and not only the head up to the next keyframe: an MP4 track has one set of codec
  parameters (H.264 SPS/PPS in ``avcC``), and a freshly encoded head's never equals the source's,
  so a re-encoded head followed by copied packets does not decode as one stream.

Every clip is decoded again after writing (``verify``): every frame must decode, and its duration
must match the span it was cut for within one frame (the largest frame interval of the source in
that span, for variable-rate recordings). Output: ``<uuid>.mp4`` per clip and ``clips.json``: a list
of ``{uuid, video, start_s, end_s, file, label, method, ...}`` where ``start_s``/``end_s`` are the
span the file holds on the source video's timeline and ``segment`` the segment's own span; for an
episode also ``episode_start_s``/``episode_end_s``, the same span in episode time (seconds from the
manifest's start, the recorded streams' timeline).
"""

from __future__ import annotations

import contextlib
import logging
import os
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any, Literal

import numpy as np

from telerig.config.process import ClipSettings
from telerig.errors import ProcessError, RecordingError
from telerig.process.segment import resolve_video
from telerig.process.segmenters import VideoInfo, probe_video
from telerig.process.stage import Item, StageContext, StageResult, write_json_atomic
from telerig.store.segments_file import SEGMENTS_FILE, Segment, read_segments

__all__ = ["CLIPS_FILE", "Clip", "ClipsStage", "cut_clip", "plan_cut", "verify_clip"]

_log = logging.getLogger("telerig.process.clips")

CLIPS_FILE = "clips.json"
#: Clip timestamps are in microseconds (as telerig's camera recordings).
_TIME_BASE = Fraction(1, 1_000_000)
#: Slack on time comparisons [s]: timestamps are integers in the stream's time base.
_EPS = 1e-4

Method = Literal["copy", "reencode"]


@dataclass(frozen=True, slots=True)
class Plan:
    """How one segment will be cut.

    Attributes:
        method: ``copy`` or ``reencode``.
        start_s: Where the clip starts on the source timeline [s] (a keyframe for ``copy``).
        end_s: Where it ends [s].
        reason: One line: why this method.
    """

    method: Method
    start_s: float
    end_s: float
    reason: str


@dataclass(frozen=True, slots=True)
class Clip:
    """A written and verified clip.

    Attributes:
        path: The file.
        method: How it was cut.
        start_s: Its first frame's time on the source timeline [s].
        end_s: The end of its last frame on the source timeline [s].
        frames: Frames it decodes to.
        duration_s: Its own duration, first frame to the end of the last [s].
        reason: Why the method.
    """

    path: Path
    method: Method
    start_s: float
    end_s: float
    frames: int
    duration_s: float
    reason: str


def plan_cut(info: VideoInfo, start_s: float, end_s: float, tolerance_s: float) -> Plan:
    """Copy from the keyframe at or before ``start_s`` when it is within ``tolerance_s``; else re-encode.

    Raises:
        ProcessError: the span is empty or outside the video.
    """
    start_s = max(0.0, start_s)
    end_s = min(end_s, info.duration_s)
    if end_s - start_s <= _EPS:
        raise ProcessError(f"{info.path}: span {start_s:.2f}-{end_s:.2f} s holds no frame of the video")
    before = info.keyframes[info.keyframes <= start_s + _EPS]
    if before.size:
        key = float(before[-1])
        lead = start_s - key
        if lead <= tolerance_s + _EPS:
            why = f"keyframe {lead:.2f} s before the start (tolerance {tolerance_s:g} s): stream copy"
            return Plan("copy", key, end_s, why)
        why = (
            f"nearest keyframe {lead:.2f} s before the start (> {tolerance_s:g} s tolerance); whole clip "
            "re-encoded (a re-encoded head cannot share one MP4 track's codec parameters with copied packets)"
        )
    else:
        why = "no keyframe before the start; whole clip re-encoded"
    # From the frame on screen at the start (the last one shown at or before it): a variable-rate
    # recording may have no frame inside a short segment at all, yet one is showing throughout.
    shown = info.frame_times[info.frame_times <= start_s + _EPS]
    return Plan("reencode", float(shown[-1]) if shown.size else start_s, end_s, why)


def cut_clip(info: VideoInfo, plan: Plan, dest: Path, settings: ClipSettings) -> Clip:
    """Write ``plan``'s clip of ``info.path`` to ``dest`` (temp file, then rename) and verify it.

    Raises:
        ProcessError: the source does not decode, the clip could not be written, or it failed
            verification (one line; no partial file is left).
    """
    import av

    dest = Path(dest)
    tmp = dest.with_name(f".{dest.name}.tmp")
    try:
        if plan.method == "copy":
            _copy(info, plan, tmp)
        else:
            _reencode(info, plan, tmp, settings)
        if settings.verify:
            frames, first, duration = verify_clip(tmp)
            _check_duration(info, plan, frames, duration)
        else:
            frames, first, duration = 0, 0.0, plan.end_s - plan.start_s
        os.replace(tmp, dest)
    except av.FFmpegError as exc:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise ProcessError(
            f"cutting {info.path} at {plan.start_s:.2f}-{plan.end_s:.2f} s failed: {exc}"
        ) from None
    except (ProcessError, OSError) as exc:
        with contextlib.suppress(OSError):
            tmp.unlink()
        if isinstance(exc, OSError):
            raise ProcessError(f"cannot write {dest}: {exc.strerror or exc}") from None
        raise
    start = plan.start_s + first
    return Clip(dest, plan.method, round(start, 4), round(start + duration, 4), frames, duration, plan.reason)


def _copy(info: VideoInfo, plan: Plan, tmp: Path) -> None:
    """Packets from the keyframe at ``plan.start_s`` while their decode time is before the end."""
    import av

    start_pts, end_pts = info.pts(plan.start_s), info.pts(plan.end_s)
    with av.open(str(info.path)) as src, av.open(str(tmp), mode="w", format="mp4") as out:
        ist = src.streams.video[0]
        ost = out.add_stream_from_template(ist)
        src.seek(start_pts, stream=ist, backward=True, any_frame=False)
        started = False
        offset = 0
        written = 0
        for packet in src.demux(ist):
            if packet.pts is None or packet.size == 0:
                continue
            if not started:
                if not (packet.is_keyframe and packet.pts >= start_pts - 1):
                    continue  # the seek landed on an earlier keyframe: skip to ours
                started = True
                offset = min(packet.pts, packet.dts if packet.dts is not None else packet.pts)
            decode = packet.dts if packet.dts is not None else packet.pts
            if decode >= end_pts or (not info.b_frames and packet.pts >= end_pts):
                break
            packet.pts -= offset
            if packet.dts is not None:
                packet.dts -= offset
            packet.stream = ost
            out.mux(packet)
            written += 1
        if written == 0:
            raise ProcessError(f"{info.path}: no packet from the keyframe at {plan.start_s:.2f} s on")


def _reencode(info: VideoInfo, plan: Plan, tmp: Path, settings: ClipSettings) -> None:
    """Decode from the keyframe before ``plan.start_s``; encode the frames in ``[start, end)``."""
    import av

    start_pts = info.pts(plan.start_s)
    width, height = info.width // 2 * 2, info.height // 2 * 2  # yuv420p needs even sides
    encoded = 0
    with av.open(str(info.path)) as src, av.open(str(tmp), mode="w", format="mp4") as out:
        ist = src.streams.video[0]
        ist.thread_type = "AUTO"
        ost: Any = out.add_stream(
            "libx264",
            rate=Fraction(info.fps).limit_denominator(1001),
            options={"crf": str(settings.crf), "preset": settings.preset},
        )
        ost.width, ost.height, ost.pix_fmt = width, height, "yuv420p"
        ost.time_base = _TIME_BASE
        ost.codec_context.time_base = _TIME_BASE
        src.seek(start_pts, stream=ist, backward=True, any_frame=False)
        for frame in src.decode(ist):
            if frame.pts is None:
                continue
            t = (frame.pts - info.start_pts) * info.time_base
            if t < plan.start_s - _EPS:
                continue
            if t >= plan.end_s - _EPS:
                break
            image = frame.reformat(width=width, height=height, format="yuv420p")
            image.pts = round((t - plan.start_s) / float(_TIME_BASE))
            image.time_base = _TIME_BASE
            image.pict_type = av.video.frame.PictureType.NONE
            for packet in ost.encode(image):
                out.mux(packet)
            encoded += 1
        for packet in ost.encode(None):
            out.mux(packet)
    if encoded == 0:
        raise ProcessError(f"{info.path}: no frame in {plan.start_s:.2f}-{plan.end_s:.2f} s to encode")


def verify_clip(path: Path) -> tuple[int, float, float]:
    """Decode every frame of a clip: ``(frames, first frame time [s], duration [s])``, the duration
    from the first frame to the end of the last (the last lasting the median frame interval).

    Raises:
        ProcessError: it does not open or a frame does not decode, or it has no frame.
    """
    import av

    times: list[float] = []
    try:
        with av.open(str(path)) as container:
            stream = container.streams.video[0]
            tb = float(stream.time_base) if stream.time_base else 1e-6
            for frame in container.decode(stream):
                if frame.pts is not None:
                    times.append(frame.pts * tb)
    except av.FFmpegError as exc:
        raise ProcessError(f"clip {path.name} does not decode: {exc}") from None
    if not times:
        raise ProcessError(f"clip {path.name} has no frames")
    t = np.sort(np.asarray(times))
    step = float(np.median(np.diff(t))) if t.size > 1 else 0.0
    return t.size, float(t[0]), float(t[-1] - t[0] + step)


def _check_duration(info: VideoInfo, plan: Plan, frames: int, duration: float) -> None:
    """A clip's duration must match its span within one frame (the largest frame interval of the
    source in the span); a copied clip of a source with B-frames within one keyframe interval."""
    times = info.frame_times
    inside = times[(times >= plan.start_s - _EPS) & (times < plan.end_s - _EPS)]
    expected_frames = inside.size
    gaps = np.diff(times[(times >= plan.start_s - 1.0) & (times <= plan.end_s + 1.0)])
    slack = float(gaps.max()) if gaps.size else 1.0 / info.fps
    if plan.method == "copy" and info.b_frames and info.keyframes.size > 1:
        slack = max(slack, float(np.max(np.diff(info.keyframes))))
    want = plan.end_s - plan.start_s
    if abs(duration - want) > slack + 1e-3:
        raise ProcessError(
            f"clip of {info.path.name} at {plan.start_s:.2f}-{plan.end_s:.2f} s lasts {duration:.3f} s, "
            f"not {want:.3f} s within one frame ({slack:.3f} s)"
        )
    if frames < expected_frames and not (plan.method == "copy" and info.b_frames):
        raise ProcessError(
            f"clip of {info.path.name} at {plan.start_s:.2f}-{plan.end_s:.2f} s decodes {frames} frames "
            f"of the {expected_frames} the source has there"
        )


class ClipsStage:
    """Stage 3 of the pipeline (see the module docstring)."""

    name = "clips"
    version = "1"

    def run(self, item: Item, ctx: StageContext) -> StageResult:
        """Cut every (not rejected) segment of the segment stage's ``segments.json`` into a clip.

        Raises:
            ProcessError: the segment stage's output is missing or invalid, or the source video is
                unreadable (one line). A clip that fails is left out and counted; all failing fails.
        """
        settings = ctx.settings if isinstance(ctx.settings, ClipSettings) else ClipSettings()
        seg_dir = ctx.upstream.get("segment")
        if seg_dir is None:
            raise ProcessError(f"item {item.id}: clips need the segment stage's output; run it first")
        try:
            record = read_segments(Path(seg_dir) / SEGMENTS_FILE)
        except RecordingError as exc:
            raise ProcessError(str(exc)) from None
        wanted = [s for s in record.segments if settings.include_rejected or s.status != "rejected"]
        wanted = [
            s
            for s in wanted
            if s.duration_s >= settings.min_clip_s - 1e-6 and s.label not in settings.skip_labels
        ]
        entries: list[dict[str, Any]] = []
        failures: list[str] = []
        metrics: dict[str, float] = {
            "clips": 0.0,
            "copied": 0.0,
            "reencoded": 0.0,
            "failed": 0.0,
            "seconds": 0.0,
        }
        if not wanted:
            write_json_atomic(ctx.out_dir / CLIPS_FILE, [])
            ctx.progress(1.0)
            why = (
                "the video has no action"
                if record.empty
                else "no segment to cut (too short, skipped or rejected)"
            )
            return StageResult("empty", (CLIPS_FILE,), metrics, why)
        video = resolve_video(record, item, ctx.work_root)
        info = probe_video(video)
        for k, seg in enumerate(wanted):
            try:
                entry = self._one(info, seg, record.video, ctx.out_dir, settings)
                if record.video_offset_s is not None:  # the span on the episode's streams' timeline
                    entry["episode_start_s"] = round(entry["start_s"] + record.video_offset_s, 3)
                    entry["episode_end_s"] = round(entry["end_s"] + record.video_offset_s, 3)
                entries.append(entry)
            except ProcessError as exc:
                failures.append(str(exc))
                _log.warning("%s", exc)
            ctx.progress((k + 1) / len(wanted))
        entries.sort(key=lambda e: (e["segment"][0], e["uuid"]))
        write_json_atomic(ctx.out_dir / CLIPS_FILE, entries)
        metrics.update(
            clips=float(len(entries)),
            copied=float(sum(e["method"] == "copy" for e in entries)),
            reencoded=float(sum(e["method"] == "reencode" for e in entries)),
            failed=float(len(failures)),
            seconds=round(sum(e["end_s"] - e["start_s"] for e in entries), 3),
        )
        outputs = (CLIPS_FILE, *(e["file"] for e in entries))
        if failures and not entries:
            return StageResult("failed", outputs, metrics, f"no clip could be cut: {failures[0]}")
        message = f"{len(failures)} of {len(wanted)} clips failed: {failures[0]}" if failures else ""
        return StageResult("ok", outputs, metrics, message)

    def _one(
        self, info: VideoInfo, seg: Segment, video: str, out_dir: Path, settings: ClipSettings
    ) -> dict[str, Any]:
        plan = plan_cut(info, seg.start_s, seg.end_s, settings.keyframe_tolerance_s)
        name = f"{seg.id}.mp4"
        clip = cut_clip(info, plan, out_dir / name, settings)
        return {
            "uuid": seg.id,
            "video": video,
            "start_s": round(clip.start_s, 3),
            "end_s": round(clip.end_s, 3),
            "segment": [seg.start_s, seg.end_s],
            "file": name,
            "label": seg.label,
            "confidence": seg.confidence,
            "status": seg.status,
            "source": seg.source,
            "actor": seg.actor,
            "method": clip.method,
            "reason": clip.reason,
            "frames": clip.frames,
            "duration_s": round(clip.duration_s, 3),
            "fps": round(info.fps, 3),
            "width": info.width // 2 * 2 if clip.method == "reencode" else info.width,
            "height": info.height // 2 * 2 if clip.method == "reencode" else info.height,
        }
