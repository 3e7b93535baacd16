"""Tests of the simulated robots' configs: model choice, gripper alone, bimanual arms sharing a station."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from telerig.robots.sim.bimanual import BimanualArm
from telerig.robots.sim.config import MujocoArmConfig, MujocoBimanualArmConfig, MujocoGripperConfig
from telerig.robots.sim.gripper import MujocoGripper

pytestmark = pytest.mark.sim


def test_arm_config_builds_the_panda() -> None:
    arm = MujocoArmConfig(id="arm0", model="panda").build()
    assert len(arm.joint_names) == 7
    assert arm.name == "arm0"


def test_arm_config_refuses_an_unknown_model() -> None:
    with pytest.raises(ValidationError, match="panda"):
        MujocoArmConfig(id="arm0", model="kuka")  # type: ignore[arg-type]


def test_gripper_config_builds_a_one_joint_driver() -> None:
    gripper = MujocoGripperConfig(id="grip0").build()
    assert isinstance(gripper, MujocoGripper)
    assert gripper.joint_names == ("gripper/finger_joint",)


def test_gripper_config_checks_the_rates() -> None:
    with pytest.raises(ValidationError, match="whole multiple"):
        MujocoGripperConfig(id="grip0", physics_rate_hz=500, control_rate_hz=300)


def test_bimanual_arm_configs_of_one_station_share_its_physics() -> None:
    left = MujocoBimanualArmConfig(id="left", bench="bench", side="left").build()
    right = MujocoBimanualArmConfig(id="right", bench="bench", side="right").build()
    assert isinstance(left, BimanualArm)
    assert isinstance(right, BimanualArm)
    assert left.physics is right.physics
    assert right.joint_names[0].startswith("right_")
