"""A real UR5e gets the workspace and self-collision guards of its model, checked against the fake controller.

The guard comes from the robot's config (``model: ur5e_robotiq85``) the way the rig builder makes it
(:func:`telerig.safety.settings.robot_guard`); the chain's output goes to the driver over real
RTDE sockets, and the fake's joints are checked by forward kinematics on the same model.
"""

from __future__ import annotations

import time
from collections.abc import Iterator

import mujoco
import numpy as np
import pytest

from telerig.config.safety import RobotSafetyConfig
from telerig.errors import ConfigError
from telerig.ir.types import JointCommand, Stamp
from telerig.robots.models import arm_kinematics_of
from telerig.robots.models.arm import ArmScene, build_arm_kinematics
from telerig.robots.ur.config import URRtdeConfig
from telerig.robots.ur.driver import URRobot
from telerig.robots.ur.fake import FakeURController
from telerig.robots.ur.limits import UR_JOINT_NAMES
from telerig.safety import SafetyChain
from telerig.safety.settings import robot_guard

pytestmark = pytest.mark.sim

RATE_HZ = 125.0
HOME = (0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0)  # the model's home: gripper down, 0.3 m up
FLOOR_M = 0.2  # workspace floor [m] in the base frame; home's grip site is above it


@pytest.fixture
def fake() -> Iterator[FakeURController]:
    with FakeURController(rtde_port=0, script_port=0, home=HOME) as running:
        yield running


def _robot(fake: FakeURController, model: str | None = "ur5e_robotiq85") -> URRobot:
    cfg = URRtdeConfig.model_validate(
        {
            "id": "ur0",
            "type": "ur_rtde",
            "host": "127.0.0.1",
            "rtde_port": fake.rtde_port,
            "script_port": fake.script_port,
            "control_rate_hz": RATE_HZ,
            "watchdog_s": 0.5,
            "stale_timeout_s": 2.0,
            **({} if model is None else {"model": model}),
        }
    )
    return cfg.build()


def _grip_z(kin: ArmScene, data: mujoco.MjData, q: np.ndarray) -> float:
    data.qpos[:] = q
    mujoco.mj_kinematics(kin.model, data)
    return float(data.site(kin.ee_site).xpos[2])  # kinematic model: base frame = world frame


def _drive(robot: URRobot, chain: SafetyChain, target: np.ndarray, seconds: float) -> list[str]:
    """Request ``target`` every tick for ``seconds``; send the chain's output; return the event codes."""
    codes: list[str] = []
    period = 1.0 / RATE_HZ
    end = time.monotonic() + seconds
    seq = 0
    while time.monotonic() < end:
        now = time.monotonic_ns()
        request = JointCommand(Stamp("test", seq, now, now), UR_JOINT_NAMES, target)
        out = chain.step(request, now_ns=now, measured=robot.read_state())
        codes.extend(e.code for e in out.events)
        if out.command is not None:
            robot.send(out.command)
        seq += 1
        time.sleep(period)
    return codes


def _chain(robot: URRobot, config: RobotSafetyConfig) -> SafetyChain:
    guard = robot_guard(robot, config, where="safety.robots.ur0")
    assert guard is not None
    return SafetyChain.default(
        robot.limits, ramp_duration_s=0.0, ramp_initial_fraction=1.0, period_s=1.0 / RATE_HZ, guard=guard
    )


def test_a_ur5e_config_naming_its_model_has_the_arm_kinematics(fake: FakeURController) -> None:
    with _robot(fake) as robot:
        kin = arm_kinematics_of(robot)
        assert kin is not None
        assert kin.arm_joints == UR_JOINT_NAMES
        assert kin.arm_model == "ur5e_robotiq85"


def test_a_ur_without_a_model_gets_no_guard_and_one_line_saying_what_to_set(fake: FakeURController) -> None:
    with _robot(fake, model=None) as robot:
        config = RobotSafetyConfig.model_validate({"self_collision": True})
        with pytest.raises(ConfigError, match=r"^safety.robots.ur0: .*model: ur5e_robotiq85"):
            robot_guard(robot, config, where="safety.robots.ur0")


def test_an_unknown_model_is_refused_naming_the_known_ones() -> None:
    with pytest.raises(ValueError, match="ur5e_robotiq85"):
        URRtdeConfig.model_validate({"id": "ur0", "type": "ur_rtde", "host": "127.0.0.1", "model": "ur5"})


def test_a_target_below_the_workspace_floor_is_held_and_the_fake_never_goes_there(
    fake: FakeURController,
) -> None:
    kin = build_arm_kinematics("ur5e_robotiq85")
    data = mujoco.MjData(kin.model)
    below = np.array(HOME) + np.array([0.0, 0.6, 0.0, 0.0, 0.0, 0.0])  # shoulder lift: hand goes down
    assert _grip_z(kin, data, below) < FLOOR_M - 0.1  # the request really is outside the box
    config = RobotSafetyConfig.model_validate(
        {"workspace": {"box": {"lower": [-1.5, -1.5, FLOOR_M], "upper": [1.5, 1.5, 1.5]}}}
    )
    with _robot(fake) as robot:
        chain = _chain(robot, config)
        codes = _drive(robot, chain, below, seconds=1.0)
        lowest = _grip_z(kin, data, fake.positions)
        for _ in range(20):  # the fake keeps servoing to the last target: it must stay above too
            lowest = min(lowest, _grip_z(kin, data, fake.positions))
            time.sleep(0.01)
    assert "workspace" in codes
    assert lowest >= FLOOR_M - 1e-3
    assert _grip_z(kin, data, fake.targets) >= FLOOR_M - 1e-3


def test_a_target_into_self_collision_is_held_and_the_fake_never_goes_there(fake: FakeURController) -> None:
    kin = build_arm_kinematics("ur5e_robotiq85")
    config = RobotSafetyConfig.model_validate({"self_collision": True})
    # Elbow folded shut: the forearm goes through the upper arm.
    folded = np.array(HOME) + np.array([0.0, 0.0, 1.5, 0.0, 0.0, 0.0])
    with _robot(fake) as robot:
        guard = robot_guard(robot, config, where="safety.robots.ur0")
        assert guard is not None
        assert guard.worst(folded) is not None  # the request really is in self-collision
        chain = _chain(robot, config)
        worst: list[float] = []
        codes = _drive(robot, chain, folded, seconds=1.0)
        for _ in range(20):
            v = guard.worst(fake.positions)
            worst.append(0.0 if v is None else v.depth_m)
            time.sleep(0.01)
        final = guard.worst(fake.targets)
    assert "self_collision" in codes
    assert max(worst) == 0.0
    assert final is None
    assert kin.arm_joints == UR_JOINT_NAMES
