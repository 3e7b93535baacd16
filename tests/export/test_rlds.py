"""RLDS export of real demo episodes: read back by tensorflow-datasets, appended, killed mid-append."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from telerig.errors import ExportError
from telerig.export.config import RldsExportConfig
from telerig.export.frames import EpisodeFrames, load_episode
from telerig.export.rlds import (
    EPISODES_FILE,
    FEATURES_FILE,
    INFO_FILE,
    RldsExporter,
    dataset_dir,
    dataset_name,
    features_json,
    read_episodes,
    shard_name,
)
from telerig.export.run import EpisodeFilter, export
from telerig.export.schema import SCHEMA_FILE, DatasetSchema
from telerig.store.episodes import EpisodeStore
from telerig.store.qa_file import QaRecord, read_qa, write_qa

pytestmark = [pytest.mark.sim, pytest.mark.broker, pytest.mark.slow]

_REPO = Path(__file__).resolve().parents[2]
_TFDS_PYTHON = _REPO / ".venv-tfds" / "bin" / "python"
_READER = Path(__file__).with_name("tfds_reader.py")
# The demo's episodes may fail a gate on a loaded host (sync): export them all the same.
_ALL = EpisodeFilter(include_failures=True)


def _only(episode_id: str) -> EpisodeFilter:
    return EpisodeFilter(ids=(episode_id,), include_failures=True)


# Mean |difference| of a channel's per-frame mean between a JPEG (quality 95) and its source.
_JPEG_MEAN_TOLERANCE = 1.5


@pytest.fixture(scope="module")
def store(demo_recording: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A copy of the shared demo recording whose first episode has gate verdicts and a score."""
    root = tmp_path_factory.mktemp("rlds-store") / "data"
    shutil.copytree(demo_recording, root)
    first = EpisodeStore(root).list(include_failures=True)[0]
    verdicts = [
        {"gate": "idle", "passed": True, "value": 0.2, "threshold": 0.6, "unit": "fraction"},
        {"gate": "joint_limits", "passed": False, "value": 0.09, "threshold": 0.05, "unit": "fraction"},
        {"gate": "fall", "passed": None, "unit": "m", "detail": "no floating base"},
    ]
    record = QaRecord(
        episode_id=first.id,
        checked_ns=1,
        thresholds_hash="x",
        report={"format": 1, "verdicts": verdicts},
        score={"total": 0.75},
    )
    write_qa(first.path, record)
    return root


@pytest.fixture(scope="module")
def ids(store: Path) -> list[str]:
    return [e.id for e in EpisodeStore(store).list(include_failures=True)]


@pytest.fixture(scope="module")
def exported(store: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Both demo episodes exported in one run."""
    out = tmp_path_factory.mktemp("rlds") / "out"
    export(store, "rlds", out, selection=_ALL)
    return out


def _kill_during_append(store: Path, out: Path, first: str | None, second: str, point: str) -> None:
    """Export ``first`` (unless ``None``), then append ``second`` in a process that SIGKILLs itself
    at ``point``."""
    if first is not None:
        export(store, "rlds", out, selection=_only(first))
    script = f"""
import os, signal
from pathlib import Path
from telerig.export import rlds
from telerig.export.run import EpisodeFilter, export

def die(*args, **kwargs):
    os.kill(os.getpid(), signal.SIGKILL)

point = {point!r}
if point == "after_shards":
    rlds.RldsExporter._commit = die
else:
    write = rlds.write_atomic
    def write_then_maybe_die(path, data):
        if point == "before_info" and path.name == rlds.INFO_FILE:
            die()
        write(path, data)
        if point == "after_info" and path.name == rlds.INFO_FILE:
            die()
    rlds.write_atomic = write_then_maybe_die
only = EpisodeFilter(ids=({second!r},), include_failures=True)
export(Path({str(store)!r}), "rlds", Path({str(out)!r}), selection=only)
"""
    cmd = [sys.executable, "-c", script]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == -9, f"the export was not killed at {point}:\n{done.stderr[-2000:]}"


@pytest.fixture(scope="module")
def killed(store: Path, ids: list[str], tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A one-episode dataset whose append of the second episode was killed just before its
    dataset_info.json was replaced (the new shard, the renamed old one and the index are there)."""
    out = tmp_path_factory.mktemp("rlds-killed") / "out"
    _kill_during_append(store, out, ids[0], ids[1], "before_info")
    return out


def _frames(store: Path, episode_id: str, fps: int) -> EpisodeFrames:
    return load_episode(EpisodeStore(store).episode_dir(episode_id), fps=fps)


def _schema(out: Path) -> DatasetSchema:
    directory = dataset_dir(out)
    assert directory is not None
    return DatasetSchema.loads((directory / SCHEMA_FILE).read_bytes())


def _exporter() -> RldsExporter:
    return RldsExporter(RldsExportConfig())


def _read_with_tfds(builder_dirs: list[Path], tmp: Path) -> list[dict[str, object]]:
    if not _TFDS_PYTHON.is_file():
        pytest.fail(f"{_TFDS_PYTHON} is missing: run `make .venv-tfds/.installed` (tensorflow-datasets)")
    cmd = [str(_TFDS_PYTHON), str(_READER), str(tmp), *map(str, builder_dirs)]
    env = {**os.environ, "TF_CPP_MIN_LOG_LEVEL": "3", "CUDA_VISIBLE_DEVICES": ""}
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=240, env=env, check=False)
    assert done.returncode == 0, f"tensorflow-datasets could not read the export:\n{done.stderr[-3000:]}"
    return [json.loads((tmp / f"{i}.json").read_text()) for i in range(len(builder_dirs))]


