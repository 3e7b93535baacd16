"""The typed manifest extra read back from disk: a camera's per-episode counters and the samples left
out before the start, as written, and one line naming the field when a file carries garbage there."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest

from telerig.errors import RecordingError
from telerig.store.episodes import EpisodeStore
from telerig.store.manifest_extra import EpisodeExtra


def _committed(root: Path, extra: dict[str, Any]) -> EpisodeExtra:
    store = EpisodeStore(root)
    draft = store.begin(rig="rig", task="t", operator="o")
    manifest = draft.commit(extra)
    return EpisodeExtra.of(store.get(manifest.id))


def test_camera_counters_and_samples_before_start_read_back(tmp_path: Path) -> None:
    camera = {"file": "cameras/scene.mp4", "frames": 448, "skipped": 2, "late": 1, "callback_errors": 0}
    extra = _committed(tmp_path, {"cameras": {"scene": camera}, "samples_before_start": 7})
    scene = extra.cameras["scene"]
    assert (scene.frames, scene.skipped, scene.late, scene.callback_errors) == (448, 2, 1, 0)
    assert extra.samples_before_start == 7
    # Written before cameras counted: None, not 0 (nothing was counted).
    old = _committed(tmp_path, {"cameras": {"scene": {"file": "cameras/scene.mp4", "frames": 3}}})
    assert (old.cameras["scene"].skipped, old.cameras["scene"].late, old.samples_before_start) == (
        None,
        None,
        0,
    )


@pytest.mark.parametrize(
    ("extra", "field"),
    [
        ({"cameras": {"scene": {"file": "c.mp4", "skipped": -1}}}, "extra.cameras.scene.skipped"),
        ({"cameras": {"scene": {"file": "c.mp4", "late": "many"}}}, "extra.cameras.scene.late"),
        (
            {"cameras": {"scene": {"file": "c.mp4", "callback_errors": 1e300}}},
            "extra.cameras.scene.callback_errors",
        ),
        ({"samples_before_start": -5}, "extra.samples_before_start"),
        ({"samples_before_start": [1, 2]}, "extra.samples_before_start"),
    ],
)
def test_garbage_counters_name_the_field(tmp_path: Path, extra: dict[str, Any], field: str) -> None:
    with pytest.raises(RecordingError, match=rf"manifest {re.escape(field)}: .*this version of telerig"):
        _committed(tmp_path, extra)
