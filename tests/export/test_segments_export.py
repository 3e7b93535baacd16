"""Segments (issue 15) in every export: a real demo episode with a ``segments.json`` sidecar written
through :mod:`telerig.store.segments_file`, exported to LeRobot v3, HDF5, robomimic and RLDS, each
read back and checked frame by frame against the segments' spans."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pyarrow.parquet as pq
import pytest

from telerig.cli.main import main
from telerig.errors import ExportError
from telerig.export import EpisodeFilter, export
from telerig.export.frames import EpisodeFrames, load_episode
from telerig.export.rlds import dataset_dir, read_episodes
from telerig.store.annotations_file import (
    EpisodeAnnotations,
    SegmentAnnotation,
    write_episode_annotations,
)
from telerig.store.episodes import EpisodeStore
from telerig.store.segments_file import (
    SEGMENTS_FILE,
    SegmentsRecord,
    edit_segment,
    machine_source,
    new_segment,
    write_episode_segments,
)

GRASP_SENTENCE = "The robot arm closes its gripper around the red cube."
ALL = EpisodeFilter(include_failures=True)


def _offset_s(frames: EpisodeFrames) -> float:
    """Episode time [s] of the scene video's first frame, from the recorded capture times."""
    track = frames.cameras["scene"]
    raw = frames.raw_time_ns["scene/frames"]
    return float(np.median((raw - frames.manifest.start_ns) / 1e9 - track.source_index / track.spec.fps))