def _check_against_source(steps: np.lib.npyio.NpzFile, frames: EpisodeFrames) -> None:
    """Every step TensorFlow decoded equals the resampled episode it came from."""
    n = frames.length
    np.testing.assert_array_equal(steps["steps/observation/state"], frames.state)
    np.testing.assert_array_equal(steps["steps/action"], frames.action)
    np.testing.assert_array_equal(steps["steps/timestamp"], frames.timestamp.astype(np.float32))
    np.testing.assert_array_equal(steps["steps/frame_ns"], frames.frame_ns)
    np.testing.assert_array_equal(steps["steps/valid"], frames.valid)
    edges = np.zeros(n, bool)
    edges[0] = True
    np.testing.assert_array_equal(steps["steps/is_first"], edges)
    np.testing.assert_array_equal(steps["steps/is_last"], edges[::-1])
    np.testing.assert_array_equal(steps["steps/is_terminal"], edges[::-1])  # complete episodes
    np.testing.assert_array_equal(steps["steps/reward"], np.zeros(n, np.float32))  # no outcome marked
    np.testing.assert_array_equal(steps["steps/discount"], np.ones(n, np.float32))
    assert steps["steps/language_instruction"].tolist() == [frames.task.encode()] * n
    worst = np.fmax.reduce(np.stack(list(frames.alignment_error_ms.values())), axis=0)
    np.testing.assert_array_equal(steps["steps/alignment_error_ms"], worst)
    for key, track in frames.cameras.items():
        prefix = f"steps/observation/image_{key}"
        spec = track.spec
        assert steps[f"{prefix}/shape"].tolist() == [n, spec.height, spec.width, 3]
        assert str(steps[f"{prefix}/dtype"]) == "uint8"
        source = list(track.frames())
        source_mean = np.stack([f.reshape(-1, 3).mean(axis=0) for f in source])
        # Per step and channel: catches a swapped channel order or a frame from another step.
        np.testing.assert_allclose(steps[f"{prefix}/mean"], source_mean, atol=_JPEG_MEAN_TOLERANCE)
        for pick, image in zip(steps[f"{prefix}/picks"], steps[f"{prefix}/frames"], strict=True):
            error = np.abs(image.astype(np.int16) - source[int(pick)].astype(np.int16))
            assert error.mean() < 3.0, f"step {pick} of camera {key} differs by {error.mean():.1f} on average"


