"""Operator session commands from controller buttons end, discard or restart episodes in the runtime."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from telerig.config import load_rig
from telerig.config.schema import EpisodeControlConfig, RigConfig, SessionCommand
from telerig.devices.config import ButtonPressConfig, ScriptedVRConfig
from telerig.robots.sim.arm import MujocoArm
from telerig.runtime.rig import RigRuntime

pytestmark = [pytest.mark.sim, pytest.mark.broker, pytest.mark.slow]


def _rig(button: str, at_s: float) -> RigConfig:
    rig = load_rig("demo").with_isolation("threads")  # the tests read its control node
    device = rig.devices[0]
    assert isinstance(device, ScriptedVRConfig)
    pressing = device.model_copy(
        update={"presses": [ButtonPressConfig(button=button, start_s=at_s, end_s=at_s + 0.3)]}
    )
    return rig.model_copy(
        update={"devices": [pressing], "cameras": [], "episode_control": EpisodeControlConfig()}
    )


@pytest.fixture
def runtime_for(tmp_path: Path) -> Iterator[Callable[..., RigRuntime]]:
    runtimes: list[RigRuntime] = []

    def make(button: str, at_s: float = 1.0) -> RigRuntime:
        runtime = RigRuntime(_rig(button, at_s), data_root=tmp_path).__enter__()
        runtimes.append(runtime)
        return runtime

    yield make
    for runtime in runtimes:
        runtime.close()


def test_a_ends_the_session_and_keeps_the_episode(runtime_for: Callable[..., RigRuntime]) -> None:
    result = runtime_for("a").run_episode(6.0)
    assert result.command is SessionCommand.END_SESSION
    assert result.status == "complete"
    assert result.duration_s < 4.0


def test_y_stops_collection_and_discards_the_episode(
    runtime_for: Callable[..., RigRuntime], tmp_path: Path
) -> None:
    runtime = runtime_for("y")
    result = runtime.run_episode(6.0)
    assert result.command is SessionCommand.STOP_COLLECTION
    assert result.status == "incomplete"
    assert runtime.store.list() == []
    assert (tmp_path / "incomplete" / result.episode_id / "manifest.json").is_file()


def test_b_keeps_the_episode_and_drives_the_arm_home(runtime_for: Callable[..., RigRuntime]) -> None:
    runtime = runtime_for("b", at_s=3.2)  # the gripper is down at the cube
    result = runtime.run_episode(6.0)
    assert result.command is SessionCommand.RESET_AND_NEXT
    assert result.status == "complete"
    arm = runtime.robots["arm0"]
    assert isinstance(arm, MujocoArm)
    np.testing.assert_allclose(arm.read_state().positions, arm.scene.home, atol=0.03)
