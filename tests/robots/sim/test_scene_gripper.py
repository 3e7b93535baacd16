"""Tests of the gripper-alone scene and its 1-DoF driver."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest

from telerig.ir.types import GripperCommand, JointCommand, Stamp
from telerig.robots.sim.gripper import GripperScene, MujocoGripper, build_gripper_scene

pytestmark = pytest.mark.sim


@pytest.fixture(scope="module")
def bench() -> GripperScene:
    return build_gripper_scene()


@pytest.fixture
def gripper(bench: GripperScene) -> Iterator[MujocoGripper]:
    with MujocoGripper(bench, realtime=False) as driver:
        yield driver


def _close(driver: MujocoGripper) -> None:
    driver.send_gripper(GripperCommand(Stamp.now("test", 0), opening=0.0))
    driver.step(500)


def test_open_pads_straddle_the_cube(gripper: MujocoGripper) -> None:
    with gripper.locked() as (_, data):
        np.testing.assert_allclose(data.site(gripper.scene.grip_site).xpos, data.body("cube").xpos, atol=2e-3)


def test_closing_on_the_cube_stops_at_its_width(gripper: MujocoGripper) -> None:
    with gripper.locked() as (_, data):
        cube_before = data.body("cube").xpos.copy()
    _close(gripper)
    angle = gripper.read_state().positions[0]
    assert 0.2 < angle < 0.6  # blocked by the 5 cm cube, well short of 0.8 rad
    with gripper.locked() as (_, data):
        np.testing.assert_allclose(data.body("cube").xpos, cube_before, atol=2e-3)


def test_closing_without_a_cube_reaches_the_end_stop() -> None:
    with MujocoGripper(build_gripper_scene(with_cube=False), realtime=False) as driver:
        _close(driver)
        assert driver.read_state().positions[0] == pytest.approx(0.8, abs=0.02)


def test_send_sets_the_finger_joint(gripper: MujocoGripper) -> None:
    applied = gripper.send(JointCommand(Stamp.now("test", 0), gripper.joint_names, np.array([0.3])))
    gripper.step(500)
    assert applied.positions[0] == pytest.approx(0.3)
    assert gripper.read_state().positions[0] == pytest.approx(0.3, abs=0.02)


def test_estop_keeps_holding_the_cube(gripper: MujocoGripper) -> None:
    _close(gripper)
    gripper.estop()
    gripper.send_gripper(GripperCommand(Stamp.now("test", 1), opening=1.0))
    held = gripper.read_state().positions[0]
    gripper.step(250)
    assert gripper.read_state().positions[0] == pytest.approx(held, abs=0.01)
