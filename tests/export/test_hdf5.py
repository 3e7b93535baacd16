"""The HDF5 export (one file per episode) on real demo episodes: layout, values, validation, append,
and a kill -9 in the middle of an append."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import av
import h5py
import numpy as np
import pytest

from telerig.errors import ExportError
from telerig.export.frames import load_episode
from telerig.export.hdf5 import CHANNEL_ORDER, EPISODES_DIR
from telerig.export.run import EpisodeFilter, build_exporter, export
from telerig.export.schema import SCHEMA_FILE, DatasetSchema
from telerig.store.episodes import EpisodeStore

#: Every committed episode: on a loaded host the quality gates may move the demo's to failures/.
ALL = EpisodeFilter(include_failures=True)


@pytest.fixture(scope="module")
def episode_dirs(demo_recording: Path) -> dict[str, Path]:
    return {e.id: e.path for e in EpisodeStore(demo_recording).list(include_failures=True)}


@pytest.fixture(scope="module")
def episode_ids(episode_dirs: dict[str, Path]) -> list[str]:
    assert len(episode_dirs) == 2
    return list(episode_dirs)


@pytest.fixture(scope="module")
def dataset(demo_recording: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("hdf5") / "dataset"
    export(demo_recording, "hdf5", out, selection=ALL)
    return out


def _file(dataset: Path, episode_id: str) -> Path:
    return dataset / EPISODES_DIR / f"{episode_id}.hdf5"


def test_one_file_per_episode_with_observations_actions_metadata_debug(
    dataset: Path, episode_ids: list[str]
) -> None:
    assert sorted(p.stem for p in (dataset / EPISODES_DIR).iterdir()) == sorted(episode_ids)
    with h5py.File(_file(dataset, episode_ids[0]), "r") as f:
        assert {"observations", "actions", "metadata", "debug"} <= set(f)
        assert {"state", "images", "timestamp", "frame_ns"} <= set(f["observations"])
        schema_file = (_file(dataset, episode_ids[0]).parent / str(f.attrs["schema_file"])).resolve()
    assert schema_file == (dataset / SCHEMA_FILE).resolve()
    assert not list(dataset.glob(".tmp-*")), "the scratch folder is removed after the export"


def test_state_actions_and_timestamps_are_the_resampled_episode(
    dataset: Path, demo_recording: Path, episode_dirs: dict[str, Path], episode_ids: list[str]
) -> None:
    frames = load_episode(episode_dirs[episode_ids[0]])
    with h5py.File(_file(dataset, episode_ids[0]), "r") as f:
        np.testing.assert_array_equal(f["observations/state"][()], frames.state)
        np.testing.assert_array_equal(f["actions"][()], frames.action)
        np.testing.assert_array_equal(f["observations/timestamp"][()], frames.timestamp)
        np.testing.assert_array_equal(f["observations/frame_ns"][()], frames.frame_ns)
        assert [str(n) for n in f["observations/state"].attrs["names"]] == list(frames.schema.state_names)
        assert [str(n) for n in f["actions"].attrs["names"]] == list(frames.schema.action_names)
        assert json.loads(f["actions"].attrs["parts"])["arm0.joints"] == [0, 6]


def test_images_are_rgb_uint8_one_gzip_chunk_per_frame_in_video_order(
    dataset: Path, demo_recording: Path, episode_dirs: dict[str, Path], episode_ids: list[str]
) -> None:
    frames = load_episode(episode_dirs[episode_ids[0]])
    track = frames.cameras["scene"]
    with av.open(str(track.path)) as container:
        decoded = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    with h5py.File(_file(dataset, episode_ids[0]), "r") as f:
        images = f["observations/images/scene"]
        assert images.dtype == np.uint8
        assert images.shape == (frames.length, 480, 640, 3)
        assert images.chunks == (1, 480, 640, 3)
        assert images.compression == "gzip"
        assert images.attrs["channel_order"] == CHANNEL_ORDER
        for k in (0, frames.length // 2, frames.length - 1):
            np.testing.assert_array_equal(images[k], decoded[int(track.source_index[k])])
        np.testing.assert_array_equal(f["debug/camera_source_index/scene"][()], track.source_index)


def test_metadata_carries_schema_rig_task_operator_rates_and_manifest(
    dataset: Path, demo_recording: Path, episode_dirs: dict[str, Path], episode_ids: list[str]
) -> None:
    summary = EpisodeStore(demo_recording).get(episode_ids[0])
    frames = load_episode(episode_dirs[episode_ids[0]])
    with h5py.File(_file(dataset, episode_ids[0]), "r") as f:
        meta = f["metadata"]
        schema = DatasetSchema.loads(meta["schema"][()])
        assert schema.to_json() == json.loads((dataset / SCHEMA_FILE).read_text())
        assert meta.attrs["rig"] == "demo"
        assert meta.attrs["fps"] == 30
        assert meta.attrs["task"] == summary.task
        assert meta.attrs["operator"] == summary.operator
        assert meta.attrs["fingerprint"] == schema.fingerprint
        assert json.loads(meta["manifest"][()])["id"] == episode_ids[0]
        rates = json.loads(meta["rates"][()])
        assert rates["dataset_hz"] == 30
        assert rates["cameras_hz"] == {"scene": 30}
        gates = json.loads(meta["gates"][()])
        assert frames.qa is not None, "telerig run checks every committed episode"
        assert gates["passed"] == frames.qa.passed
        assert gates["gates"] == frames.gates
        assert gates["gates"]["sync"] in (True, False)


def test_debug_carries_raw_times_alignment_errors_and_ik_residuals(
    dataset: Path, demo_recording: Path, episode_dirs: dict[str, Path], episode_ids: list[str]
) -> None:
    frames = load_episode(episode_dirs[episode_ids[0]])
    with h5py.File(_file(dataset, episode_ids[0]), "r") as f:
        debug = f["debug"]
        for source, times in frames.raw_time_ns.items():
            np.testing.assert_array_equal(debug["raw_time_ns"][source][()], times)
            np.testing.assert_array_equal(
                debug["alignment_error_ms"][source][()], frames.alignment_error_ms[source]
            )
        np.testing.assert_array_equal(debug["valid"][()], frames.valid)
        residual = debug["residual/arm0"]
        assert residual["capture_ns"].shape[0] > 10, "the demo's control node publishes one per tick"
        assert residual["flagged"].dtype == np.bool_
        assert "position_error_m" in residual
        assert np.all(np.diff(residual["capture_ns"][()]) >= 0)


def test_a_wrong_action_dimension_fails_validation_in_one_line(dataset: Path, tmp_path: Path) -> None:
    broken = tmp_path / "broken"
    shutil.copytree(dataset, broken)
    path = next((broken / EPISODES_DIR).glob("*.hdf5"))
    with h5py.File(path, "a") as f:
        actions = f["actions"][()]
        names = f["actions"].attrs["names"]
        del f["actions"]
        f.create_dataset("actions", data=actions[:, :6]).attrs["names"] = names[:6]
    report = build_exporter("hdf5").validate(broken)
    assert not report.ok
    assert (
        f"{path.name}: /actions has shape ({actions.shape[0]}, 6), the schema's DoF count is 7"
        in report.problems[0]
    )
    with pytest.raises(ExportError) as err:
        report.raise_if_invalid(broken)
    assert "\n" not in str(err.value)


def test_timestamps_that_go_back_fail_validation(dataset: Path, tmp_path: Path) -> None:
    broken = tmp_path / "broken"
    shutil.copytree(dataset, broken)
    path = next((broken / EPISODES_DIR).glob("*.hdf5"))
    with h5py.File(path, "a") as f:
        f["observations/timestamp"][5] = 0.0
    problems = build_exporter("hdf5").validate(broken).problems
    assert len(problems) == 1
    assert "/observations/timestamp is not strictly increasing (frame 5" in problems[0]


def test_a_joint_order_other_than_the_schema_fails_validation(dataset: Path, tmp_path: Path) -> None:
    broken = tmp_path / "broken"
    shutil.copytree(dataset, broken)
    path = next((broken / EPISODES_DIR).glob("*.hdf5"))
    with h5py.File(path, "a") as f:
        names = list(f["observations/state"].attrs["names"])
        f["observations/state"].attrs["names"] = names[::-1]
    problems = build_exporter("hdf5").validate(broken).problems
    assert any("joint order" in p for p in problems)


def test_rerun_appends_new_episodes_and_leaves_written_files_alone(
    demo_recording: Path, episode_ids: list[str], tmp_path: Path
) -> None:
    out = tmp_path / "dataset"
    first = export(
        demo_recording, "hdf5", out, selection=EpisodeFilter(ids=(episode_ids[0],), include_failures=True)
    )
    assert first.added == (episode_ids[0],)
    before = _file(out, episode_ids[0]).stat()
    second = export(demo_recording, "hdf5", out, selection=ALL)
    assert second.added == (episode_ids[1],)
    assert second.skipped == (episode_ids[0],)
    assert second.episodes_total == 2
    after = _file(out, episode_ids[0]).stat()
    assert (after.st_ino, after.st_mtime_ns) == (before.st_ino, before.st_mtime_ns)


_EXPORT_SCRIPT = (
    "import sys; from telerig.export.run import EpisodeFilter, export; "
    "export(*sys.argv[1:4], selection=EpisodeFilter(include_failures=True))"
)


def kill_mid_write(demo_recording: Path, fmt: str, out: Path, grown: int) -> None:
    """Start ``telerig`` exporting in a subprocess and SIGKILL it once a file under its scratch folder
    is bigger than ``grown`` bytes (it is then writing images); fail if it finishes first."""
    proc = subprocess.Popen(
        [sys.executable, "-c", _EXPORT_SCRIPT, str(demo_recording), fmt, str(out)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    scratch = out / f".tmp-{proc.pid}"
    deadline = time.monotonic() + 120
    try:
        while time.monotonic() < deadline:
            sizes = [p.stat().st_size for p in scratch.glob("*")] if scratch.is_dir() else []
            if any(s > grown for s in sizes):
                os.kill(proc.pid, signal.SIGKILL)
                break
            if proc.poll() is not None:
                output = proc.stdout.read().decode() if proc.stdout else ""
                pytest.fail(f"the export finished before it could be killed mid-write:\n{output[-2000:]}")
            time.sleep(0.01)
        else:
            pytest.fail("the export wrote nothing in 120 s")
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait()
        if proc.stdout:
            proc.stdout.close()
    assert proc.returncode == -signal.SIGKILL


def test_kill_9_mid_append_leaves_the_previous_dataset_readable(
    demo_recording: Path, episode_ids: list[str], tmp_path: Path
) -> None:
    out = tmp_path / "dataset"
    export(demo_recording, "hdf5", out, selection=EpisodeFilter(ids=(episode_ids[0],), include_failures=True))
    kill_mid_write(demo_recording, "hdf5", out, grown=1_000_000)
    exporter = build_exporter("hdf5")
    assert exporter.existing_episodes(out) == {episode_ids[0]}
    report = exporter.validate(out)
    assert report.ok, report.problems
    assert report.episodes == 1
    # The next run finishes the job and clears the killed run's scratch folder.
    summary = export(demo_recording, "hdf5", out, selection=ALL)
    assert summary.added == (episode_ids[1],)
    assert not list(out.glob(".tmp-*"))


def test_a_truncated_episode_file_fails_validation_naming_it(dataset: Path, tmp_path: Path) -> None:
    broken = tmp_path / "broken"
    shutil.copytree(dataset, broken)
    path = sorted((broken / EPISODES_DIR).glob("*.hdf5"))[-1]
    with open(path, "r+b") as f:
        f.truncate(4096)
    report = build_exporter("hdf5").validate(broken)
    assert report.problems == (
        f"{EPISODES_DIR}/{path.name}: cannot read it ({_open_error(path)}); delete it and re-run the export",
    )


def _open_error(path: Path) -> str:
    try:
        h5py.File(path, "r").close()
    except OSError as exc:
        return str(exc)
    raise AssertionError(f"{path} opens")
