"""Stage 3 on real H.264: stream copy where a keyframe is near the start, a re-encode elsewhere, every
clip decoded and its duration and first picture checked against the source."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import av
import numpy as np
import pytest

from telerig.config.process import ClipSettings
from telerig.errors import ProcessError
from telerig.process.clips import CLIPS_FILE, ClipsStage, verify_clip
from telerig.process.segment import SegmentStage
from telerig.process.stage import Item, StageContext
from telerig.store.episodes import EpisodeStore
from telerig.store.segments_file import (
    SEGMENTS_FILE,
    SegmentsRecord,
    edit_segment,
    machine_source,
    new_segment,
    read_segments,
    write_segments,
)

from .segment_kit import blob_video

SOURCE = machine_source("motion_energy", "1")
FPS = 30


@pytest.fixture(scope="module")
def source(tmp_path_factory: pytest.TempPathFactory) -> Path:
    # Keyframes every 1 s (30 frames), no B-frames; the blob moves throughout so frames differ.
    return blob_video(tmp_path_factory.mktemp("clips") / "src.mp4", seconds=6.0, moving=[(0.0, 6.0)])


def _run(
    tmp_path: Path,
    video: Path,
    spans: list[tuple[float, float]],
    *,
    reject: int | None = None,
    label: str = "manipulation",
) -> tuple[list[dict[str, object]], SegmentsRecord, StageContext]:
    segments = tuple(new_segment(label, a, b, confidence=0.7, source=SOURCE) for a, b in spans)
    record = SegmentsRecord(video=str(video), duration_s=6.0, segments=segments, empty=not segments)
    if reject is not None:
        record = edit_segment(record, segments[reject].id, by="alice", status="rejected")
    seg_dir = tmp_path / "segment"
    seg_dir.mkdir(exist_ok=True)
    write_segments(seg_dir / SEGMENTS_FILE, record)
    out = tmp_path / "clips"
    out.mkdir(exist_ok=True)
    ctx = StageContext(out, tmp_path, {"segment": seg_dir}, ClipSettings(), lambda _f: None)
    item = Item("video-0123456789ab", "video", (video,), None, "0" * 64, {})
    result = ClipsStage().run(item, ctx)
    assert result.status in ("ok", "empty"), result.message
    assert result.outputs[0] == CLIPS_FILE
    return json.loads((out / CLIPS_FILE).read_text()), record, ctx


def _frame(path: Path, t: float | None = None) -> np.ndarray:
    """The frame shown at ``t`` [s] from the file's first frame (``None``: the first frame), grey."""
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        first = None
        for frame in container.decode(stream):
            assert frame.pts is not None
            first = frame.pts if first is None else first
            if t is None or float((frame.pts - first) * stream.time_base) >= t - 1e-3:
                image: np.ndarray = frame.to_ndarray(format="gray").astype(np.float32)
                return image
    raise AssertionError(f"{path} has no frame at {t}")


def test_copy_near_a_keyframe_and_reencode_elsewhere(source: Path, tmp_path: Path) -> None:
    clips, record, ctx = _run(tmp_path, source, [(2.1, 3.5), (3.7, 5.2), (0.5, 1.5)], reject=2)
    kept = sorted((s.start_s, s.id) for s in record.segments if s.status != "rejected")
    assert [c["uuid"] for c in clips] == [i for _, i in kept]  # the rejected one is left out
    copy, reencode = clips
    assert copy["method"] == "copy"
    assert "0.10 s before the start" in str(copy["reason"])
    assert (copy["start_s"], copy["segment"]) == (2.0, [2.1, 3.5])  # from the keyframe at 2.0 s
    assert reencode["method"] == "reencode"
    assert "0.70 s before the start (> 0.5 s tolerance); whole clip re-encoded" in str(reencode["reason"])
    for clip, (start, end) in ((copy, (2.0, 3.5)), (reencode, (3.7, 5.2))):
        path = ctx.out_dir / str(clip["file"])
        assert path.name == f"{clip['uuid']}.mp4"
        frames, _first, duration = verify_clip(path)
        assert abs(duration - (end - start)) <= 1 / FPS + 1e-3
        assert frames == round((end - start) * FPS)
        # Its first picture is the source's at the clip's start (a cut in the right place).
        assert np.mean(np.abs(_frame(path) - _frame(source, start))) < 3.0
        assert np.mean(np.abs(_frame(path) - _frame(source, start + 0.3))) > 3.0  # the blob moved
    with av.open(str(ctx.out_dir / str(copy["file"]))) as c, av.open(str(source)) as s:
        assert c.streams.video[0].codec_context.extradata == s.streams.video[0].codec_context.extradata


