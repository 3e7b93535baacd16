"""Stage 5 with the real stages before it (segment, clips, offline annotate): clips by scene with
their annotation files, an episode's streams cut to each clip, the global index (JSON and the index
database), re-runs, stale clips pruned, and damaged inputs."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from core_kit import T0_NS, make_episode, make_video

from telerig.config.process import ProcessSettings
from telerig.errors import ProcessError
from telerig.process.items import discover
from telerig.process.layout import DATASET_DIR, index_clips, read_index
from telerig.process.run import RunSummary, item_dir, plan, run_pipeline
from telerig.registry import PROCESS_STAGES
from telerig.store.index import EpisodeIndex

_STAGES = ("segment", "clips", "annotate", "layout")


def _run(target: Path, work: Path, names: tuple[str, ...] = _STAGES) -> RunSummary:
    found = discover(str(target))
    settings = ProcessSettings()
    stages = plan([PROCESS_STAGES.get(n)() for n in names], {n: settings.for_stage(n) for n in names})
    return run_pipeline(found.items, stages, work, workers=1)


def test_episode_clips_land_by_scene_with_annotation_and_streams(tmp_path: Path) -> None:
    root = tmp_path / "data"
    episode_id = make_episode(root, seconds=3.0)
    work = tmp_path / "processed"
    summary = _run(root, work)
    assert [s.status for s in summary.outcomes[0].stages] == ["ok"] * 4
    index = read_index(work)
    assert index["clips"], "the episode gave no clip"
    clip = index["clips"][0]
    assert clip["source_id"] == episode_id
    assert clip["scene"] != "unknown"  # the (offline) annotation's scene names the folder
    mp4 = work / clip["path"]
    assert mp4.is_file()
    assert mp4.parent == work / DATASET_DIR / clip["scene"]
    note = json.loads((work / clip["annotation_file"]).read_text())
    assert note["annotation"]["offline"] is True
    assert note["source"]["device_id"] == "station-7"
    assert note["source"]["date"].startswith("2026-09-21")
    assert clip["fps"] == pytest.approx(10.0)
    source = index["sources"][episode_id]
    assert source["clips"] == [clip["id"]]
    # The streams: the arm's joint states within the clip's span (+0.1 s margin), on the common
    # clock moved by the camera's frame stamps, values as recorded (positions 0.01 * sample index).
    streams = work / clip["streams"]
    meta = json.loads((streams / "streams.json").read_text())
    assert meta["start_ns"] == T0_NS + round(clip["start_s"] * 1e9)
    rows = [json.loads(line) for line in (streams / "arm0.joint_state.jsonl").read_text().splitlines()]
    assert rows
    assert all(-0.1 - 1e-9 <= r["t_s"] <= clip["end_s"] - clip["start_s"] + 0.1 + 1e-9 for r in rows)
    for r in rows:
        i = (r["capture_ns"] - T0_NS) // 20_000_000
        assert r["positions"] == pytest.approx([0.01 * i, -0.01 * i])
    expected = sum(1 for i in range(150) if meta["start_ns"] - 1e8 <= T0_NS + i * 2e7 <= meta["end_ns"] + 1e8)
    assert len(rows) == expected
    # And the index database links the recording to its clip.
    with EpisodeIndex.open(tmp_path / "index.sqlite") as db:
        assert index_clips(work, db) == 1
        (row,) = db.processed_clips(source_id=episode_id)
        assert (row.id, row.scene, row.device_id) == (clip["id"], clip["scene"], "station-7")
        assert row.fps == pytest.approx(10.0)


def test_without_annotations_scene_is_unknown_and_videos_have_no_streams(tmp_path: Path) -> None:
    folder = tmp_path / "videos"
    make_video(folder / "a.mp4", seconds=3.0)
    work = tmp_path / "processed"
    summary = _run(folder, work, ("segment", "clips", "layout"))
    statuses = [s.status for s in summary.outcomes[0].stages]
    assert statuses[-1] in ("ok", "empty")
    index = read_index(work)
    for clip in index["clips"]:
        assert clip["scene"] == "unknown"
        assert clip["streams"] is None
        assert (work / clip["path"]).is_file()


def test_rerun_skips_and_stale_clips_are_pruned(tmp_path: Path) -> None:
    root = tmp_path / "data"
    make_episode(root, seconds=3.0)
    work = tmp_path / "processed"
    _run(root, work)
    first = read_index(work)["clips"][0]
    again = _run(root, work)
    assert all(s.reused for s in again.outcomes[0].stages)
    # A deleted dataset file redoes the layout (its outputs are checked), nothing before it.
    (work / first["path"]).unlink()
    redo = _run(root, work)
    assert [s.reused for s in redo.outcomes[0].stages] == [True, True, True, False]
    assert (work / first["path"]).is_file()
    # A clip no item lists any more (an older segmentation's) is removed from the dataset.
    stale = work / DATASET_DIR / first["scene"] / "0badc0de-0000-4000-8000-000000000000.mp4"
    stale.write_bytes(b"old clip")
    (work / DATASET_DIR / first["scene"] / "README.txt").write_text("kept: not a clip")
    layout_dir = item_dir(work, again.outcomes[0].item_id) / "layout"
    (layout_dir / "provenance.json").write_text("{")  # damaged: the layout is redone, index rebuilt
    _run(root, work)
    assert not stale.exists()
    assert (work / DATASET_DIR / first["scene"] / "README.txt").is_file()
    assert [c["id"] for c in read_index(work)["clips"]] == [first["id"]]


def test_damaged_clips_file_fails_that_item_only(tmp_path: Path) -> None:
    root = tmp_path / "data"
    make_episode(root, seconds=3.0)
    work = tmp_path / "processed"
    _run(root, work)
    item_id = discover(str(root)).items[0].id
    (item_dir(work, item_id) / "clips" / "clips.json").write_bytes(b"\x00garbage")
    (item_dir(work, item_id) / "layout" / "provenance.json").unlink()
    summary = _run(root, work)
    failed = summary.outcomes[0].failed
    assert failed is not None
    assert failed.name == "layout"
    assert "clips.json is not a clips file" in failed.message
    assert json.loads((work / "failures.json").read_text())["failures"][0]["stage"] == "layout"
    assert read_index(work)["clips"] == []  # a failed layout is left out of the index


@pytest.mark.parametrize("content", [b"[]", b"{", b'{"schema": 1}', b"\xff" * 10])
def test_damaged_index_is_one_line(tmp_path: Path, content: bytes) -> None:
    (tmp_path / "index.json").write_bytes(content)
    with pytest.raises(ProcessError, match="index") as info:
        read_index(tmp_path)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("content", [b"", b"{", b'{"source": 1, "clips": "x"}', b"[" * 50000, b"\xff"])
def test_garbage_layout_or_annotations_file_is_handled(tmp_path: Path, content: bytes) -> None:
    root = tmp_path / "data"
    make_episode(root, seconds=3.0)
    work = tmp_path / "processed"
    first = _run(root, work)
    item = item_dir(work, first.outcomes[0].item_id)
    # A damaged layout.json (its provenance intact) is left out of the global index, never a crash.
    (item / "layout" / "layout.json").write_bytes(content)
    from telerig.process.layout import write_index

    assert write_index(work)["clips"] == []
    # A damaged annotations.json fails that item's layout in one line (redone: its record removed).
    (item / "annotate" / "annotations.json").write_bytes(content)
    (item / "layout" / "provenance.json").unlink()
    again = _run(root, work)
    failed = again.outcomes[0].failed
    assert failed is not None
    assert failed.name == "layout"
    assert "annotations" in failed.message
    assert "\n" not in failed.message


@pytest.mark.parametrize(
    "clips",
    [
        [1],
        [{"id": "x"}],
        [{"id": "x", "source_id": "s", "path": "p", "scene": "s", "start_s": "soon"}],
        ["a"],
    ],
)
def test_garbage_index_entries_are_one_line_for_the_database(tmp_path: Path, clips: list[object]) -> None:
    (tmp_path / "index.json").write_text(json.dumps({"schema": 1, "sources": {}, "clips": clips}))
    with (
        EpisodeIndex.open(tmp_path / "index.sqlite") as db,
        pytest.raises(ProcessError, match="malformed") as info,
    ):
        index_clips(tmp_path, db)
    assert "\n" not in str(info.value)
