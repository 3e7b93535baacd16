"""Tests of the MuJoCo UR5e + Robotiq scene and its driver."""

from __future__ import annotations

import importlib.util
import re
import time
from collections.abc import Iterator
from pathlib import Path

import mujoco
import numpy as np
import pytest

from telerig.errors import DependencyError, RobotError
from telerig.ir.types import GripperCommand, JointCommand, Stamp
from telerig.robots.base import RobotDriver
from telerig.robots.models import arm as arm_model_module
from telerig.robots.models.arm import ArmScene
from telerig.robots.sim.arm import MujocoArm
from telerig.robots.sim.scene import build_arm_scene

pytestmark = pytest.mark.sim


@pytest.fixture(scope="module")
def arm_scene() -> ArmScene:
    return build_arm_scene()


@pytest.fixture
def arm(arm_scene: ArmScene) -> Iterator[MujocoArm]:
    with MujocoArm(arm_scene, realtime=False) as driver:
        yield driver


def _command(names: tuple[str, ...], positions: object) -> JointCommand:
    return JointCommand(Stamp.now("test", 0), names, np.asarray(positions, dtype=np.float64))


def _finger_positions(arm: MujocoArm) -> np.ndarray:
    with arm.locked() as (model, data):
        return np.array([data.qpos[model.joint(j).qposadr[0]] for j in arm.scene.gripper_joints])


def test_scene_names_its_parts(arm_scene: ArmScene) -> None:
    model = arm_scene.model
    assert arm_scene.cameras[0] == "scene"
    assert model.site(arm_scene.ee_site).id >= 0
    assert len(arm_scene.arm_actuators) == len(arm_scene.arm_joints) == 6
    assert model.body("cube").id >= 0
    assert model.vis.global_.offwidth >= 640
    assert model.vis.global_.offheight >= 480
    assert model.opt.timestep == pytest.approx(0.002)


def test_scene_timestep_is_configurable() -> None:
    assert build_arm_scene(timestep=0.001, with_cube=False).model.opt.timestep == pytest.approx(0.001)


def test_home_holds_gripper_above_table_pointing_down(arm: MujocoArm) -> None:
    arm.step(250)
    with arm.locked() as (model, data):
        site = data.site(arm.scene.ee_site)
        table_top = data.geom("table_top").xpos[2] + model.geom("table_top").size[2]
        assert site.xpos[2] - table_top > 0.2
        assert site.xmat.reshape(3, 3)[:, 2] @ np.array([0.0, 0.0, -1.0]) > 0.99


def test_missing_robosuite_raises_dependency_error(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *args: None)
    with pytest.raises(DependencyError, match=re.escape("pip install --no-deps robosuite==1.5.2")):
        build_arm_scene()


