"""LeRobot v3.0 export of real demo episodes, read back with pyarrow and PyAV.

The real ``lerobot`` cannot live in telerig's venv (CUDA torch, ~8 GB): these tests check the
files against the layout ``lerobot.datasets`` 0.4 reads; ``scripts/check_lerobot_export.py``
loads an export with the real ``LeRobotDataset`` in a separate venv.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import av
import numpy as np
import numpy.typing as npt
import pyarrow.parquet as pq
import pytest

from telerig.cameras.encoder import VideoEncoder
from telerig.errors import ExportError
from telerig.export import EpisodeFilter, export
from telerig.export._lerobot_stats import ImageStats, aggregate, sample_indices, vector_stats
from telerig.export.config import LeRobotExportConfig
from telerig.export.frames import EpisodeFrames, load_episode
from telerig.export.lerobot import LeRobotExporter
from telerig.store.episodes import EpisodeStore

SCENE = "observation.images.scene"
STAT_KEYS = ("min", "max", "mean", "std", "count", "q01", "q10", "q50", "q90", "q99")


@pytest.fixture(scope="module")
def episode_dirs(demo_recording: Path) -> list[Path]:
    # Gates may reject demo episodes on a loaded machine (camera under rate): export them all.
    return [e.path for e in EpisodeStore(demo_recording).list(include_failures=True)]


@pytest.fixture(scope="module")
def exported(demo_recording: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("lerobot") / "ds"
    export(demo_recording, "lerobot", out, selection=EpisodeFilter(include_failures=True))
    return out


def _info(out: Path) -> dict[str, object]:
    info: dict[str, object] = json.loads((out / "meta/info.json").read_text())
    return info


def _episodes(out: Path) -> list[dict[str, object]]:
    rows: list[dict[str, object]] = []
    for path in sorted(out.glob("meta/episodes/chunk-*/file-*.parquet")):
        rows += pq.read_table(path).to_pylist()
    return rows


def _decode(path: Path) -> dict[float, npt.NDArray[np.uint8]]:
    """Every frame of an MP4 by its pts [s] (rounded to 1e-6), RGB."""
    with av.open(str(path)) as container:
        return {
            round(float(f.pts * f.time_base), 6): f.to_ndarray(format="rgb24")
            for f in container.decode(video=0)
        }


def _psnr(a: npt.NDArray[np.uint8], b: npt.NDArray[np.uint8]) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return 99.0 if mse == 0 else 10 * np.log10(255.0**2 / mse)


def _video_file(row: dict[str, object], key: str = SCENE) -> tuple[int, int]:
    return int(row[f"videos/{key}/chunk_index"]), int(row[f"videos/{key}/file_index"])  # type: ignore[call-overload]


def _assert_video_spans_tile_their_files(rows: list[dict[str, object]]) -> None:
    """Episodes follow one another in file order; inside a file each starts where the last ended.

    A live recording is copied when its camera kept one frame per dataset frame and re-encoded when
    it did not (a frame dropped on a loaded machine), and the two never share a file: which files a
    demo export has depends on the machine, so this checks the layout, not a file count.
    """
    last: tuple[int, int] | None = None
    to = 0.0
    for row in rows:
        here = _video_file(row)
        if here != last:
            assert last is None or here > last, (last, here)
            to = 0.0
        assert row[f"videos/{SCENE}/from_timestamp"] == pytest.approx(to)
        to = row[f"videos/{SCENE}/to_timestamp"]  # type: ignore[assignment]
        assert to == pytest.approx(row[f"videos/{SCENE}/from_timestamp"] + row["length"] / 30)  # type: ignore[operator]
        last = here


def _assert_frames_at_their_timestamps(
    out: Path, rows: list[dict[str, object]], episodes: list[EpisodeFrames]
) -> None:
    """Frame ``k`` of each episode decodes from the file its row names at ``from_timestamp + k/30``."""
    decoded: dict[tuple[int, int], dict[float, npt.NDArray[np.uint8]]] = {}
    for row, frames in zip(rows, episodes, strict=True):
        chunk, file = _video_file(row)
        if (chunk, file) not in decoded:
            decoded[chunk, file] = _decode(out / f"videos/{SCENE}/chunk-{chunk:03d}/file-{file:03d}.mp4")
        images = decoded[chunk, file]
        start = float(row[f"videos/{SCENE}/from_timestamp"])  # type: ignore[arg-type]
        for k, source in enumerate(frames.cameras["scene"].frames()):
            image = images.get(round(start + k / 30, 6))
            assert image is not None, (
                f"episode {row['episode_index']} frame {k} is not at {start + k / 30:.6f} s "
                f"of file {chunk}/{file}"
            )
            assert image.shape == (480, 640, 3)
            # Copied packets decode bit-identical; re-encoded ones within H.264 loss (a channel
            # swap or a frame shifted by one would fall far below).
            assert _psnr(image, source) > 30.0


def _digests(out: Path) -> dict[str, str]:
    return {
        str(p.relative_to(out)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(out.rglob("*"))
        if p.is_file() and p.name != ".telerig-export.lock"
    }


# -- layout -------------------------------------------------------------------------------------------


def test_info_declares_v3_with_the_schema_names_and_lerobot_defaults(exported: Path) -> None:
    info = _info(exported)
    schema = json.loads((exported / "meta/robot_schema.json").read_text())
    assert info["codebase_version"] == "v3.0"
    assert info["robot_type"] == "ur5e_robotiq85"
    assert (info["total_episodes"], info["total_tasks"], info["fps"]) == (2, 1, 30)
    assert (info["chunks_size"], info["data_files_size_in_mb"], info["video_files_size_in_mb"]) == (
        1000,
        100,
        200,
    )
    assert info["splits"] == {"train": "0:2"}
    assert info["data_path"] == "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
    assert info["video_path"] == "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
    features = info["features"]
    assert isinstance(features, dict)
    assert features["action"]["names"] == [a["name"] for a in schema["action"]]
    assert features["action"]["shape"] == [len(schema["action"])]
    assert features["observation.state"]["names"] == [s["name"] for s in schema["state"]]
    assert features[SCENE]["dtype"] == "video"
    assert features[SCENE]["shape"] == [480, 640, 3]
    assert features[SCENE]["names"] == ["height", "width", "channels"]
    assert features[SCENE]["info"]["video.codec"] == "h264"
    for key in ("timestamp", "frame_index", "episode_index", "index", "task_index"):
        assert features[key]["shape"] == [1]
    assert all("/" not in key for key in features)


def test_frames_hold_every_episode_in_order_at_k_over_fps(exported: Path, episode_dirs: list[Path]) -> None:
    table = pq.read_table(exported / "data/chunk-000/file-000.parquet")
    rows = _episodes(exported)
    assert table.num_rows == _info(exported)["total_frames"] == sum(int(r["length"]) for r in rows)  # type: ignore[call-overload]
    np.testing.assert_array_equal(table["index"].to_numpy(), np.arange(table.num_rows))
    for row, episode_dir in zip(rows, episode_dirs, strict=True):
        frames = load_episode(episode_dir)
        sel = table.slice(row["dataset_from_index"], row["length"])  # type: ignore[arg-type]
        assert row["telerig/episode_id"] == frames.episode_id
        assert row["length"] == frames.length
        assert set(sel["episode_index"].to_numpy()) == {row["episode_index"]}
        np.testing.assert_array_equal(sel["frame_index"].to_numpy(), np.arange(frames.length))
        np.testing.assert_allclose(sel["timestamp"].to_numpy(), np.arange(frames.length) / 30, atol=1e-6)
        state = np.stack(sel["observation.state"].to_numpy(zero_copy_only=False))
        np.testing.assert_array_equal(state, frames.state)
        action = np.stack(sel["action"].to_numpy(zero_copy_only=False))
        np.testing.assert_array_equal(action, frames.action)
        names = _info(exported)["features"]["telerig.alignment_error_ms"]["names"]  # type: ignore[index]
        errors = np.stack(sel["telerig.alignment_error_ms"].to_numpy(zero_copy_only=False))
        recorded = np.stack([frames.alignment_error_ms[n] for n in names], axis=1)
        np.testing.assert_array_equal(errors, np.nan_to_num(recorded, nan=-1.0))  # -1: no sample


def test_tasks_parquet_maps_the_task_string_to_its_index_as_pandas_reads_it(exported: Path) -> None:
    table = pq.read_table(exported / "meta/tasks.parquet")
    pandas_meta = json.loads(table.schema.metadata[b"pandas"])
    assert pandas_meta["index_columns"] == ["task"]
    assert table["task_index"].to_pylist() == [0]
    assert table["task"].to_pylist() == _episodes(exported)[0]["tasks"]


def test_episode_rows_locate_data_and_video_and_carry_telerig_metadata(
    exported: Path, episode_dirs: list[Path]
) -> None:
    rows = _episodes(exported)
    assert [r["episode_index"] for r in rows] == [0, 1]
    _assert_video_spans_tile_their_files(rows)
    for row, episode_dir in zip(rows, episode_dirs, strict=True):
        assert (row["data/chunk_index"], row["data/file_index"]) == (0, 0)
        assert (row["meta/episodes/chunk_index"], row["meta/episodes/file_index"]) == (0, 0)
        frames = load_episode(episode_dir)
        assert json.loads(row["telerig/gates"]) == frames.gates  # type: ignore[arg-type]
        assert row["telerig/quality"] == frames.quality
        assert 0.0 <= row["telerig/valid_fraction"] <= 1.0  # type: ignore[operator]
        for key in ("action", "observation.state", SCENE, "timestamp", "index"):
            for stat in STAT_KEYS:
                assert row[f"stats/{key}/{stat}"] is not None
        assert np.asarray(row[f"stats/{SCENE}/mean"]).shape == (3, 1, 1)


def test_every_video_frame_sits_at_its_timestamp_and_shows_the_recorded_image(
    exported: Path, episode_dirs: list[Path]
) -> None:
    _assert_frames_at_their_timestamps(exported, _episodes(exported), [load_episode(d) for d in episode_dirs])


def test_stats_hold_lerobots_keys_aggregated_over_the_episodes(
    exported: Path, episode_dirs: list[Path]
) -> None:
    stats = json.loads((exported / "meta/stats.json").read_text())
    actions = np.concatenate([load_episode(d).action for d in episode_dirs]).astype(np.float64)
    assert set(stats) == set(_info(exported)["features"])  # type: ignore[call-overload]
    assert set(stats["action"]) == set(STAT_KEYS)
    np.testing.assert_allclose(stats["action"]["mean"], actions.mean(axis=0), rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(stats["action"]["std"], actions.std(axis=0), rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(stats["action"]["min"], actions.min(axis=0), rtol=1e-6)
    assert stats["action"]["count"] == [len(actions)]
    assert np.asarray(stats[SCENE]["mean"]).shape == (3, 1, 1)
    assert all(0.0 <= v <= 1.0 for v in np.ravel(stats[SCENE]["q50"]))


def test_validate_passes_on_the_export(exported: Path) -> None:
    report = LeRobotExporter().validate(exported)
    assert report.problems == ()
    assert report.episodes == 2


# -- copying the recorded video -----------------------------------------------------------------------


def _pattern(k: int) -> npt.NDArray[np.uint8]:
    """A moving colour pattern: red ramp, green stripes, blue by frame number."""
    y, x = np.mgrid[0:480, 0:640]
    image = np.empty((480, 640, 3), dtype=np.uint8)
    image[..., 0] = (x + 4 * k) % 256
    image[..., 1] = ((y // 16) % 2) * 200
    image[..., 2] = (10 * k) % 256
    return image


def _regular(frames: EpisodeFrames, tmp_path: Path) -> EpisodeFrames:
    """The episode as if its camera had kept 30 Hz exactly: a recorder-written H.264 MP4, one
    recorded frame per dataset frame (so the exporter may copy its packets)."""
    path = tmp_path / f"{frames.episode_id}.mp4"
    with VideoEncoder(path, width=640, height=480, fps=30) as encoder:
        for k in range(frames.length):
            while not encoder.submit(_pattern(k), 10**9 + round(k * 1e9 / 30)):
                time.sleep(0.002)
    track = frames.cameras["scene"]
    regular = dataclasses.replace(
        track,
        path=path,
        source_index=np.arange(frames.length),
        error_ms=np.zeros(frames.length, dtype=np.float32),
        one_to_one=True,
    )
    return dataclasses.replace(frames, cameras={"scene": regular})


@pytest.fixture(scope="module")
def regular_episodes(
    episode_dirs: list[Path], tmp_path_factory: pytest.TempPathFactory
) -> list[EpisodeFrames]:
    where = tmp_path_factory.mktemp("regular")
    return [_regular(load_episode(d), where) for d in episode_dirs]


def test_a_one_to_one_recording_is_copied_not_reencoded(
    regular_episodes: list[EpisodeFrames], tmp_path: Path
) -> None:
    exporter = LeRobotExporter()
    exporter.write(tmp_path, regular_episodes[0].schema, regular_episodes, lambda _: None)
    assert (exporter.timings.remuxed, exporter.timings.encoded) == (2, 0)
    assert exporter.validate(tmp_path).problems == ()
    decoded = _decode(tmp_path / f"videos/{SCENE}/chunk-000/file-000.mp4")
    start = 0.0
    for episode in regular_episodes:
        source = list(_decode(episode.cameras["scene"].path).values())
        for k in range(episode.length):
            np.testing.assert_array_equal(decoded[round(start + k / 30, 6)], source[k])
        start += episode.length / 30
    assert len(decoded) == sum(e.length for e in regular_episodes)


def test_a_copied_and_a_reencoded_episode_go_to_separate_files_that_rows_locate(
    regular_episodes: list[EpisodeFrames], tmp_path: Path
) -> None:
    # What a demo recording on a loaded machine exports to: one camera kept 30 Hz (copied), the
    # other dropped a frame (re-encoded). Packets of two codec configurations cannot share a file.
    copied, dropped = regular_episodes
    dropped = dataclasses.replace(
        dropped, cameras={"scene": dataclasses.replace(dropped.cameras["scene"], one_to_one=False)}
    )
    exporter = LeRobotExporter()
    exporter.write(tmp_path, copied.schema, [copied, dropped], lambda _: None)
    assert (exporter.timings.remuxed, exporter.timings.encoded) == (1, 1)
    rows = _episodes(tmp_path)
    assert [_video_file(r) for r in rows] == [(0, 0), (0, 1)]
    _assert_video_spans_tile_their_files(rows)
    _assert_frames_at_their_timestamps(tmp_path, rows, [copied, dropped])
    assert exporter.validate(tmp_path).problems == ()


def test_a_red_frame_stays_red(regular_episodes: list[EpisodeFrames], tmp_path: Path) -> None:
    episode = regular_episodes[0]
    path = tmp_path / "red.mp4"
    red = np.zeros((480, 640, 3), dtype=np.uint8)
    red[..., 0] = 220
    with VideoEncoder(path, width=640, height=480, fps=30) as encoder:
        for k in range(episode.length):
            while not encoder.submit(red, 10**9 + round(k * 1e9 / 30)):
                time.sleep(0.002)
    # Not one-to-one: decoded (RGB) and encoded again, the path of irregular recordings.
    track = dataclasses.replace(episode.cameras["scene"], path=path, one_to_one=False)
    exporter = LeRobotExporter()
    out = tmp_path / "ds"
    exporter.write(
        out, episode.schema, [dataclasses.replace(episode, cameras={"scene": track})], lambda _: None
    )
    assert exporter.timings.encoded == 1
    image = next(iter(_decode(out / f"videos/{SCENE}/chunk-000/file-000.mp4").values()))
    assert tuple(int(v) for v in image[240, 320]) == pytest.approx((220, 0, 0), abs=4)
    stats = json.loads((out / "meta/stats.json").read_text())
    assert np.ravel(stats[SCENE]["mean"]) == pytest.approx([220 / 255, 0, 0], abs=3 / 255)


def test_each_camera_is_a_video_key_with_its_own_files(
    regular_episodes: list[EpisodeFrames], tmp_path: Path
) -> None:
    def with_wrist(episode: EpisodeFrames) -> EpisodeFrames:
        scene = episode.cameras["scene"]
        wrist = dataclasses.replace(scene.spec, key="wrist")
        schema = dataclasses.replace(episode.schema, cameras=(scene.spec, wrist))
        cameras = {"scene": scene, "wrist": dataclasses.replace(scene, spec=wrist)}
        return dataclasses.replace(episode, schema=schema, cameras=cameras)

    episodes = [with_wrist(e) for e in regular_episodes]
    exporter = LeRobotExporter()
    exporter.write(tmp_path, episodes[0].schema, episodes, lambda _: None)
    features = _info(tmp_path)["features"]
    assert isinstance(features, dict)
    assert [k for k, ft in features.items() if ft["dtype"] == "video"] == [SCENE, "observation.images.wrist"]
    row = _episodes(tmp_path)[1]
    assert row["videos/observation.images.wrist/from_timestamp"] == row[f"videos/{SCENE}/from_timestamp"]
    assert (tmp_path / "videos/observation.images.wrist/chunk-000/file-000.mp4").is_file()
    assert exporter.validate(tmp_path).problems == ()


def test_files_roll_over_at_the_size_limits(regular_episodes: list[EpisodeFrames], tmp_path: Path) -> None:
    config = LeRobotExportConfig(data_files_size_in_mb=0.001, video_files_size_in_mb=0.001)
    exporter = LeRobotExporter(config)
    exporter.write(tmp_path, regular_episodes[0].schema, regular_episodes, lambda _: None)
    rows = _episodes(tmp_path)
    assert [(r["data/chunk_index"], r["data/file_index"]) for r in rows] == [(0, 0), (0, 1)]
    assert [r[f"videos/{SCENE}/file_index"] for r in rows] == [0, 1]
    assert [r[f"videos/{SCENE}/from_timestamp"] for r in rows] == [0.0, 0.0]
    assert _info(tmp_path)["data_files_size_in_mb"] == 0.001
    assert exporter.validate(tmp_path).problems == ()


def test_copy_video_off_reencodes_one_to_one_recordings(
    regular_episodes: list[EpisodeFrames], tmp_path: Path
) -> None:
    exporter = LeRobotExporter(LeRobotExportConfig(copy_video=False))
    exporter.write(tmp_path, regular_episodes[0].schema, regular_episodes, lambda _: None)
    assert (exporter.timings.remuxed, exporter.timings.encoded) == (0, 2)
    with av.open(str(tmp_path / f"videos/{SCENE}/chunk-000/file-000.mp4")) as container:
        keys = [p.is_keyframe for p in container.demux(video=0) if p.size]
    assert int(np.diff(np.flatnonzero(keys)).max()) <= 2  # a keyframe every 2 frames, as LeRobot encodes
    assert exporter.validate(tmp_path).problems == ()


# -- appending and interruption -----------------------------------------------------------------------


def test_appending_writes_new_files_and_keeps_the_old_ones_byte_for_byte(
    regular_episodes: list[EpisodeFrames], tmp_path: Path
) -> None:
    first, second = regular_episodes
    exporter = LeRobotExporter()
    exporter.write(tmp_path, first.schema, [first], lambda _: None)
    before = _digests(tmp_path)
    assert exporter.existing_episodes(tmp_path) == {first.episode_id}
    exporter.write(tmp_path, first.schema, [first, second], lambda _: None)  # first is already there
    after = _digests(tmp_path)
    rewritten = {p for p in before if after[p] != before[p]}
    assert rewritten == {"meta/info.json", "meta/stats.json"}
    new = set(after) - set(before)
    assert new == {
        "data/chunk-000/file-001.parquet",
        f"videos/{SCENE}/chunk-000/file-001.mp4",
        "meta/episodes/chunk-000/file-001.parquet",
    }
    rows = _episodes(tmp_path)
    assert [r["telerig/episode_id"] for r in rows] == [first.episode_id, second.episode_id]
    assert rows[1]["dataset_from_index"] == first.length
    assert rows[1][f"videos/{SCENE}/from_timestamp"] == 0.0
    assert exporter.validate(tmp_path).problems == ()

    # Stats of the appended dataset are those of exporting both at once.
    both = tmp_path / "both"
    exporter.write(both, first.schema, [first, second], lambda _: None)
    appended = json.loads((tmp_path / "meta/stats.json").read_text())
    at_once = json.loads((both / "meta/stats.json").read_text())
    for key in ("action", "observation.state", SCENE):
        for stat in STAT_KEYS:
            np.testing.assert_allclose(appended[key][stat], at_once[key][stat], rtol=1e-9, atol=1e-12)


def test_ctrl_c_mid_export_leaves_the_previous_dataset_untouched(
    regular_episodes: list[EpisodeFrames], tmp_path: Path
) -> None:
    first, second = regular_episodes
    exporter = LeRobotExporter()
    exporter.write(tmp_path, first.schema, [first], lambda _: None)
    before = _digests(tmp_path)

    def interrupt(_: EpisodeFrames) -> None:
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        exporter.write(tmp_path, first.schema, [second], interrupt)
    assert _digests(tmp_path) == before
    assert not list(tmp_path.glob(".tmp-*"))
    assert exporter.validate(tmp_path).problems == ()


_KILLER = """
import os, pickle, signal, sys
from pathlib import Path
import telerig.export.lerobot as lerobot
episodes = pickle.loads(Path(sys.argv[2]).read_bytes())
real_replace = os.replace
moved = []
def replace(src, dst):
    real_replace(src, dst)
    moved.append(dst)
    if sys.argv[3] == "move" and len(moved) == 2:
        os.kill(os.getpid(), signal.SIGKILL)
