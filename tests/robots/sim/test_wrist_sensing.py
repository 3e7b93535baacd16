"""The simulated robots' measurements beyond their joints (issue 13): the gripper's measured opening
(arm, gripper alone, hand synergy) and the arm's wrist force/torque sensor, which reads a known load
with the right sign, magnitude and moment."""

from __future__ import annotations

from collections.abc import Iterator

import mujoco
import numpy as np
import pytest

from telerig.ir.types import FloatArray, GripperCommand, JointCommand, Stamp
from telerig.robots.base import GripperSensor, WrenchSensor
from telerig.robots.sim.arm import MujocoArm
from telerig.robots.sim.gripper import MujocoGripper, build_gripper_scene
from telerig.robots.sim.hand import MujocoHand, build_hand_scene
from telerig.robots.sim.humanoid import MujocoHumanoid
from telerig.robots.sim.scene import build_arm_scene

pytestmark = pytest.mark.sim

_G = 9.81  # [m/s^2], the scene's gravity


@pytest.fixture
def arm() -> Iterator[MujocoArm]:
    # A fresh scene per test: a test changes the model (a load's mass).
    with MujocoArm(build_arm_scene(with_cube=False), realtime=False) as driver:
        driver.step(250)  # settle at home
        yield driver


def _world_wrench(arm: MujocoArm) -> tuple[FloatArray, FloatArray]:
    """The sensor's force [N] and torque [N m], rotated from the sensor frame into the world."""
    wrench = arm.read_wrench()
    site = arm.scene.ft_site
    assert site is not None
    with arm.locked() as (_, data):
        rot = data.site(site).xmat.reshape(3, 3).copy()
    return rot @ wrench.force, rot @ wrench.torque


def _body(arm: MujocoArm, name: str) -> int:
    return int(arm.scene.model.body(name).id)


def test_the_arm_offers_its_gripper_opening_and_its_wrist_wrench() -> None:
    driver = MujocoArm(build_arm_scene(with_cube=False), realtime=False)
    assert isinstance(driver, GripperSensor)
    assert isinstance(driver, WrenchSensor)
    assert driver.has_wrench_sensor


def test_without_a_load_the_wrist_sensor_reads_zero(arm: MujocoArm) -> None:
    force, torque = _world_wrench(arm)
    assert np.linalg.norm(force) < 0.05  # the gripper's own 1.5 N weight is compensated
    assert np.linalg.norm(torque) < 0.01
    assert arm.read_wrench().frame_id == "ur5e_sim/ft_sensor"


def test_a_held_mass_reads_its_weight_downward_and_its_moment(arm: MujocoArm) -> None:
    # 0.5 kg more at the grasp point (body gripper/eef): an object of known mass held there.
    eef = _body(arm, "gripper/eef")
    with arm.locked() as (model, data):
        model.body_mass[eef] += 0.5
        mujoco.mj_setConst(model, data)  # the model's subtree masses now include it
    # Tilt the wrist so that the mass hangs off the sensor's axis: a moment to read too.
    tilted = arm.scene.home + np.array([0.0, 0.0, 0.0, 0.6, 0.0, 0.0])
    arm.send(JointCommand(Stamp("test", 0, 0, 0), arm.joint_names, tilted))
    arm.step(1500)
    force, torque = _world_wrench(arm)
    weight = np.array([0.0, 0.0, -0.5 * _G])
    with arm.locked() as (_, data):
        lever = data.xipos[eef] - data.site(arm.scene.ft_site or "").xpos
    np.testing.assert_allclose(force, weight, atol=0.05)
    np.testing.assert_allclose(torque, np.cross(lever, weight), atol=0.02)
    assert np.linalg.norm(np.cross(lever, weight)) > 0.3  # a real moment, not zero compared to zero


def test_a_push_on_a_finger_reads_its_force_and_its_moment_about_the_sensor(arm: MujocoArm) -> None:
    finger = _body(arm, "gripper/right_inner_finger")
    push = np.array([3.0, -2.0, 10.0])  # [N], world frame, at the finger's centre of mass
    with arm.locked() as (_, data):
        data.xfrc_applied[finger, :3] = push
    arm.step(500)
    force, torque = _world_wrench(arm)
    with arm.locked() as (_, data):
        lever = data.xipos[finger] - data.site(arm.scene.ft_site or "").xpos
    np.testing.assert_allclose(force, push, atol=0.1)
    np.testing.assert_allclose(torque, np.cross(lever, push), atol=0.02)
    assert np.linalg.norm(np.cross(lever, push)) > 0.3  # a real moment, not a zero compared to zero


def test_the_measured_opening_follows_the_fingers(arm: MujocoArm) -> None:
    assert arm.read_gripper().opening == pytest.approx(1.0, abs=0.02)
    arm.send_gripper(GripperCommand(Stamp("test", 0, 0, 0), opening=0.0))
    arm.step(500)
    closed = arm.read_gripper()
    assert closed.opening == pytest.approx(0.0, abs=0.05)
    arm.send_gripper(GripperCommand(Stamp("test", 1, 0, 0), opening=0.5))
    arm.step(500)
    assert arm.read_gripper().opening == pytest.approx(0.5, abs=0.05)
    assert arm.read_gripper().stamp.seq > closed.stamp.seq


def test_a_humanoid_without_fingers_or_sensor_offers_neither() -> None:
    humanoid = MujocoHumanoid(realtime=False)
    assert not humanoid.has_gripper
    assert not humanoid.has_wrench_sensor
    assert not humanoid.floating_base  # bolted to its stand: no base_pose stream


def test_a_harnessed_humanoid_measures_its_pelvis_at_standing_height() -> None:
    from telerig.robots.sim.humanoid import build_humanoid_scene

    with MujocoHumanoid(build_humanoid_scene(support="harness"), realtime=False) as g1:
        assert g1.floating_base
        g1.step(250)
        pose = g1.read_base_pose()
    assert pose.frame_id == "world"
    assert pose.position[2] == pytest.approx(g1.standing_height_m, abs=0.02)
    assert abs(np.linalg.norm(pose.orientation) - 1.0) < 1e-9


@pytest.mark.parametrize("opening", [0.3, 0.0])
def test_the_gripper_alone_measures_its_opening(opening: float) -> None:
    with MujocoGripper(build_gripper_scene(with_cube=False), realtime=False) as gripper:
        assert isinstance(gripper, GripperSensor)
        assert gripper.read_gripper().opening == pytest.approx(1.0, abs=0.02)
        gripper.send_gripper(GripperCommand(Stamp("test", 0, 0, 0), opening=opening))
        gripper.step(1000)
        assert gripper.read_gripper().opening == pytest.approx(opening, abs=0.03)


def test_the_gripper_alone_reads_a_grasped_cube_as_an_opening_it_cannot_close() -> None:
    with MujocoGripper(build_gripper_scene(with_cube=True), realtime=False) as gripper:
        gripper.send_gripper(GripperCommand(Stamp("test", 0, 0, 0), opening=0.0))
        gripper.step(1000)
        assert gripper.read_gripper().opening > 0.2  # the cube between the fingers stops them


def test_a_hand_measures_its_synergy_opening() -> None:
    with MujocoHand(build_hand_scene("inspire"), realtime=False) as hand:
        hand.step(200)
        assert hand.read_gripper().opening == pytest.approx(1.0, abs=0.02)
        hand.send_gripper(GripperCommand(Stamp("test", 0, 0, 0), opening=0.0))
        hand.step(1000)
        assert hand.read_gripper().opening < 0.3
