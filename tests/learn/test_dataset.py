"""The LeRobot v3 reader on a real telerig export: values, frame alignment, cache, and garbage."""

from __future__ import annotations

import dataclasses
import json
import logging
import shutil
from pathlib import Path

import av
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from telerig.errors import PolicyError
from telerig.export import EpisodeFilter, export
from telerig.learn.dataset import (
    MAX_INFO_BYTES,
    PolicyDataset,
    image_size_for,
    read_dataset,
    split_episodes,
)
from telerig.policy.images import resize_rgb

SIZE = (24, 32)
VIDEO = "videos/observation.images.scene/chunk-000/file-000.mp4"
DATA = "data/chunk-000/file-000.parquet"
EPISODES = "meta/episodes/chunk-000/file-000.parquet"


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("frames-cache")


@pytest.fixture(scope="module")
def dataset(lerobot_export: Path, cache_dir: Path) -> PolicyDataset:
    """The export read once at 32 px wide (24x32 from the 640x480 camera), filling ``cache_dir``."""
    return read_dataset(lerobot_export, image_width=32, cache_dir=cache_dir)


def test_reads_state_action_and_names_as_exported(lerobot_export: Path, dataset: PolicyDataset) -> None:
    ds = dataset
    assert ds.image_size == SIZE
    info = json.loads((lerobot_export / "meta/info.json").read_text())
    table = pq.read_table(lerobot_export / DATA)
    assert ds.fps == info["fps"] == 30
    assert ds.camera_keys == ("scene",)
    assert ds.state_names == tuple(info["features"]["observation.state"]["names"])
    assert ds.action_names == tuple(info["features"]["action"]["names"])
    assert len(ds.episodes) == info["total_episodes"] == 2
    assert ds.frames == info["total_frames"]
    episode_index = table["episode_index"].to_numpy()
    for ep in ds.episodes:
        rows = table.filter(pa.array(episode_index == ep.index))
        state = np.array(rows["observation.state"].to_pylist(), dtype=np.float32)
        action = np.array(rows["action"].to_pylist(), dtype=np.float32)
        np.testing.assert_array_equal(ep.state, state)
        np.testing.assert_array_equal(ep.action, action)
        assert ep.images["scene"].shape == (ep.length, *SIZE, 3)
        assert ep.images["scene"].dtype == np.uint8
        assert ep.episode_id.startswith("ep-")