lerobot.os.replace = replace
def progress(_):
    if sys.argv[3] == "loop":
        os.kill(os.getpid(), signal.SIGKILL)
lerobot.LeRobotExporter().write(Path(sys.argv[1]), episodes[0].schema, episodes, progress)
"""


@pytest.mark.parametrize("when", ["loop", "move"])
def test_kill_9_mid_export_leaves_the_previous_dataset_readable_and_the_next_run_cleans_up(
    regular_episodes: list[EpisodeFrames], tmp_path: Path, when: str
) -> None:
    import pickle

    first, second = regular_episodes
    out = tmp_path / "ds"
    exporter = LeRobotExporter()
    exporter.write(out, first.schema, [first], lambda _: None)
    before = _digests(out)
    payload = tmp_path / "episodes.pickle"
    payload.write_bytes(pickle.dumps([second]))
    done = subprocess.run(
        [sys.executable, "-c", _KILLER, str(out), str(payload), when],
        check=False,
        capture_output=True,
        timeout=120,
    )
    assert done.returncode == -signal.SIGKILL, done.stderr.decode()[-2000:]
    # The previous dataset: same metadata, same episodes, still valid.
    for path in (
        "meta/info.json",
        "meta/stats.json",
        "meta/tasks.parquet",
        "meta/episodes/chunk-000/file-000.parquet",
    ):
        assert _digests(out)[path] == before[path]
    report = exporter.validate(out)
    assert (report.problems, report.episodes) == ((), 1)
    # The next run deletes what the killed one left and appends.
    exporter.write(out, first.schema, [second], lambda _: None)
    assert not list(out.glob(".tmp-*"))
    assert [r["telerig/episode_id"] for r in _episodes(out)] == [first.episode_id, second.episode_id]
    assert exporter.validate(out).problems == ()


# -- validation ---------------------------------------------------------------------------------------


def _corrupt_info(out: Path, change: dict[str, object]) -> None:
    info = _info(out)
    features = info["features"]
    assert isinstance(features, dict)
    for key, value in change.items():
        features[key] = {**features[key], **value}  # type: ignore[dict-item]
    (out / "meta/info.json").write_text(json.dumps(info))


def test_validate_names_an_action_dimension_other_than_the_robots(
    regular_episodes: list[EpisodeFrames], tmp_path: Path
) -> None:
    exporter = LeRobotExporter()
    exporter.write(tmp_path, regular_episodes[0].schema, regular_episodes[:1], lambda _: None)
    _corrupt_info(tmp_path, {"action": {"shape": [6]}})
    report = exporter.validate(tmp_path)
    assert report.problems[0].startswith("action has shape [6], the robots have 7 entries")
    with pytest.raises(ExportError, match=r"^.*action has shape \[6\]") as err:
        report.raise_if_invalid(tmp_path)
    assert "\n" not in str(err.value)


def test_validate_names_a_video_that_does_not_match_its_timestamps(
    regular_episodes: list[EpisodeFrames], tmp_path: Path
) -> None:
    exporter = LeRobotExporter()
    exporter.write(tmp_path, regular_episodes[0].schema, regular_episodes, lambda _: None)
    path = next(tmp_path.glob("meta/episodes/chunk-000/file-000.parquet"))
    table = pq.read_table(path)
    shifted = table.set_column(
        table.schema.get_field_index(f"videos/{SCENE}/from_timestamp"),
        f"videos/{SCENE}/from_timestamp",
        [[0.0, float(regular_episodes[0].length / 30 + 0.01)]],
    )
    pq.write_table(shifted, path)
    problems = exporter.validate(tmp_path).problems
    assert problems
    assert "has no frame within 0.0001 s" in problems[0]


def test_validate_names_a_dataset_without_info(tmp_path: Path) -> None:
    assert LeRobotExporter().validate(tmp_path).problems == ("no meta/info.json",)


# -- stats as LeRobot computes them -------------------------------------------------------------------


def test_sampled_frames_follow_lerobots_rule() -> None:
    # LeRobot's estimate_num_samples: ~460 frames or fewer -> 100, 1000 -> 177, 2000 -> 299, 20000 -> 1681.
    assert [len(sample_indices(n)) for n in (50, 400, 1000, 2000, 20000)] == [50, 100, 177, 299, 1681]
    assert sample_indices(500)[0] == 0
    assert sample_indices(500)[-1] == 499


def test_image_stats_are_per_channel_over_the_strided_frames_in_unit_range() -> None:
    rng = np.random.default_rng(3)
    images = [(rng.random((480, 640, 3)) * 255).astype(np.uint8) for _ in range(3)]
    stats = ImageStats(480, 640)
    for image in images:
        stats.add(image)
    result = stats.result()
    pixels = np.stack([i[::4, ::4] for i in images]).reshape(-1, 3).astype(np.float64) / 255
    np.testing.assert_allclose(result["mean"].ravel(), pixels.mean(axis=0))
    np.testing.assert_allclose(result["std"].ravel(), pixels.std(axis=0))
    for key, q in (("q01", 0.01), ("q50", 0.5), ("q99", 0.99)):
        np.testing.assert_allclose(result[key].ravel(), np.quantile(pixels, q, axis=0), atol=1e-12)
    assert result["count"].tolist() == [3]


def test_aggregated_stats_equal_the_stats_of_the_concatenation() -> None:
    rng = np.random.default_rng(4)
    parts = [rng.normal(size=(n, 3)) for n in (40, 90, 7)]
    merged = aggregate([vector_stats(p) for p in parts])
    whole = np.concatenate(parts)
    np.testing.assert_allclose(merged["mean"], whole.mean(axis=0))
    np.testing.assert_allclose(merged["std"], whole.std(axis=0))
    np.testing.assert_allclose(merged["min"], whole.min(axis=0))
    assert merged["count"].tolist() == [137]


def test_nan_alignment_errors_are_left_out_of_the_stats() -> None:
    values = np.array([[1.0, np.nan], [3.0, np.nan], [np.nan, np.nan]], dtype=np.float32)
    stats = vector_stats(values)
    assert stats["mean"].tolist() == [2.0, 0.0]
    assert stats["count"].tolist() == [3]


def test_the_lock_refuses_a_second_export_into_the_same_directory(
    regular_episodes: list[EpisodeFrames], tmp_path: Path
) -> None:
    import fcntl

    tmp_path.mkdir(exist_ok=True)
    with open(tmp_path / ".telerig-export.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        with pytest.raises(ExportError, match="another export is writing"):
            LeRobotExporter().write(tmp_path, regular_episodes[0].schema, regular_episodes, lambda _: None)
    assert not (tmp_path / "meta").exists()
    assert os.listdir(tmp_path) == [".telerig-export.lock"]
