"""Stage 2 on real inputs: the demo rig's recorded episodes (robot streams) and generated H.264 video
(motion energy), through the stage as the runner calls it."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from telerig.bus.catalogue import GRIPPER_STATE
from telerig.config.process import SegmentSettings
from telerig.errors import ProcessError
from telerig.process.segment import SegmentStage, video_offset_s
from telerig.process.segmenters import (
    RobotStreamsSegmenter,
    Segmenter,
    SegmentInput,
    build_segmenter,
    probe_video,
)
from telerig.process.stage import Item, StageContext
from telerig.qa.episode import load_episode
from telerig.registry import SEGMENTERS
from telerig.store.episodes import EpisodeStore
from telerig.store.segments_file import (
    SEGMENTS_FILE,
    edit_segment,
    read_episode_segments,
    read_segments,
    write_episode_segments,
)

from .segment_kit import blob_video

MOVING = [(1.0, 3.0), (4.5, 6.0)]


def _ctx(tmp_path: Path, upstream: dict[str, Path] | None = None, settings: object = None) -> StageContext:
    out = tmp_path / "work" / "segment"
    out.mkdir(parents=True, exist_ok=True)
    return StageContext(out, tmp_path / "work", upstream or {}, settings, lambda _f: None)


def _video_item(path: Path) -> Item:
    return Item("video-0123456789ab", "video", (path,), None, "0" * 64, {})


@pytest.fixture(scope="module")
def blob(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return blob_video(tmp_path_factory.mktemp("blob") / "blob.mp4", seconds=7.0, moving=MOVING)


def test_robot_streams_find_the_recorded_grasp(demo_recording: Path, tmp_path: Path) -> None:
    root = tmp_path / "data"
    shutil.copytree(demo_recording, root)
    summaries = EpisodeStore(root).list(include_failures=True)
    assert len(summaries) == 2
    stage = SegmentStage()
    grasped = 0
    for summary in summaries:
        episode_dir = summary.path
        video = episode_dir / "cameras" / "scene.mp4"
        item = Item(summary.id, "episode", (video,), episode_dir, "0" * 64, {})
        ctx = _ctx(tmp_path / summary.id)
        result = stage.run(item, ctx)
        assert result.status in ("ok", "empty"), result.message
        record = read_segments(ctx.out_dir / SEGMENTS_FILE)
        assert record.video == "cameras/scene.mp4"
        assert record.episode_id == summary.id
        assert read_episode_segments(episode_dir) == record  # the sidecar beside the episode
        for seg in record.segments:
            assert seg.status == "proposed"
            assert seg.source == "machine:robot_streams@1"
            assert 0 <= seg.start_s < seg.end_s <= record.duration_s
        # On the episode's own timeline (a loaded host's camera may miss part of the episode): each
        # moment the gripper was recorded closing lies in one grasp segment, and no grasp segment
        # is anywhere else. Closing: the measured opening falling through the middle between open
        # and its most closed (not a fixed level: with the commands stalled for a second on a
        # loaded host, the gripper crept from 1.0 to 0.88 and closed a second later).
        episode = load_episode(episode_dir)
        info = dataclasses.replace(probe_video(video), duration_s=episode.duration_s)
        inp = SegmentInput(video, info, episode=episode)
        proposals = RobotStreamsSegmenter().segment(inp, lambda _f: None)
        gripper = episode.robots["arm0"].streams[GRIPPER_STATE]
        opening = gripper.fields["opening"]
        middle = (opening.max() + opening.min()) / 2
        falls = np.flatnonzero((opening[1:] < middle) & (opening[:-1] >= middle)) + 1
        closes = [float(t) for t in episode.seconds(gripper.time_ns[falls])] if np.ptp(opening) > 0.3 else []
        grasps = [p for p in proposals if p.label == "grasp"]
        shown = [(p.label, round(p.start_s, 2), round(p.end_s, 2)) for p in proposals]
        assert len(grasps) == len(closes), (closes, shown)
        for t_close, grasp in zip(closes, grasps, strict=True):
            assert grasp.start_s - 0.15 <= t_close <= grasp.end_s + 0.05, (t_close, shown)
            assert grasp.confidence >= 0.6
            assert grasp.actor == "arm0"
            labels = [p.label for p in proposals]
            at = labels.index("grasp")
            assert "reach" in labels[:at], shown
            after = labels[at + 1 :]
            holding = after[: after.index("release")] if "release" in after else after
            assert set(holding) <= {"transport", "place", "idle"}, shown  # what it holds it carries
        grasped += len(grasps)
        # The stage's segments are these, moved onto the camera's timeline.
        offset = video_offset_s(episode, video, probe_video(video))
        assert record.video_offset_s == pytest.approx(offset, abs=1e-4)
        in_video = [
            g for g in grasps if g.end_s - offset > 0.05 and g.start_s - offset < record.duration_s - 0.05
        ]
        assert len([s for s in record.segments if s.label == "grasp"]) == len(in_video)
        for g, s in zip(in_video, (s for s in record.segments if s.label == "grasp"), strict=False):
            assert abs(max(g.start_s - offset, 0.0) - s.start_s) <= 0.011
    assert grasped >= 1, "the scripted operator closes the gripper at 2.1-2.6 s of each episode"


def test_a_rerun_keeps_a_persons_review_in_the_episode_sidecar(demo_recording: Path, tmp_path: Path) -> None:
    summary = EpisodeStore(demo_recording).list(include_failures=True)[0]
    episode_dir = tmp_path / summary.id
    shutil.copytree(summary.path, episode_dir)
    item = Item(summary.id, "episode", (episode_dir / "cameras" / "scene.mp4",), episode_dir, "0" * 64, {})
    stage = SegmentStage()
    stage.run(item, _ctx(tmp_path))
    record = read_episode_segments(episode_dir)
    assert record is not None
    assert record.segments, "the scripted operator moves the arm in every episode"
    grasp = record.segments[-1]  # the grasp, on a loaded host maybe only the reach before it
    write_episode_segments(
        episode_dir, edit_segment(record, grasp.id, by="alice", status="corrected", label="pick cube")
    )
    stage.run(item, _ctx(tmp_path))
    again = read_episode_segments(episode_dir)
    assert again is not None
    kept = [s for s in again.segments if s.id == grasp.id]
    assert [(s.label, s.source, s.status) for s in kept] == [("pick cube", "human:alice", "corrected")]
    proposed = [(s.start_s, s.end_s) for s in again.segments if s.source.startswith("machine:")]
    assert (grasp.start_s, grasp.end_s) not in proposed  # the review settled it
    # The same input gives the same proposals with the same ids (the clips keep their names).
    assert {s.id for s in again.segments if s.source.startswith("machine:")} == {
        s.id for s in record.segments if s.id != grasp.id
    }
    # A damaged sidecar is replaced, not fatal.
    (episode_dir / SEGMENTS_FILE).write_text("{garbage")
    assert stage.run(item, _ctx(tmp_path)).status == "ok"
    assert read_episode_segments(episode_dir) is not None


def test_motion_energy_finds_the_moving_spans(blob: Path, tmp_path: Path) -> None:
    ctx = _ctx(tmp_path)
    result = SegmentStage().run(_video_item(blob), ctx)
    assert result.status == "ok"
    record = read_segments(ctx.out_dir / SEGMENTS_FILE)
    assert record.video == str(blob.resolve())
    assert record.duration_s == 7.0
    spans = [(s.label, s.start_s, s.end_s) for s in record.segments]
    assert len(spans) == 2, spans
    for (label, start, end), (a, b) in zip(spans, MOVING, strict=True):
        assert label == "manipulation"
        assert abs(start - a) <= 0.3
        assert abs(end - b) <= 0.3
    assert result.metrics["segments"] == 2
    # Idempotent: a re-run writes the same file, ids included.
    first = (ctx.out_dir / SEGMENTS_FILE).read_bytes()
    SegmentStage().run(_video_item(blob), ctx)
    assert (ctx.out_dir / SEGMENTS_FILE).read_bytes() == first


def test_a_still_video_is_marked_empty(tmp_path: Path) -> None:
    still = blob_video(tmp_path / "still.mp4", seconds=3.0, moving=[])
    ctx = _ctx(tmp_path)
    result = SegmentStage().run(_video_item(still), ctx)
    assert result.status == "empty"
    assert "no action" in result.message
    record = read_segments(ctx.out_dir / SEGMENTS_FILE)
    assert record.empty
    assert record.segments == ()


def _filter_dir(tmp_path: Path, video: Path, *, empty: bool, samples: list[dict[str, object]] | None) -> Path:
    folder = tmp_path / "work" / "filter"
    folder.mkdir(parents=True, exist_ok=True)
    entry: dict[str, object] = {"video": str(video), "kept": [] if empty else [[0.0, 7.0]], "empty": empty}
    if samples is not None:
        (folder / "samples.json").write_text(json.dumps(samples))
        entry["samples_file"] = "samples.json"
    (folder / "filter.json").write_text(json.dumps({"schema": 1, "videos": [entry]}))
    return folder


def test_filter_no_hands_means_no_action(blob: Path, tmp_path: Path) -> None:
    folder = _filter_dir(tmp_path, blob, empty=True, samples=None)
    ctx = _ctx(tmp_path, {"filter": folder})
    assert SegmentStage().run(_video_item(blob), ctx).status == "empty"
    assert read_segments(ctx.out_dir / SEGMENTS_FILE).empty


def test_motion_counts_only_where_the_filter_saw_hands(blob: Path, tmp_path: Path) -> None:
    # Hands seen (around the blob's sweep) at 2 Hz during the first moving span only.
    box = [0.0, 0.3, 1.0, 0.7]
    samples: list[dict[str, object]] = [
        {"t": t / 2, "hands": [{"label": "Right", "score": 0.9, "box": box}] if t / 2 < 3.5 else []}
        for t in range(14)
    ]
    samples.append({"t": "bad"})  # malformed samples are left out
    ctx = _ctx(tmp_path, {"filter": _filter_dir(tmp_path, blob, empty=False, samples=samples)})
    assert SegmentStage().run(_video_item(blob), ctx).status == "ok"
    spans = [(s.start_s, s.end_s) for s in read_segments(ctx.out_dir / SEGMENTS_FILE).segments]
    assert len(spans) == 1, spans
    assert abs(spans[0][0] - 1.0) <= 0.3


def test_hostile_filter_record_is_a_one_line_error(blob: Path, tmp_path: Path) -> None:
    folder = tmp_path / "work" / "filter"
    folder.mkdir(parents=True)
    (folder / "filter.json").write_text("[not json")
    with pytest.raises(ProcessError, match="invalid JSON") as info:
        SegmentStage().run(_video_item(blob), _ctx(tmp_path, {"filter": folder}))
    assert "\n" not in str(info.value)
    (folder / "filter.json").write_text(json.dumps({"videos": 3}))
    with pytest.raises(ProcessError, match="has no videos list"):
        SegmentStage().run(_video_item(blob), _ctx(tmp_path, {"filter": folder}))


def test_not_a_video_is_a_one_line_error(tmp_path: Path) -> None:
    bogus = tmp_path / "bogus.mp4"
    bogus.write_bytes(b"\x00" * 4096)
    with pytest.raises(ProcessError, match="not a readable video") as info:
        SegmentStage().run(_video_item(bogus), _ctx(tmp_path))
    assert "\n" not in str(info.value)


def test_segmenters_are_registered_plugins() -> None:
    assert {"robot_streams", "motion_energy"} <= set(SEGMENTERS.names())
    settings = SegmentSettings.model_validate({"video": {"type": "motion_energy", "threshold": 0.2}})
    segmenter = build_segmenter(settings.video)
    assert isinstance(segmenter, Segmenter)
    assert segmenter.name == "motion_energy"
    with pytest.raises(
        ValueError, match=r"video\.type: unknown segmenter type 'opentad'\. Valid: motion_energy"
    ):
        SegmentSettings.model_validate({"video": {"type": "opentad"}})
    with pytest.raises(ValueError, match=r"speed_off_m_s 0\.5 is above speed_on_m_s"):
        SegmentSettings.model_validate({"robot": {"type": "robot_streams", "speed_off_m_s": 0.5}})


def test_garbage_values_in_recorded_streams_do_not_break_segmentation(demo_recording: Path) -> None:
    """NaN, infinite and absurd values in a real episode's streams (a faulty driver): the segmenter
    still answers, with finite spans inside the video, and the grasp outside the damage is found."""
    summary = EpisodeStore(demo_recording).list(include_failures=True)[0]
    episode = load_episode(summary.path)
    robot = episode.robots["arm0"]
    streams = dict(robot.streams)
    joints = streams["joint_state"]
    q = joints.fields["positions"].copy()
    q[: q.shape[0] // 5] = np.nan  # the first fifth of the joint states unreadable
    q[q.shape[0] // 5, 0] = 1e300
    streams["joint_state"] = dataclasses.replace(joints, fields={**joints.fields, "positions": q})
    wrench = streams["wrench"]
    force = wrench.fields["force"].copy()
    force[::7] = np.inf
    force[3::7] = -1e30
    streams["wrench"] = dataclasses.replace(wrench, fields={**wrench.fields, "force": force})
    gripper = streams[GRIPPER_STATE]
    opening = gripper.fields["opening"].copy()
    opening[:5] = np.nan
    opening[5:10] = 7.0  # out of range: clipped to open
    streams[GRIPPER_STATE] = dataclasses.replace(gripper, fields={**gripper.fields, "opening": opening})
    damaged = dataclasses.replace(episode, robots={"arm0": dataclasses.replace(robot, streams=streams)})
    video = summary.path / "cameras" / "scene.mp4"
    info = dataclasses.replace(probe_video(video), duration_s=episode.duration_s)
    proposals = RobotStreamsSegmenter().segment(SegmentInput(video, info, episode=damaged), lambda _f: None)
    assert proposals
    for p in proposals:
        assert np.isfinite([p.start_s, p.end_s, p.confidence]).all()
        assert 0 <= p.start_s < p.end_s <= episode.duration_s
        assert 0 <= p.confidence <= 1
    clean = RobotStreamsSegmenter().segment(SegmentInput(video, info, episode=episode), lambda _f: None)
    grasps = [(round(p.start_s, 2), round(p.end_s, 2)) for p in clean if p.label == "grasp"]
    assert grasps == [(round(p.start_s, 2), round(p.end_s, 2)) for p in proposals if p.label == "grasp"]