def test_missing_model_file_raises_robot_error(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setattr(arm_model_module, "robosuite_assets", lambda: tmp_path)
    with pytest.raises(RobotError, match=re.escape(str(tmp_path / "robots" / "ur5e" / "robot.xml"))):
        build_arm_scene()


def test_driver_satisfies_protocol(arm: MujocoArm) -> None:
    assert isinstance(arm, RobotDriver)


def test_gripper_closes_and_opens(arm: MujocoArm) -> None:
    open_fingers = _finger_positions(arm)
    arm.send_gripper(GripperCommand(Stamp.now("test", 0), opening=0.0))
    arm.step(400)
    closed_fingers = _finger_positions(arm)
    arm.send_gripper(GripperCommand(Stamp.now("test", 1), opening=1.0))
    arm.step(400)
    reopened = _finger_positions(arm)
    assert np.all(closed_fingers - open_fingers > 0.7)
    np.testing.assert_allclose(reopened, open_fingers, atol=0.01)


def test_send_gripper_returns_clipped_opening(arm: MujocoArm) -> None:
    applied = arm.send_gripper(GripperCommand(Stamp.now("test", 0), opening=1.7))
    assert applied.opening == pytest.approx(1.0)
    assert applied.stamp.source_id == arm.name


def test_send_returns_positions_clipped_to_ctrlrange(arm: MujocoArm) -> None:
    request = np.array([10.0, -10.0, 4.0, 0.1, 0.2, 0.3])
    applied = arm.send(_command(arm.joint_names, request))
    upper = arm.limits.upper
    np.testing.assert_allclose(applied.positions[:3], [upper[0], -upper[1], upper[2]])
    np.testing.assert_allclose(applied.positions[3:], request[3:])
    assert applied.stamp.source_id == arm.name
    assert applied.stamp.capture_ns > 0


def test_send_accepts_a_subset_of_joints(arm: MujocoArm) -> None:
    applied = arm.send(_command(("elbow_joint",), [1.2]))
    assert applied.names == ("elbow_joint",)
    np.testing.assert_allclose(applied.positions, [1.2])


def test_send_unknown_joint_names_available_ones(arm: MujocoArm) -> None:
    with pytest.raises(RobotError, match="Available: shoulder_pan_joint"):
        arm.send(_command(("nope",), [0.0]))


def test_arm_tracks_position_targets(arm: MujocoArm) -> None:
    target = arm.scene.home + np.array([0.3, -0.2, 0.2, 0.1, -0.1, 0.3])
    arm.send(_command(arm.joint_names, target))
    arm.step(1000)
    state = arm.read_state()
    np.testing.assert_allclose(state.positions, target, atol=2e-3)
    assert state.stamp.device_ns == round(1000 * 0.002 * 1e9)


def test_estop_latches_and_holds_position(arm: MujocoArm) -> None:
    arm.send(_command(arm.joint_names, arm.scene.home + 0.5))
    arm.step(50)
    arm.estop()
    held = arm.read_state().positions
    applied = arm.send(_command(arm.joint_names, arm.scene.home - 0.5))
    arm.step(500)
    np.testing.assert_allclose(applied.positions, held)
    np.testing.assert_allclose(arm.read_state().positions, held, atol=0.02)
    assert arm.estopped


def test_reset_estop_accepts_commands_again(arm: MujocoArm) -> None:
    arm.estop()
    arm.reset_estop()
    applied = arm.send(_command(arm.joint_names, arm.scene.home + 0.1))
    np.testing.assert_allclose(applied.positions, arm.scene.home + 0.1)


def test_stepping_is_deterministic(arm_scene: ArmScene) -> None:
    def run() -> np.ndarray:
        with MujocoArm(arm_scene, realtime=False) as driver:
            driver.send(_command(driver.joint_names, arm_scene.home + 0.2))
            driver.send_gripper(GripperCommand(Stamp.now("test", 0), opening=0.3))
            driver.step(300)
            with driver.locked() as (_, data):
                return data.qpos.copy()

    np.testing.assert_array_equal(run(), run())


def test_step_refused_in_realtime_mode(arm_scene: ArmScene) -> None:
    with MujocoArm(arm_scene) as driver, pytest.raises(RobotError, match="realtime=False"):
        driver.step()


def test_send_before_connect_raises(arm_scene: ArmScene) -> None:
    driver = MujocoArm(arm_scene, realtime=False)
    with pytest.raises(RobotError, match="connect"):
        driver.read_state()


def test_realtime_thread_steps_until_closed(arm_scene: ArmScene) -> None:
    driver = MujocoArm(arm_scene)
    driver.connect()
    deadline = time.monotonic() + 5.0
    while driver.stats().steps < 10 and time.monotonic() < deadline:
        time.sleep(0.01)
    driver.close()
    steps = driver.stats().steps
    driver.close()
    assert steps >= 10
    assert driver.stats().steps == steps


def test_scene_camera_renders_the_arm(arm: MujocoArm) -> None:
    with arm.locked() as (model, _):
        renderer = mujoco.Renderer(model, 480, 640)
    try:
        with arm.locked() as (_, data):
            renderer.update_scene(data, "scene")
        image = renderer.render()
    finally:
        renderer.close()
    assert image.shape == (480, 640, 3)
    assert image.std() > 10


@pytest.mark.sim
def test_reset_objects_puts_the_cube_back_without_moving_the_arm() -> None:
    arm = MujocoArm(realtime=False)
    arm.connect()
    try:
        with arm.locked() as (model, data):
            cube = next(j for j in range(model.njnt) if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE)
            adr = model.jnt_qposadr[cube]
            data.qpos[adr : adr + 3] += [0.1, -0.2, 0.0]
        before = arm.read_state().positions.copy()
        arm.reset_objects()
        with arm.locked() as (model, data):
            np.testing.assert_allclose(data.qpos[adr : adr + 7], model.qpos0[adr : adr + 7])
        np.testing.assert_allclose(arm.read_state().positions, before)
    finally:
        arm.close()
