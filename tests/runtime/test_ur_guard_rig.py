"""A real UR5e rig gets the workspace guard of its model: the demo's pick against the fake RTDE controller.

The rig is the demo with ``arm0`` a ``ur_rtde`` robot (``model: ur5e_robotiq85``) served by
:class:`~telerig.robots.ur.fake.FakeURController` over real sockets; the scripted operator reaches
down to the cube (about 0.03 m above the base plane) through a workspace floor at 0.15 m. The fake's
joints are watched by forward kinematics on the same model: they never take the gripper below it.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from typing import Any

import mujoco
import numpy as np
import pytest

from telerig.config import load_rig
from telerig.config.schema import RigConfig
from telerig.errors import ConfigError
from telerig.robots.models.arm import build_arm_kinematics
from telerig.robots.ur.driver import URRobot
from telerig.robots.ur.fake import FakeURController
from telerig.runtime.rig import RigRuntime

pytestmark = [pytest.mark.sim, pytest.mark.broker, pytest.mark.slow]

_FLOOR_M = 0.15  # [m] in the base frame; the scripted pick reaches down to ~0.03 m
_HOME = (0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0)


@pytest.fixture
def fake() -> Iterator[FakeURController]:
    with FakeURController(rtde_port=0, script_port=0, gripper_port=0, home=_HOME) as running:
        yield running


def _rig(fake: FakeURController, *, model: str | None) -> RigConfig:
    raw = load_rig("demo").with_isolation("threads").model_dump(mode="json", exclude_none=True)
    raw["cameras"] = []
    ur: dict[str, Any] = {
        "id": "arm0",
        "type": "ur_rtde",
        "host": "127.0.0.1",
        "rtde_port": fake.rtde_port,
        "script_port": fake.script_port,
        "gripper": "robotiq_urcap",
        "gripper_port": fake.gripper_port,
        "control_rate_hz": 125.0,
        "watchdog_s": 0.5,
        "stale_timeout_s": 2.0,
    }
    if model is not None:
        ur["model"] = model
    raw["robots"] = [ur]
    raw["safety"]["robots"] = {
        "arm0": {"workspace": {"box": {"lower": [-1.0, -1.0, _FLOOR_M], "upper": [1.0, 1.0, 1.5]}}}
    }
    return RigConfig.model_validate(raw)


def test_the_workspace_floor_holds_a_real_ur5e_above_it(fake: FakeURController, tmp_path: Any) -> None:
    kin = build_arm_kinematics("ur5e_robotiq85")
    data = mujoco.MjData(kin.model)
    lowest = [np.inf]
    done = threading.Event()

    def watch() -> None:
        while not done.wait(0.004):
            data.qpos[:] = fake.positions
            mujoco.mj_kinematics(kin.model, data)
            lowest[0] = min(lowest[0], float(data.site(kin.ee_site).xpos[2]))  # base frame = world

    with RigRuntime(_rig(fake, model="ur5e_robotiq85"), data_root=tmp_path) as runtime:
        assert isinstance(runtime.robots["arm0"], URRobot)
        watcher = threading.Thread(target=watch)
        watcher.start()
        try:
            runtime.run_episode(6.0)  # the scripted pick reaches down at ~4 s
        finally:
            done.set()
            watcher.join()
        counts = runtime.controls["arm0"].safety.counts
    assert counts["workspace"] > 0
    assert lowest[0] > _FLOOR_M - 0.01  # never below the floor (braking stays inside the margin)


def test_a_ur_rig_with_a_workspace_but_no_model_says_what_to_set(
    fake: FakeURController, tmp_path: Any
) -> None:
    rig = _rig(fake, model=None)
    ik = r"arm IK needs an arm model; robot 'arm0' names none .*model: ur5e"
    with pytest.raises(ConfigError, match=ik), RigRuntime(rig, data_root=tmp_path):
        pass
    # With the robot in a process of its own, the child's ConfigError reaches the station as one.
    isolated = rig.with_isolation("processes")
    with pytest.raises(ConfigError, match=ik), RigRuntime(isolated, data_root=tmp_path):
        pass
    unbound = RigConfig.model_validate({**rig.model_dump(mode="json", exclude_none=True), "bindings": []})
    guard = r"safety.robots.arm0: .*model: ur5e_robotiq85"
    with pytest.raises(ConfigError, match=guard), RigRuntime(unbound, data_root=tmp_path):
        pass
