"""``telerig view DATASET``: each format's export of real demo episodes as a Rerun .rrd, read back
with rerun's own reader and compared with the episodes the export was made from."""

from __future__ import annotations

import math
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from telerig.cli.main import main
from telerig.export import EpisodeFilter, export, load_episode
from telerig.export.view_base import end_effector_path
from telerig.export.view_dataset import DATASET_TIMELINE, IMAGE_RATE_HZ, dataset_format
from telerig.store.episodes import EpisodeStore

pytestmark = [pytest.mark.sim, pytest.mark.broker, pytest.mark.slow]

_UR5E_REACH_M = 0.85 + 0.25


def _chunks(path: Path) -> tuple[Counter[str], dict[str, list[Any]], dict[str, list[Any]]]:
    """Rows per temporal entity, temporal record batches and static record batches per entity."""
    from rerun.chunk import RrdReader

    rows: Counter[str] = Counter()
    temporal: dict[str, list[Any]] = {}
    static: dict[str, list[Any]] = {}
    for chunk in RrdReader(path).stream():
        batch = chunk.to_record_batch()
        if chunk.is_static:
            static.setdefault(chunk.entity_path, []).append(batch)
        else:
            assert DATASET_TIMELINE in chunk.timeline_names
            rows[chunk.entity_path] += chunk.num_rows
            temporal.setdefault(chunk.entity_path, []).append(batch)
    return rows, temporal, static


def _scalars(batches: list[Any]) -> tuple[np.ndarray, np.ndarray]:
    t = np.concatenate([b.column(DATASET_TIMELINE).cast("int64").to_numpy() for b in batches]) / 1e9
    v = np.concatenate([np.array(b.column("Scalars:scalars").to_pylist()).ravel() for b in batches])
    order = np.argsort(t, kind="stable")
    return t[order], v[order]


@pytest.mark.parametrize("fmt", ["lerobot", "hdf5", "robomimic", "rlds"])
def test_view_of_an_export_shows_every_frame_of_every_episode(
    fmt: str, demo_recording: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / fmt
    # Every episode, also those the station's quality gates moved to the failures partition.
    summary = export(demo_recording, fmt, out, selection=EpisodeFilter(include_failures=True))
    found, schema = dataset_format(out)
    assert found == fmt
    rrd = tmp_path / f"{fmt}.rrd"
    assert main(["view", str(out), "--out", str(rrd)]) == 0
    printed = capsys.readouterr().out
    assert ("video: asset" if fmt == "lerobot" else f"video: frames at {IMAGE_RATE_HZ:g} Hz") in printed
    rows, temporal, static = _chunks(rrd)

    episodes = {e.id: e for e in EpisodeStore(demo_recording).list(include_failures=True)}
    assert set(summary.added) == set(episodes)
    for episode_id in summary.added:
        frames = load_episode(episodes[episode_id].path, fps=schema.fps)
        n = frames.length
        base = f"/episodes/{episode_id}"
        for vector, names, values in (
            ("state", schema.state_names, frames.state),
            ("action", schema.action_names, frames.action),
        ):
            for j, name in enumerate(names):
                t, v = _scalars(temporal[f"{base}/{vector}/{name}"])
                assert len(v) == n, (vector, name)
                np.testing.assert_allclose(t, np.arange(n) / schema.fps, atol=1e-6)
                np.testing.assert_allclose(v, values[:, j], rtol=1e-6, atol=1e-6)
        (camera,) = schema.cameras
        shown = rows[f"{base}/cameras/{camera.key}"]
        assert shown == (n if fmt == "lerobot" else math.ceil(n / round(schema.fps / IMAGE_RATE_HZ)))
        (strip,) = static[f"{base}/robots/arm0/ee_path"]
        path = np.array(strip.column("LineStrips3D:strips")[0].as_py()[0])
        assert path.shape == (n, 3)
        assert np.linalg.norm(path, axis=1).max() < _UR5E_REACH_M
        arm = [i for i, s in enumerate(schema.state) if s.robot == "arm0" and s.part == "joints"]
        names = tuple(schema.state_names[i] for i in arm)
        expected = end_effector_path(schema.robots["arm0"], names, frames.state[:, arm].astype(np.float64))
        np.testing.assert_allclose(path, expected, atol=1e-5)  # the exported state's joints, in order

    if fmt == "lerobot":  # frame references point into the dataset's MP4, inside its length
        import rerun as rr

        # One asset per MP4 file; an episode copied from its recording and one re-encoded (its
        # camera dropped a frame on a loaded machine) lie in different files.
        assets = {e.lstrip("/") for e in static if e.startswith("/videos/")}
        assert assets
        last = {
            entity: rr.AssetVideo(path=out / f"{entity}.mp4").read_frame_timestamps_nanos().max()
            for entity in assets  # videos/<key>/chunk-i/file-j
        }
        used: set[str] = set()
        for episode_id in summary.added:
            references: set[str] = set()
            for batch in temporal[f"/episodes/{episode_id}/cameras/{camera.key}"]:
                (entity,) = set(batch.column("VideoFrameReference:video_reference").to_pylist()[0])
                references.add(entity)
                ts = np.array(batch.column("VideoFrameReference:timestamp").to_pylist()).ravel()
                assert ts.max() <= last[entity] + 1e9 / schema.fps
            assert len(references) == 1, references  # an episode lies in one file
            used |= references
        assert used == assets


def test_a_directory_of_no_format_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "robot_schema.json").write_text("{}")
    assert main(["view", str(tmp_path), "--out", str(tmp_path / "x.rrd")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