def test_tensorflow_datasets_reads_every_step_of_the_export(
    store: Path, ids: list[str], exported: Path, killed: Path, tmp_path: Path
) -> None:
    directory = dataset_dir(exported)
    killed_directory = dataset_dir(killed)
    assert directory is not None
    assert killed_directory is not None
    assert directory == exported / "demo" / "1.0.0"
    full, partial = _read_with_tfds([directory, killed_directory], tmp_path)

    assert full["name"] == "demo"
    assert full["version"] == "1.0.0"
    assert full["episodes"] == ids
    assert full["shard_lengths"] == [2]
    schema = _schema(exported)
    sources = {episode_id: _frames(store, episode_id, schema.fps) for episode_id in ids}
    for episode_id in ids:
        with np.load(tmp_path / f"0-{episode_id}.npz") as steps:
            _check_against_source(steps, sources[episode_id])
            assert steps["meta/episode_id"].item() == episode_id.encode()
            assert steps["meta/rig"].item() == b"demo"
            qa = read_qa(EpisodeStore(store).episode_dir(episode_id))
            verdicts = qa.verdicts if qa is not None else ()
            passed = [v.gate.encode() for v in verdicts if v.passed is True]
            failed = [v.gate.encode() for v in verdicts if v.passed is False]
            assert steps["meta/gates_passed"].tolist() == passed
            assert steps["meta/gates_failed"].tolist() == failed
            if qa is None or qa.score_total is None:
                assert np.isnan(steps["meta/quality"])
            else:
                assert steps["meta/quality"] == np.float32(qa.score_total)
            if episode_id == ids[0]:  # the verdicts the store fixture wrote
                assert steps["meta/quality"] == np.float32(0.75)
                assert steps["meta/gates_failed"].tolist() == [b"joint_limits"]

    # The append killed before its commit: TFDS sees the first episode only, intact.
    assert partial["episodes"] == [ids[0]]
    assert partial["shard_lengths"] == [1]
    with np.load(tmp_path / f"1-{ids[0]}.npz") as steps:
        _check_against_source(steps, sources[ids[0]])


def test_export_validates_and_lists_its_episodes(exported: Path, ids: list[str]) -> None:
    exporter = _exporter()
    report = exporter.validate(exported)
    assert report.ok, report.problems
    assert report.episodes == 2
    assert exporter.existing_episodes(exported) == set(ids)
    assert exporter.schema_path(exported) == exported / "demo" / "1.0.0" / SCHEMA_FILE


def test_append_adds_a_shard_and_renames_the_old_one(store: Path, ids: list[str], tmp_path: Path) -> None:
    out = tmp_path / "out"
    export(store, "rlds", out, selection=_only(ids[0]))
    directory = out / "demo" / "1.0.0"
    first_shard = (directory / shard_name("demo", 0, 1)).read_bytes()

    summary = export(store, "rlds", out, selection=_ALL)

    assert summary.added == (ids[1],)
    assert summary.skipped == (ids[0],)
    assert summary.episodes_total == 2
    shards = sorted(p.name for p in directory.glob("demo-train.tfrecord-*"))
    assert shards == [shard_name("demo", 0, 2), shard_name("demo", 1, 2)]
    assert (directory / shard_name("demo", 0, 2)).read_bytes() == first_shard  # not rewritten
    info = json.loads((directory / INFO_FILE).read_text())
    assert info["splits"][0]["shardLengths"] == ["1", "1"]
    assert int(info["splits"][0]["numBytes"]) == sum(p.stat().st_size for p in directory.glob("demo-train.*"))
    stored = [e["episode_metadata/episode_id"].as_bytes("episode_id")[0] for e in read_episodes(directory)]
    assert stored == [i.encode() for i in ids]

    again = export(store, "rlds", out, selection=_ALL)
    assert again.added == ()
    assert again.skipped == tuple(ids)


@pytest.mark.parametrize(
    ("point", "committed"), [("after_shards", False), ("before_info", False), ("after_info", True)]
)
def test_kill_9_during_an_append_leaves_a_readable_dataset(
    store: Path, ids: list[str], tmp_path: Path, point: str, committed: bool
) -> None:
    out = tmp_path / "out"
    _kill_during_append(store, out, ids[0], ids[1], point)

    exporter = _exporter()
    report = exporter.validate(out)
    assert report.ok, report.problems
    expected = set(ids) if committed else {ids[0]}
    assert exporter.existing_episodes(out) == expected
    assert report.episodes == len(expected)

    # The next run finishes the job and removes the leftovers.
    summary = export(store, "rlds", out, selection=_ALL)
    assert set(summary.added) == set(ids) - expected
    directory = out / "demo" / "1.0.0"
    files = {p.name for p in directory.iterdir()}
    shards = {shard_name("demo", 0, 2), shard_name("demo", 1, 2)}
    dataset = {EPISODES_FILE, FEATURES_FILE, INFO_FILE, SCHEMA_FILE, *shards}
    if committed:
        # Nothing was left to write, so nothing ran to tidy up: what the killed run left is its
        # empty temp dir and the first shard's old name, a second link to the same file.
        old = directory / shard_name("demo", 0, 1)
        assert old.stat().st_ino == (directory / shard_name("demo", 0, 2)).stat().st_ino
        (tmp,) = files - dataset - {old.name}
        assert tmp.startswith(".tmp-")
        assert not any((directory / tmp).iterdir())
    else:
        assert files == dataset
    assert exporter.validate(out).ok


