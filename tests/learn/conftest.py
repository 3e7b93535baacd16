"""A real LeRobot v3 export of the session's demo recording (tests/conftest.py ``demo_recording``)."""

from __future__ import annotations

from pathlib import Path

import pytest

from telerig.export import EpisodeFilter, export


@pytest.fixture(scope="session")
def lerobot_export(demo_recording: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``telerig export --format lerobot`` of the 2 demo episodes (640x480 scene camera, 30 Hz).

    Read it, never change it: copy it with ``shutil.copytree`` first.
    """
    out = tmp_path_factory.mktemp("learn-lerobot") / "ds"
    export(demo_recording, "lerobot", out, selection=EpisodeFilter(include_failures=True))
    return out