def test_copy_of_a_source_with_b_frames_decodes(tmp_path: Path) -> None:
    video = blob_video(tmp_path / "b.mp4", seconds=4.0, moving=[(0.0, 4.0)], b_frames=2)
    clips, _record, ctx = _run(tmp_path, video, [(1.05, 2.5)])
    assert clips[0]["method"] == "copy"
    frames, _first, duration = verify_clip(ctx.out_dir / str(clips[0]["file"]))
    assert frames >= round(1.5 * FPS)
    assert 1.5 - 1e-3 <= duration <= 1.5 + 1.0  # within one keyframe interval of its span


def test_no_segments_no_clips(source: Path, tmp_path: Path) -> None:
    clips, _record, _ctx = _run(tmp_path, source, [])
    assert clips == []
    clips, _record, _ctx = _run(tmp_path, source, [(1.0, 3.0)], label="idle")  # nothing happens in it
    assert clips == []


def test_hostile_segments_file_is_a_one_line_error(source: Path, tmp_path: Path) -> None:
    seg_dir = tmp_path / "segment"
    seg_dir.mkdir()
    out = tmp_path / "clips"
    out.mkdir()
    item = Item("video-0123456789ab", "video", (source,), None, "0" * 64, {})
    ctx = StageContext(out, tmp_path, {"segment": seg_dir}, ClipSettings(), lambda _f: None)
    for text in ("{garbage", json.dumps({"schema": 1, "video": "x", "duration_s": -1, "segments": []})):
        (seg_dir / SEGMENTS_FILE).write_text(text)
        with pytest.raises(ProcessError, match="is not a segments file") as info:
            ClipsStage().run(item, ctx)
        assert "\n" not in str(info.value)
    write_segments(
        seg_dir / SEGMENTS_FILE,
        SegmentsRecord(
            video="gone.mp4",
            duration_s=6,
            segments=(new_segment("manipulation", 1, 2, confidence=1, source=SOURCE),),
        ),
    )
    with pytest.raises(ProcessError, match=r"'gone\.mp4', which does not exist"):
        ClipsStage().run(item, ctx)
    with pytest.raises(ProcessError, match="run it first"):
        ClipsStage().run(item, StageContext(out, tmp_path, {}, None, lambda _f: None))


def test_clips_of_a_recorded_episode(demo_recording: Path, tmp_path: Path) -> None:
    """The recorder's camera file (fragmented MP4, variable frame rate on a loaded host) cut along
    the robot streams' segments: every clip decodes, and its episode span is its video span moved
    by the camera's start."""
    summary = EpisodeStore(demo_recording).list(include_failures=True)[0]
    episode_dir = tmp_path / summary.id
    shutil.copytree(summary.path, episode_dir)
    item = Item(summary.id, "episode", (episode_dir / "cameras" / "scene.mp4",), episode_dir, "0" * 64, {})
    seg_dir, out = tmp_path / "segment", tmp_path / "clips"
    seg_dir.mkdir()
    out.mkdir()
    SegmentStage().run(item, StageContext(seg_dir, tmp_path, {}, None, lambda _f: None))
    record = read_segments(seg_dir / SEGMENTS_FILE)
    result = ClipsStage().run(item, StageContext(out, tmp_path, {"segment": seg_dir}, None, lambda _f: None))
    clips = json.loads((out / CLIPS_FILE).read_text())
    # The stage keeps segments of at least min_clip_s (0.2 s) within 1e-6 s: a segment the
    # segmenter cut to 0.19999999 s gets its clip.
    wanted = [s for s in record.segments if s.label != "idle" and s.duration_s >= 0.2 - 1e-6]
    assert result.status == ("ok" if wanted else "empty"), result.message
    assert result.metrics["failed"] == 0, result.message
    assert sorted(c["uuid"] for c in clips) == sorted(s.id for s in wanted)
    assert record.video_offset_s is not None
    for clip in clips:
        frames, _first, _duration = verify_clip(out / clip["file"])
        assert frames == clip["frames"] >= 1
        assert clip["method"] in ("copy", "reencode")
        assert clip["episode_start_s"] == pytest.approx(clip["start_s"] + record.video_offset_s, abs=2e-3)
        assert clip["video"] == "cameras/scene.mp4"
