"""Every finished episode is indexed; with object storage configured, committed ones are uploaded and
their location in the index becomes the remote URL."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from telerig.config import load_rig
from telerig.config.schema import StorageConfig
from telerig.runtime.rig import RigRuntime
from telerig.store.fingerprint import rig_fingerprint
from telerig.store.index import EpisodeIndex

pytestmark = [pytest.mark.sim, pytest.mark.broker, pytest.mark.slow]


def test_episodes_are_indexed_and_uploaded_to_the_remote(tmp_path: Path) -> None:
    remote = tmp_path / "archive"
    rig = load_rig("demo").model_copy(
        update={"cameras": [], "storage": StorageConfig(remote=str(remote), upload="now")}
    )
    with RigRuntime(rig, data_root=tmp_path / "data") as runtime:
        result = runtime.run_episode(1.5)
        assert runtime.uploads is not None
        deadline = time.monotonic() + 20
        while runtime.uploads.pending() and time.monotonic() < deadline:
            time.sleep(0.1)
    with EpisodeIndex.open(tmp_path / "data") as index:
        record = index.get(result.episode_id)
    assert record.status == "complete"
    # Issue 11 finding 8: the runtime wrote the fingerprint where the index did not look (always NULL).
    assert record.fingerprint == rig_fingerprint(rig).digest
    assert record.session is not None
    assert record.robots == ("ur5e_robotiq85",)
    assert record.location is not None
    assert not record.location.startswith(str(tmp_path / "data"))  # moved to the archive's URL
    assert (remote / result.episode_id / "manifest.json").is_file()
    assert (remote / result.episode_id / "episode.mcap").is_file()