def test_kill_9_during_the_first_export_leaves_nothing_a_rerun_trips_on(
    store: Path, ids: list[str], tmp_path: Path
) -> None:
    out = tmp_path / "out"
    _kill_during_append(store, out, None, ids[1], "before_info")
    exporter = _exporter()
    assert exporter.existing_episodes(out) == set()
    assert exporter.validate(out).problems == (f"no RLDS dataset ({INFO_FILE}) under {out}",)

    summary = export(store, "rlds", out, selection=_only(ids[1]))

    assert summary.added == (ids[1],)
    files = {p.name for p in (out / "demo" / "1.0.0").iterdir()}
    assert files == {EPISODES_FILE, FEATURES_FILE, INFO_FILE, SCHEMA_FILE, shard_name("demo", 0, 1)}


def test_validate_names_a_corrupt_shard(store: Path, ids: list[str], tmp_path: Path) -> None:
    out = tmp_path / "out"
    export(store, "rlds", out, selection=_only(ids[1]))
    shard = out / "demo" / "1.0.0" / shard_name("demo", 0, 1)
    data = bytearray(shard.read_bytes())
    data[len(data) // 2] ^= 0xFF
    shard.write_bytes(bytes(data))

    report = _exporter().validate(out)

    assert report.problems == (f"{shard}: record 0 fails its CRC; re-export this shard",)
    with pytest.raises(ExportError, match="fails its CRC"):
        report.raise_if_invalid(out)


def test_validate_checks_the_action_dimension_against_the_schema(
    store: Path, ids: list[str], tmp_path: Path
) -> None:
    out = tmp_path / "out"
    export(store, "rlds", out, selection=_only(ids[1]))
    schema_file = out / "demo" / "1.0.0" / SCHEMA_FILE
    schema = json.loads(schema_file.read_text())
    schema["action"] = schema["action"][:-1]  # one joint fewer than the shards hold
    schema_file.write_text(json.dumps(schema))

    problems = _exporter().validate(out).problems

    assert f"{FEATURES_FILE} does not match {SCHEMA_FILE}" in problems
    assert any("steps/action has" in p and "(the DoF count)" in p for p in problems), problems


def test_append_with_another_image_format_is_refused(store: Path, ids: list[str], tmp_path: Path) -> None:
    out = tmp_path / "out"
    export(store, "rlds", out, selection=_only(ids[1]))
    with pytest.raises(ExportError, match="stores jpeg images; export with image_format: jpeg"):
        export(store, "rlds", out, selection=_only(ids[0]), options={"image_format": "png"})
    assert _exporter().existing_episodes(out) == {ids[1]}


def test_png_images_are_the_recorded_frames_exactly(store: Path, ids: list[str], tmp_path: Path) -> None:
    from io import BytesIO

    from PIL import Image

    out = tmp_path / "out"
    export(store, "rlds", out, selection=_only(ids[1]), options={"image_format": "png"})
    directory = out / "demo" / "1.0.0"
    (episode,) = list(read_episodes(directory))
    frames = _frames(store, ids[1], _schema(out).fps)
    for key, track in frames.cameras.items():
        stored = episode[f"steps/observation/image_{key}"].as_bytes(key)
        for k, source in enumerate(track.frames()):
            with Image.open(BytesIO(stored[k])) as image:
                assert image.format == "PNG"
                np.testing.assert_array_equal(np.asarray(image), source, err_msg=f"step {k}")


@pytest.mark.parametrize(
    ("rig", "name"), [("demo", "demo"), ("Bimanual-Bench 2", "bimanual_bench_2"), ("2arms", "rig_2arms")]
)
def test_dataset_name_is_a_tfds_identifier_from_the_rig(rig: str, name: str) -> None:
    assert dataset_name(rig) == name


def test_a_camera_key_that_cannot_name_a_feature_is_refused(exported: Path) -> None:
    schema = _schema(exported)
    data = json.loads(schema.dumps())
    data["cameras"][0]["key"] = "scene/left"
    with pytest.raises(ExportError, match="camera 'scene/left' cannot name an RLDS feature"):
        features_json(DatasetSchema.loads(json.dumps(data)), "jpeg")
