"""The robomimic export on real demo episodes: the /data and /mask layout robomimic's loader reads, the
stable train/valid split, appends, a kill -9 mid-append, and loading in robomimic itself."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import h5py
import numpy as np
import pytest

from telerig.export.frames import load_episode
from telerig.export.robomimic import DATASET_FILE, ENV_TYPE
from telerig.export.run import EpisodeFilter, build_exporter, export
from telerig.export.schema import SCHEMA_FILE, DatasetSchema
from telerig.store.episodes import EpisodeStore

from .test_hdf5 import kill_mid_write

ROOT = Path(__file__).resolve().parents[2]
ROBOMIMIC_PYTHON = ROOT / ".venv-robomimic" / "bin" / "python"
READER = Path(__file__).with_name("robomimic_reader.py")
#: Every committed episode: on a loaded host the quality gates may move the demo's to failures/.
ALL = EpisodeFilter(include_failures=True)


@pytest.fixture(scope="module")
def episode_dirs(demo_recording: Path) -> dict[str, Path]:
    dirs = {e.id: e.path for e in EpisodeStore(demo_recording).list(include_failures=True)}
    assert len(dirs) == 2
    return dirs


@pytest.fixture(scope="module")
def dataset(demo_recording: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("robomimic") / "dataset"
    export(demo_recording, "robomimic", out, selection=ALL)
    return out / DATASET_FILE


def _mask(f: h5py.File, key: str) -> list[str]:
    return [b.decode() for b in f[f"mask/{key}"][()]]


def _demo_of(f: h5py.File, episode_id: str) -> str:
    return next(name for name, g in f["data"].items() if g.attrs["episode_id"] == episode_id)


def test_data_group_has_total_and_env_args_as_robomimic_reads_them(dataset: Path) -> None:
    with h5py.File(dataset, "r") as f:
        data = f["data"]
        assert sorted(data) == ["demo_0", "demo_1"]
        assert data.attrs["total"] == sum(int(g.attrs["num_samples"]) for g in data.values())
        env = json.loads(data.attrs["env_args"])
        assert env["env_name"] == "demo"
        assert env["type"] == ENV_TYPE
        keys = env["env_kwargs"]["obs_keys"]
        assert keys[0] == "state"
        assert {"arm0_joints", "scene_image"} <= set(keys)
        assert set(keys) == set(data["demo_0/obs"]) == set(data["demo_0/next_obs"])
        assert env["env_kwargs"]["control_freq"] == 30


def test_each_demo_holds_obs_actions_rewards_dones_of_the_episode(
    dataset: Path, episode_dirs: dict[str, Path]
) -> None:
    episode_id, path = next(iter(episode_dirs.items()))
    frames = load_episode(path)
    n = frames.length
    with h5py.File(dataset, "r") as f:
        demo = f["data"][_demo_of(f, episode_id)]
        assert demo.attrs["num_samples"] == n
        np.testing.assert_array_equal(demo["obs/state"][()], frames.state)
        np.testing.assert_array_equal(demo["obs/arm0_joints"][()], frames.state[:, 0:6])
        np.testing.assert_array_equal(demo["actions"][()], frames.action)
        assert demo["actions"].dtype == np.float32
        images = demo["obs/scene_image"]
        assert (images.shape, images.dtype) == ((n, 480, 640, 3), np.uint8)
        assert demo["rewards"].shape == (n,)
        assert demo["dones"][()].tolist() == [0] * (n - 1) + [1]
        assert demo["rewards"][-1] == (1.0 if frames.outcome == "success" else 0.0)


def test_next_obs_is_obs_one_frame_later_without_a_second_copy(dataset: Path) -> None:
    with h5py.File(dataset, "r") as f:
        demo = f["data/demo_0"]
        n = int(demo.attrs["num_samples"])
        for key in ("state", "scene_image"):
            obs, nxt = demo[f"obs/{key}"], demo[f"next_obs/{key}"]
            assert nxt.is_virtual
            assert nxt.shape == obs.shape
            np.testing.assert_array_equal(nxt[: n - 1], obs[1:n])
            np.testing.assert_array_equal(nxt[n - 1], obs[n - 1])


def test_masks_split_train_valid_and_carry_gate_verdicts(
    dataset: Path, episode_dirs: dict[str, Path]
) -> None:
    with h5py.File(dataset, "r") as f:
        train, valid = _mask(f, "train"), _mask(f, "valid")
        assert sorted(train + valid) == ["demo_0", "demo_1"]
        assert valid, "a file of two demos validates on at least one"
        for episode_id, path in episode_dirs.items():
            frames = load_episode(path)
            assert frames.qa is not None
            demo = _demo_of(f, episode_id)
            assert (demo in _mask(f, "passed_qa")) == frames.qa.passed
            assert (demo in _mask(f, "gate_sync")) == (frames.gates["sync"] is not False)
            assert demo in _mask(f, "gate_fall"), "the fall gate does not apply to a fixed arm"
            assert (demo in _mask(f, "success")) == (frames.outcome == "success")
        assert sorted(_mask(f, "gate_sync_train") + _mask(f, "gate_sync_valid")) == sorted(
            _mask(f, "gate_sync")
        )


def test_a_demo_marked_success_gets_the_success_key_and_the_final_reward(
    demo_recording: Path, tmp_path: Path
) -> None:
    root = tmp_path / "data"
    shutil.copytree(demo_recording, root)
    first = EpisodeStore(root).list(include_failures=True)[0]
    manifest = json.loads((first.path / "manifest.json").read_text())
    manifest["extra"]["outcome"] = "success"
    (first.path / "manifest.json").write_text(json.dumps(manifest))
    export(root, "robomimic", tmp_path / "out", selection=ALL)
    with h5py.File(tmp_path / "out" / DATASET_FILE, "r") as f:
        demo = _demo_of(f, first.id)
        assert _mask(f, "success") == [demo]
        assert f[f"data/{demo}/rewards"][-1] == 1.0
        assert f[f"data/{demo}/rewards"][()].sum() == 1.0


def test_rerun_appends_a_demo_and_keeps_every_demo_in_its_split(
    demo_recording: Path, episode_dirs: dict[str, Path], tmp_path: Path
) -> None:
    first, second = list(episode_dirs)
    out = tmp_path / "dataset"
    export(demo_recording, "robomimic", out, selection=EpisodeFilter(ids=(first,), include_failures=True))
    with h5py.File(out / DATASET_FILE, "r") as f:
        assert list(f["data"]) == ["demo_0"]
        before = {k: _mask(f, k) for k in ("train", "valid")}
    summary = export(demo_recording, "robomimic", out, selection=ALL)
    assert (summary.added, summary.skipped) == ((second,), (first,))
    assert build_exporter("robomimic").existing_episodes(out) == {first, second}
    with h5py.File(out / DATASET_FILE, "r") as f:
        assert f["data/demo_1"].attrs["episode_id"] == second
        for key, members in before.items():
            assert set(members) <= set(_mask(f, key)), f"demo_0 left mask/{key}"
        assert _mask(f, "valid"), "once two demos exist one validates"
        assert f["data"].attrs["total"] == sum(int(g.attrs["num_samples"]) for g in f["data"].values())


def test_kill_9_mid_append_leaves_the_previous_file_readable(
    demo_recording: Path, episode_dirs: dict[str, Path], tmp_path: Path
) -> None:
    first, second = list(episode_dirs)
    out = tmp_path / "dataset"
    export(demo_recording, "robomimic", out, selection=EpisodeFilter(ids=(first,), include_failures=True))
    size = (out / DATASET_FILE).stat().st_size
    kill_mid_write(demo_recording, "robomimic", out, grown=size + 1_000_000)
    exporter = build_exporter("robomimic")
    assert exporter.existing_episodes(out) == {first}
    report = exporter.validate(out)
    assert report.ok, report.problems
    assert report.episodes == 1
    summary = export(demo_recording, "robomimic", out, selection=ALL)
    assert summary.added == (second,)
    assert not list(out.glob(".tmp-*"))


def test_a_mask_naming_a_missing_demo_fails_validation(dataset: Path, tmp_path: Path) -> None:
    out = tmp_path / "broken"
    shutil.copytree(dataset.parent, out)
    with h5py.File(out / DATASET_FILE, "a") as f:
        del f["mask/train"]
        f["mask/train"] = np.array([b"demo_0", b"demo_7"])
    problems = build_exporter("robomimic").validate(out).problems
    assert "/mask/train names demo_7, which is not in /data" in problems


def test_num_samples_other_than_the_datasets_fails_validation(dataset: Path, tmp_path: Path) -> None:
    out = tmp_path / "broken"
    shutil.copytree(dataset.parent, out)
    with h5py.File(out / DATASET_FILE, "a") as f:
        n = int(f["data/demo_0"].attrs["num_samples"])
        f["data/demo_0"].attrs["num_samples"] = n + 1
    problems = build_exporter("robomimic").validate(out).problems
    assert any(p.startswith(f"/data/demo_0: /actions has {n} rows for {n + 1} frames") for p in problems)


def test_robomimic_sequence_dataset_loads_every_split(dataset: Path) -> None:
    if not ROBOMIMIC_PYTHON.is_file():
        pytest.fail(
            f"{ROBOMIMIC_PYTHON} is missing: run `make .venv-robomimic/.installed` (make unit does it)"
        )
    done = subprocess.run(
        [str(ROBOMIMIC_PYTHON), str(READER), str(dataset)],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    report = json.loads(done.stdout.strip().splitlines()[-1])
    with h5py.File(dataset, "r") as f:
        lengths = {name: int(g.attrs["num_samples"]) for name, g in f["data"].items()}
        train, valid = _mask(f, "train"), _mask(f, "valid")
    assert report["shapes"]["scene_image"] == [3, 480, 640], "robomimic reads the camera as RGB, channel-last"
    assert report["train"]["demos"] == sorted(train)
    assert report["valid"]["demos"] == sorted(valid)
    assert report["None"]["sequences"] == sum(lengths.values()), "one sequence per frame"
    item = report["None"]
    assert item["obs"]["scene_image"] == [10, 480, 640, 3]
    schema = DatasetSchema.loads((dataset.parent / SCHEMA_FILE).read_bytes())
    assert item["next_obs"]["state"] == [10, len(schema.state)]
    assert item["actions"] == [10, len(schema.action)]


def test_a_normalized_export_keeps_actions_in_robomimics_range(demo_recording: Path, tmp_path: Path) -> None:
    out = tmp_path / "dataset"
    export(demo_recording, "robomimic", out, selection=ALL, normalize=True)
    with h5py.File(out / DATASET_FILE, "r") as f:
        actions = np.concatenate([g["actions"][()] for g in f["data"].values()])
        env = json.loads(f["data"].attrs["env_args"])
    assert env["env_kwargs"]["normalized"] is True
    assert -1.0 <= actions.min() <= actions.max() <= 1.0, "robomimic's get_dataset_info.py refuses others"
    with h5py.File(out / DATASET_FILE, "a") as f:
        f["data/demo_0/actions"][0, 0] = 1.5
    problems = build_exporter("robomimic").validate(out).problems
    assert "/data/demo_0: normalized actions leave [-1, 1]" in problems