@pytest.fixture(scope="module")
def root(demo_recording: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A copy of the demo recording; its first episode carries segments and one description."""
    data = tmp_path_factory.mktemp("segments") / "data"
    shutil.copytree(demo_recording, data)
    return data


@pytest.fixture(scope="module")
def labelled(root: Path) -> tuple[Path, float]:
    """(the segmented episode's directory, its scene video offset [s])."""
    episodes = sorted(EpisodeStore(root).list(include_failures=True), key=lambda e: e.id)
    ep = episodes[0].path
    offset = _offset_s(load_episode(ep))
    src = machine_source("robot_streams", "1")
    segs = [
        new_segment("reach", 0.5, 1.5, confidence=0.5, source=src, key="k"),
        new_segment("wrong", 1.0, 2.3, confidence=0.9, source=src, key="k"),
        new_segment("grasp", 1.5, 2.5, confidence=0.4, source=src, key="k"),
        new_segment("transport", 2.5, 3.5, confidence=0.95, source=src, key="k"),
    ]
    record = SegmentsRecord(
        video="cameras/scene.mp4",
        duration_s=4.0,
        segments=tuple(segs),
        episode_id=ep.name,
        video_offset_s=offset,
    )
    record = edit_segment(record, segs[2].id, by="ana", status="accepted")  # a person's: wins over "wrong"
    record = edit_segment(record, segs[3].id, by="ana", status="rejected")  # left out everywhere
    write_episode_segments(ep, record)
    notes = EpisodeAnnotations(
        episode_id=ep.name, segments={segs[2].id: SegmentAnnotation(description=GRASP_SENTENCE, model="qwen")}
    )
    write_episode_annotations(ep, notes)
    return ep, offset


def _expected(frames: EpisodeFrames, offset: float) -> tuple[list[str], list[str]]:
    """(subtask, instruction) per frame, from the spans above, independently of the export code."""
    t = (frames.frame_ns - frames.manifest.start_ns) / 1e9 - offset
    subtask, sentence = [], []
    for v in t.tolist():
        if 1.5 <= v < 2.5:
            subtask.append("grasp")
            sentence.append(GRASP_SENTENCE)
        elif 1.0 <= v < 1.5:  # "wrong" (0.9) beats "reach" (0.5); "grasp" (a person's) beats both
            subtask.append("wrong")
            sentence.append(f"wrong: {frames.task}")
        elif 0.5 <= v < 1.0:
            subtask.append("reach")
            sentence.append(f"reach: {frames.task}")
        else:  # "transport" 2.5..3.5 was rejected
            subtask.append("")
            sentence.append(frames.task)
    return subtask, sentence


@pytest.fixture(scope="module")
def expected(labelled: tuple[Path, float]) -> tuple[EpisodeFrames, list[str], list[str]]:
    ep, offset = labelled
    frames = load_episode(ep)
    subtask, sentence = _expected(frames, offset)
    assert {"reach", "wrong", "grasp", ""} <= set(subtask), "the demo episode is too short for the spans"
    return frames, subtask, sentence


def test_frames_carry_the_active_segment_and_leave_the_rejected_one_out(
    expected: tuple[EpisodeFrames, list[str], list[str]],
) -> None:
    frames, subtask, sentence = expected
    assert frames.language is not None
    assert list(frames.language.subtask) == subtask
    assert list(frames.language.instruction) == sentence
    assert "transport" not in {s.label for s in frames.language.segments}


def test_lerobot_export_has_subtask_index_subtasks_parquet_and_a_language_column(
    root: Path, expected: tuple[EpisodeFrames, list[str], list[str]], tmp_path: Path
) -> None:
    frames, subtask, sentence = expected
    out = tmp_path / "lerobot"
    export(root, "lerobot", out, selection=ALL)
    info = json.loads((out / "meta/info.json").read_text())
    assert info["features"]["subtask_index"] == {"dtype": "int64", "shape": [1], "names": None}
    assert info["features"]["language_instruction"] == {"dtype": "string", "shape": [1], "names": None}
    subtasks = pq.read_table(out / "meta/subtasks.parquet")
    pandas_meta = json.loads(subtasks.schema.metadata[b"pandas"])
    assert pandas_meta["index_columns"] == ["subtask"]  # LeRobot 0.4: meta.subtasks.iloc[i].name
    names = dict(zip(subtasks["subtask_index"].to_pylist(), subtasks["subtask"].to_pylist(), strict=True))
    rows = pq.read_table(out / "data/chunk-000/file-000.parquet").to_pylist()
    episodes = pq.read_table(out / "meta/episodes/chunk-000/file-000.parquet").to_pylist()
    index = {e["telerig/episode_id"]: e["episode_index"] for e in episodes}
    mine = [r for r in rows if r["episode_index"] == index[frames.episode_id]]
    assert [names[r["subtask_index"]] for r in mine] == subtask
    assert [r["language_instruction"] for r in mine] == sentence
    others = [r for r in rows if r["episode_index"] != index[frames.episode_id]]
    assert {names[r["subtask_index"]] for r in others} <= {""}  # the other episode has no segments
    tasks = pq.read_table(out / "meta/tasks.parquet").to_pylist()
    assert {r["task_index"] for r in mine} == {t["task_index"] for t in tasks if t["task"] == frames.task}


def test_hdf5_and_robomimic_carry_per_frame_strings_and_the_segments(
    root: Path, expected: tuple[EpisodeFrames, list[str], list[str]], tmp_path: Path
) -> None:
    frames, subtask, sentence = expected
    export(root, "hdf5", tmp_path / "h5", selection=ALL)
    files = sorted((tmp_path / "h5" / "episodes").glob("*.hdf5"))
    assert len(files) >= 2
    with h5py.File(tmp_path / "h5" / "episodes" / f"{frames.episode_id}.hdf5") as f:
        assert [s.decode() for s in f["language/subtask"][()]] == subtask
        assert [s.decode() for s in f["language/instruction"][()]] == sentence
        segments = json.loads(f["language"].attrs["segments"])
    assert [s["label"] for s in segments] == ["reach", "wrong", "grasp"]
    assert [s["status"] for s in segments] == ["proposed", "proposed", "accepted"]
    assert segments[2]["description"] == GRASP_SENTENCE
    for path in files:  # an episode without segments has no language group (its file is as before)
        if path.stem != frames.episode_id:
            with h5py.File(path) as f:
                assert "language" not in f

    export(root, "robomimic", tmp_path / "rm", selection=ALL)
    with h5py.File(tmp_path / "rm" / "robomimic.hdf5") as f:
        demos = {str(g.attrs["episode_id"]): g for g in f["data"].values()}
        demo = demos[frames.episode_id]
        assert [s.decode() for s in demo["language/subtask"][()]] == subtask
        assert [s.decode() for s in demo["language/instruction"][()]] == sentence
        assert all("language" not in g for k, g in demos.items() if k != frames.episode_id)


def test_rlds_steps_carry_the_segment_language_instruction(
    root: Path, expected: tuple[EpisodeFrames, list[str], list[str]], tmp_path: Path
) -> None:
    frames, _, sentence = expected
    export(root, "rlds", tmp_path / "rlds", selection=ALL)
    directory = dataset_dir(tmp_path / "rlds")
    assert directory is not None
    found = {}
    for episode in read_episodes(directory):
        ident = episode["episode_metadata/episode_id"].as_bytes("episode_id")[0].decode()
        found[ident] = episode["steps/language_instruction"].as_bytes("language_instruction")
    assert [s.decode() for s in found.pop(frames.episode_id)] == sentence
    for other in found.values():  # no segments: the task on every step, as before
        assert len(set(other)) == 1


def test_a_corrupted_sidecar_stops_the_export_in_one_line_naming_the_file(
    labelled: tuple[Path, float], tmp_path: Path
) -> None:
    ep, _ = labelled
    data = tmp_path / "data"
    shutil.copytree(ep.parent.parent, data)
    broken = next(data.rglob(f"{ep.name}/{SEGMENTS_FILE}"))
    broken.write_text('{"schema": 1, "video": "cameras/scene.mp4", "duration_s": -3, "segments": [')
    with pytest.raises(ExportError) as err:
        export(data, "hdf5", tmp_path / "out", selection=EpisodeFilter(ids=(ep.name,), include_failures=True))
    message = str(err.value)
    assert "\n" not in message
    assert str(broken) in message
    assert "re-run `telerig process`" in message
    assert not any((tmp_path / "out").glob("episodes/*.hdf5"))


def test_episodes_show_lists_the_segments_with_status_and_annotation(
    root: Path, labelled: tuple[Path, float], capsys: pytest.CaptureFixture[str]
) -> None:
    ep, _ = labelled
    assert main(["episodes", "show", ep.name, "--data-root", str(root)]) == 0
    out = capsys.readouterr().out
    lines = {line.split("│")[1].strip(): line for line in out.splitlines() if line.count("│") >= 7}
    for word in ("0.50", "1.50", "proposed", "machine:robot_streams@1"):
        assert word in lines["reach"]
    for word in ("accepted", "human:ana", "1.00"):
        assert word in lines["grasp"]
    assert "The robot arm closes its gripper" in lines["grasp"]
    assert "rejected" in lines["transport"]  # shown, with its review state
    for word in ("gates:", "score:", "label:", "episode.mcap"):
        assert word in out


def test_episodes_show_names_a_damaged_segments_file_in_one_line(
    labelled: tuple[Path, float], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    ep, _ = labelled
    data = tmp_path / "data"
    shutil.copytree(ep.parent.parent, data)
    broken = next(data.rglob(f"{ep.name}/{SEGMENTS_FILE}"))
    broken.write_bytes(b"\x00" * 100)
    assert main(["episodes", "show", ep.name, "--data-root", str(data)]) == 2
    captured = capsys.readouterr()
    assert "episode.mcap" in captured.out  # the rest is still shown
    err = captured.err.strip().splitlines()
    assert len(err) == 1
    assert str(broken) in err[0]
    assert "telerig process" in err[0]


def test_telerig_process_offline_labels_the_exported_frames_with_its_descriptions(
    demo_recording: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The pipeline's segment and annotate stages leave both sidecars; the export reads them."""
    for name in ("TELERIG_VLM_URL", "TELERIG_VLM_MODEL", "TELERIG_VLM_API_KEY"):
        monkeypatch.delenv(name, raising=False)
    data = tmp_path / "data"
    shutil.copytree(demo_recording, data)
    ep = sorted(EpisodeStore(data).list(include_failures=True), key=lambda e: e.id)[0].path
    args = ["process", str(ep), "--out", str(tmp_path / "processed"), "--workers", "1"]
    assert main([*args, "--stages", "segment,clips,annotate"]) == 0
    frames = load_episode(ep)
    lang = frames.language
    assert lang is not None
    assert lang.segments, "the robot_streams segmenter found no action in the demo episode"
    # offline: one description per clip (a segment too short for a clip has none)
    assert lang.descriptions
    assert set(lang.descriptions) <= {s.id for s in lang.segments}
    for i, seg in enumerate(lang.segments):
        inside = lang.segment_index == i
        assert inside.any(), f"no frame inside segment {seg.label} {seg.start_s}..{seg.end_s}"
        t = lang.video_time_s[inside]
        assert t.min() >= seg.start_s
        assert t.max() < seg.end_s
        said = lang.descriptions.get(seg.id, f"{seg.label}: {frames.task}")
        assert {lang.instruction[k] for k in np.flatnonzero(inside)} == {said}
        assert {lang.subtask[k] for k in np.flatnonzero(inside)} == {seg.label}
