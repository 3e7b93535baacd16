"""A rig's start: the cameras start while the control nodes are built (``StationNodes.open``)."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Literal

import pytest

from telerig.config import load_rig
from telerig.errors import ConfigError
from telerig.runtime.rig import RigRuntime

pytestmark = [pytest.mark.sim, pytest.mark.broker]


@pytest.mark.parametrize("isolation", ["threads", "processes"])
def test_a_camera_that_cannot_start_fails_the_start_in_one_line_and_leaves_nothing_running(
    tmp_path: Path, isolation: Literal["threads", "processes"]
) -> None:
    rig = load_rig("demo").with_isolation(isolation)
    camera = rig.cameras[0].model_copy(update={"camera": "no_such_camera"})
    rig = rig.model_copy(update={"cameras": [camera]})
    before = set(threading.enumerate())
    with (
        pytest.raises(ConfigError, match=r"no_such_camera.*Available: scene") as failed,
        RigRuntime(rig, data_root=tmp_path),
    ):
        pass
    assert "\n" not in str(failed.value)
    deadline = time.monotonic() + 5.0
    while (left := [t.name for t in set(threading.enumerate()) - before if t.is_alive()]) and (
        time.monotonic() < deadline
    ):
        time.sleep(0.05)
    assert not left  # no control loop, camera, bus client or start-up thread outlives the failed start