def _assert_frames_from_their_rows_files(root: Path, ds: PolicyDataset) -> None:
    """Frame ``k`` of each episode is the frame at ``from_timestamp + k / fps`` of the MP4 its row
    names (a demo export on a loaded machine may put its two episodes in two files)."""
    rows = pq.read_table(root / EPISODES).to_pylist()
    decoded: dict[str, dict[float, np.ndarray]] = {}
    for ep, row in zip(ds.episodes, rows, strict=True):
        key = "videos/observation.images.scene"
        rel = f"{key}/chunk-{row[f'{key}/chunk_index']:03d}/file-{row[f'{key}/file_index']:03d}.mp4"
        if rel not in decoded:
            with av.open(str(root / rel)) as container:
                decoded[rel] = {
                    round(float(f.pts * f.time_base), 4): f.to_ndarray(format="rgb24")
                    for f in container.decode(video=0)
                }
        start = row[f"{key}/from_timestamp"]
        for k in (0, ep.length // 2, ep.length - 1):
            expected = resize_rgb(decoded[rel][round(start + k / ds.fps, 4)], SIZE)
            np.testing.assert_array_equal(ep.images["scene"][k], expected)


def test_frame_k_is_the_video_frame_at_from_timestamp_plus_k_over_fps(
    lerobot_export: Path, dataset: PolicyDataset
) -> None:
    ds = dataset
    _assert_frames_from_their_rows_files(lerobot_export, ds)
    # Episodes differ and frames move: the reader did not hand every frame the same picture.
    first = ds.episodes[0].images["scene"]
    assert np.abs(first[0].astype(int) - first[-1].astype(int)).mean() > 0.5


def test_episodes_in_separate_data_and_video_files_are_read_from_each(
    demo_recording: Path, dataset: PolicyDataset, tmp_path: Path
) -> None:
    out = tmp_path / "rolled"
    tiny = {"data_files_size_in_mb": 0.001, "video_files_size_in_mb": 0.001}  # a file per episode
    export(demo_recording, "lerobot", out, selection=EpisodeFilter(include_failures=True), options=tiny)
    rows = pq.read_table(out / EPISODES).to_pylist()
    assert [r["videos/observation.images.scene/file_index"] for r in rows] == [0, 1]
    assert [r["data/file_index"] for r in rows] == [0, 1]
    rolled = read_dataset(out, image_width=32)
    _assert_frames_from_their_rows_files(out, rolled)
    for a, b in zip(dataset.episodes, rolled.episodes, strict=True):
        np.testing.assert_array_equal(b.state, a.state)
        np.testing.assert_array_equal(b.action, a.action)


def test_image_width_keeps_the_camera_aspect() -> None:
    assert image_size_for(480, 640, 64) == (48, 64)
    assert image_size_for(480, 640, 32) == SIZE
    assert image_size_for(120, 160, 96) == (72, 96)
    with pytest.raises(PolicyError, match="cannot size policy images"):
        image_size_for(480, 640, 4)


def test_cache_is_reused_and_a_damaged_cache_is_decoded_again(
    lerobot_export: Path, dataset: PolicyDataset, cache_dir: Path, caplog: pytest.LogCaptureFixture
) -> None:
    (cache,) = cache_dir.glob("frames-*-24x32.npz")
    again = read_dataset(lerobot_export, image_size=SIZE, cache_dir=cache_dir)
    for a, b in zip(dataset.episodes, again.episodes, strict=True):
        np.testing.assert_array_equal(a.images["scene"], b.images["scene"])
    good = cache.read_bytes()
    cache.write_bytes(good[:1000])
    try:
        with caplog.at_level(logging.WARNING, logger="telerig.learn.dataset"):
            third = read_dataset(lerobot_export, image_size=SIZE, cache_dir=cache_dir)
    finally:
        cache.write_bytes(good)
    assert "unreadable" in caplog.text
    np.testing.assert_array_equal(third.episodes[1].images["scene"], dataset.episodes[1].images["scene"])


def test_a_normalized_export_is_read_back_in_physical_units(
    demo_recording: Path, lerobot_export: Path, tmp_path: Path
) -> None:
    out = tmp_path / "norm"
    export(demo_recording, "lerobot", out, selection=EpisodeFilter(include_failures=True), normalize=True)
    assert json.loads((out / "meta/robot_schema.json").read_text())["normalized"] is True
    plain = read_dataset(lerobot_export, image_size=SIZE, cameras=())
    normed = read_dataset(out, image_size=SIZE, cameras=())
    assert normed.camera_keys == ()
    for a, b in zip(plain.episodes, normed.episodes, strict=True):
        np.testing.assert_allclose(b.state, a.state, atol=2e-5)
        np.testing.assert_allclose(b.action, a.action, atol=2e-5)


def test_split_is_by_episode_disjoint_and_seeded(dataset: PolicyDataset) -> None:
    episodes = [dataclasses.replace(dataset.episodes[i % 2], index=i) for i in range(10)]
    train, val = split_episodes(episodes, 0.2, seed=3)
    assert len(val) == 2
    assert len(train) == 8
    assert sorted(e.index for e in train + val) == list(range(10))
    assert split_episodes(episodes, 0.2, seed=4) != (train, val)
    assert split_episodes(episodes, 0.2, seed=3) == (train, val)
    one_train, one_val = split_episodes(episodes[:1], 0.5, seed=0)
    assert (len(one_train), len(one_val)) == (1, 0)  # one episode always trains
    with pytest.raises(PolicyError, match=r"validation fraction must be in \[0, 1\)"):
        split_episodes(episodes, 1.0, seed=0)


def _damage(root: Path, how: str) -> Path:
    if how == "a file":
        (root / "f.txt").write_text("x")
        return root / "f.txt"
    if how == "missing":
        return root / "nope"
    if how == "empty dir":
        (root / "empty").mkdir()
        return root / "empty"
    return root


def _write_parquet_with_nan(ds: Path) -> None:
    table = pq.read_table(ds / DATA)
    state = table["observation.state"].to_pylist()
    state[3][2] = float("nan")
    col = pa.array(state, type=table.schema.field("observation.state").type)
    pq.write_table(
        table.set_column(table.column_names.index("observation.state"), "observation.state", col), ds / DATA
    )


GARBAGE = {
    "info-not-json": ("meta/info.json", b"{not json", "info.json is unreadable"),
    "info-a-list": ("meta/info.json", b"[1, 2]", "not a JSON object"),
    "info-binary": ("meta/info.json", b"\xff\xfe\x00garbage", "info.json is unreadable"),
    "info-v2": ("meta/info.json", json.dumps({"codebase_version": "v2.1"}).encode(), "'v2.1' dataset"),
    "schema-garbage": ("meta/robot_schema.json", b"\x00\x01\x02", "robot_schema.json"),
    "episodes-garbage": (EPISODES, b"PAR1 this is not parquet", "re-export"),
    "data-garbage": (DATA, b"PAR1" + b"\x00" * 100 + b"PAR1", "unreadable"),
    "video-garbage": (VIDEO, b"\x00\x00\x00\x18ftypmp42" + b"\x13" * 5000, "unreadable"),
}


@pytest.mark.parametrize("name", sorted(GARBAGE))
def test_garbage_files_give_one_line_errors(lerobot_export: Path, tmp_path: Path, name: str) -> None:
    ds = tmp_path / "ds"
    shutil.copytree(lerobot_export, ds)
    rel, content, match = GARBAGE[name]
    (ds / rel).write_bytes(content)
    with pytest.raises(PolicyError, match=match) as info:
        read_dataset(ds, image_size=SIZE)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize(
    ("how", "match"),
    [
        ("a file", "is not a directory"),
        ("missing", "is not a directory"),
        ("empty dir", r"not a LeRobot dataset \(no meta/info.json\); export one with"),
        ("no schema", "has no meta/robot_schema.json"),
        ("no episodes", "no meta/episodes"),
        ("no data", "is missing; the export is incomplete"),
        ("no video", "is missing; the export is incomplete"),
        ("truncated video", "re-export the dataset"),
        ("zero episodes", "no episode to train on"),
        ("huge info", "more than LeRobot metadata ever is"),
        ("nan state", "NaN or inf"),
        ("short data", "holds .* frames, its length is"),
        ("unknown camera", "camera 'wrist' is not in"),
    ],
)
def test_broken_datasets_give_one_line_errors(
    lerobot_export: Path, tmp_path: Path, how: str, match: str
) -> None:
    ds = tmp_path / "ds"
    shutil.copytree(lerobot_export, ds)
    target = _damage(tmp_path, how) if how in ("a file", "missing", "empty dir") else ds
    cameras = None
    if how == "no schema":
        (ds / "meta/robot_schema.json").unlink()
    elif how == "no episodes":
        shutil.rmtree(ds / "meta/episodes")
    elif how == "no data":
        (ds / DATA).unlink()
    elif how == "no video":
        (ds / VIDEO).unlink()
    elif how == "truncated video":
        video = (ds / VIDEO).read_bytes()
        (ds / VIDEO).write_bytes(video[: len(video) // 3])
    elif how == "zero episodes":
        info = json.loads((ds / "meta/info.json").read_text())
        info["total_episodes"] = 0
        (ds / "meta/info.json").write_text(json.dumps(info))
    elif how == "huge info":
        (ds / "meta/info.json").write_bytes(b" " * (MAX_INFO_BYTES + 1))
    elif how == "nan state":
        _write_parquet_with_nan(ds)
    elif how == "short data":
        table = pq.read_table(ds / DATA)
        pq.write_table(table.slice(0, table.num_rows - 5), ds / DATA)
    elif how == "unknown camera":
        cameras = ["wrist"]
    with pytest.raises(PolicyError, match=match) as info:
        read_dataset(target, image_size=SIZE, cameras=cameras)
    assert "\n" not in str(info.value)
