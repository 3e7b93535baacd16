"""The simulated G1 humanoid: scene, kinematic model and upper-body driver."""

from __future__ import annotations

import numpy as np
import pytest

from telerig.errors import RobotError
from telerig.ir.types import GripperCommand, JointCommand, Stamp
from telerig.robots.base import RobotDriver
from telerig.robots.models.g1 import HUMANOID_HOME, UPPER_BODY_JOINTS, build_humanoid_kinematics
from telerig.robots.sim.humanoid import MujocoHumanoid, build_humanoid_scene

pytestmark = pytest.mark.sim

_PELVIS_HEIGHT = 0.795  # [m], the G1 URDF standing on straight legs


def _command(q: np.ndarray, seq: int = 0) -> JointCommand:
    return JointCommand(Stamp.now("test", seq), UPPER_BODY_JOINTS, q)


@pytest.fixture(scope="module")
def robot() -> MujocoHumanoid:
    driver = MujocoHumanoid(build_humanoid_scene(), realtime=False)
    driver.connect()
    yield driver
    driver.close()


def test_driver_implements_the_robot_driver_protocol(robot: MujocoHumanoid) -> None:
    assert isinstance(robot, RobotDriver)
    assert robot.joint_names == UPPER_BODY_JOINTS
    assert len(UPPER_BODY_JOINTS) == 17


def test_kinematic_model_has_exactly_the_upper_body_joints() -> None:
    scene = build_humanoid_kinematics()
    assert scene.model.nq == scene.model.nv == len(UPPER_BODY_JOINTS)
    assert scene.actuators == ()


@pytest.mark.parametrize("support", ["fixed", "harness"])
def test_pelvis_stays_up_for_five_seconds_while_the_arms_move(support: str) -> None:
    robot = MujocoHumanoid(build_humanoid_scene(support=support), realtime=False)  # type: ignore[arg-type]
    with robot:
        home = np.array(HUMANOID_HOME)
        wave = np.r_[0.4, 0.0, 0.0, np.ones(7), -np.ones(7)] * 0.6  # waist yaw, left arm, right arm
        for k in range(250):  # 250 x 20 ms = 5 s of simulated time
            robot.send(_command(home + wave * np.sin(2 * np.pi * k / 100), k))
            robot.step(10)
            position, orientation = robot.pelvis_pose()
            assert abs(position[2] - _PELVIS_HEIGHT) < 0.01, f"pelvis at {position} after {k * 0.02:.2f} s"
        tilt = 2 * np.degrees(np.arccos(min(1.0, np.hypot(orientation[0], orientation[3]))))
        assert tilt < 2.0
        assert robot.stats().sim_time == pytest.approx(5.0)
        assert np.all(np.isfinite(robot.read_state().positions))


def test_read_state_is_stamped_with_sim_and_wall_time(robot: MujocoHumanoid) -> None:
    robot.step(5)
    state = robot.read_state()
    assert state.names == UPPER_BODY_JOINTS
    assert state.stamp.source_id == robot.name
    assert state.stamp.capture_ns > 0
    with robot.locked() as (_, data):
        assert state.stamp.device_ns == round(data.time * 1e9)


def test_send_returns_targets_clipped_to_the_joint_limits(robot: MujocoHumanoid) -> None:
    limits = robot.limits
    applied = robot.send(_command(limits.upper + 1.0))
    np.testing.assert_allclose(applied.positions, limits.upper)
    applied = robot.send(_command(limits.lower - 1.0))
    np.testing.assert_allclose(applied.positions, limits.lower)
    robot.send(_command(np.array(HUMANOID_HOME)))


def test_servos_reach_a_commanded_posture(robot: MujocoHumanoid) -> None:
    # Arms out to the sides, clear of the torso and the table.
    target = (
        np.array(HUMANOID_HOME)
        + np.r_[0.2, 0.1, 0.1, 0.2, 0.4, -0.3, 0.4, 0.2, 0.2, 0.2, 0.2, -0.4, 0.3, 0.4, -0.2, -0.2, -0.2]
    )
    robot.send(_command(target))
    robot.step(500)  # 1 s
    np.testing.assert_allclose(robot.read_state().positions, target, atol=0.01)
    robot.send(_command(np.array(HUMANOID_HOME)))
    robot.step(500)


def test_limits_come_from_the_model_with_positive_speed_limits(robot: MujocoHumanoid) -> None:
    limits = robot.limits
    assert limits.names == UPPER_BODY_JOINTS
    assert np.all(limits.lower < limits.upper)
    assert np.all(limits.velocity > 0)
    assert np.all(limits.acceleration > 0)


def test_the_handless_g1_has_no_gripper_and_refuses_gripper_commands(robot: MujocoHumanoid) -> None:
    assert not robot.has_gripper
    with pytest.raises(RobotError, match="no gripper on this robot; remove the gripper from its binding"):
        robot.send_gripper(GripperCommand(Stamp.now("test", 0), opening=1.0))


def test_estop_holds_position_and_ignores_commands() -> None:
    robot = MujocoHumanoid(build_humanoid_scene(), realtime=False)
    with robot:
        robot.step(50)
        robot.estop()
        held = robot.read_state().positions
        applied = robot.send(_command(np.array(HUMANOID_HOME) + 0.5))
        np.testing.assert_allclose(applied.positions, held, atol=1e-6)
        robot.step(250)
        np.testing.assert_allclose(robot.read_state().positions, held, atol=0.01)


def test_kinematic_scene_is_refused_by_the_driver() -> None:
    with pytest.raises(RobotError, match="no actuators"):
        MujocoHumanoid(build_humanoid_kinematics())
