"""TIAGo driver contract: lifecycle, stamped state, clipped and returned commands, e-stop, base servo."""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np
import pytest

from telerig.errors import RobotError
from telerig.ir.types import BaseVelocity, GripperCommand, JointCommand, Stamp
from telerig.robots.base import MobileBase, RobotDriver
from telerig.robots.models.tiago import TIAGO_JOINTS, TiagoScene
from telerig.robots.sim.config import MujocoTiagoConfig
from telerig.robots.sim.tiago import build_tiago_scene
from telerig.robots.sim.tiago_driver import MujocoTiago

pytestmark = pytest.mark.sim

PERIOD = 0.01  # [s], the driver's control period
STEPS = 5  # physics steps of 2 ms per control period


@pytest.fixture(scope="module")
def scene() -> TiagoScene:
    return build_tiago_scene(with_cup=False)


@pytest.fixture
def robot(scene: TiagoScene) -> Iterator[MujocoTiago]:
    driver = MujocoTiago(scene, realtime=False, control_period_s=PERIOD)
    driver.connect()
    yield driver
    driver.close()


def _command(q: np.ndarray, names: tuple[str, ...] = TIAGO_JOINTS, seq: int = 0) -> JointCommand:
    return JointCommand(Stamp("test", seq, 0, 0), names, q)


def _drive(robot: MujocoTiago, q: np.ndarray, ticks: int) -> None:
    for k in range(ticks):
        robot.send(_command(q, seq=k))
        robot.step(STEPS)


def test_implements_the_driver_and_mobile_base_protocols(robot: MujocoTiago) -> None:
    assert isinstance(robot, RobotDriver)
    assert isinstance(robot, MobileBase)
    assert robot.joint_names == TIAGO_JOINTS
    assert robot.limits.names == TIAGO_JOINTS
    assert np.all(np.isinf(robot.limits.lower[:3]))
    assert robot.scene.home.shape == (10,)


def test_connect_and_close_are_idempotent(scene: TiagoScene) -> None:
    driver = MujocoTiago(scene, realtime=False)
    driver.connect()
    driver.connect()
    driver.close()
    driver.close()
    with pytest.raises(RobotError, match="closed"):
        driver.read_state()


def test_read_state_is_stamped_and_starts_at_home(robot: MujocoTiago, scene: TiagoScene) -> None:
    a = robot.read_state()
    robot.step(3)
    b = robot.read_state()
    assert a.names == TIAGO_JOINTS
    np.testing.assert_allclose(a.positions, scene.home, atol=1e-9)
    assert b.stamp.seq == a.stamp.seq + 1
    assert b.stamp.device_ns - a.stamp.device_ns == 6_000_000  # 3 steps of 2 ms, simulation clock
    assert b.stamp.capture_ns >= a.stamp.capture_ns > 0
    assert a.stamp.source_id == "tiago_sim"


def test_send_clips_arm_targets_and_returns_what_was_applied(robot: MujocoTiago, scene: TiagoScene) -> None:
    q = scene.home.copy()
    q[3] = 5.0  # torso far above its 0.35 m travel
    q[0] = 0.02  # base 2 cm forward: not clipped, it is a pose target
    sent = robot.send(_command(q))
    assert sent.names == TIAGO_JOINTS
    assert sent.positions[3] == pytest.approx(0.35)
    assert sent.positions[0] == pytest.approx(0.02)
    np.testing.assert_allclose(sent.positions[4:], q[4:])
    assert sent.stamp.source_id == "tiago_sim"


def test_send_accepts_a_subset_in_any_order(robot: MujocoTiago) -> None:
    sent = robot.send(_command(np.array([0.1, 0.03]), ("arm_right_2_joint", "base_y")))
    assert sent.names == ("arm_right_2_joint", "base_y")
    np.testing.assert_allclose(sent.positions, [0.1, 0.03])


def test_unknown_joint_is_rejected_naming_the_valid_ones(robot: MujocoTiago) -> None:
    with pytest.raises(RobotError, match=r"'elbow' not found\. Available: base_x"):
        robot.send(_command(np.zeros(1), ("elbow",)))


def test_base_follows_pose_targets_through_its_velocity_servos(robot: MujocoTiago, scene: TiagoScene) -> None:
    q = scene.home.copy()
    speed, turn = 0.2, 0.3  # [m/s] forward in the base frame, [rad/s]
    for k in range(150):  # 1.5 s of small target steps, as a controller sends them
        q = q.copy()
        q[0] -= speed * PERIOD * math.cos(q[2])  # backwards, away from the table
        q[1] -= speed * PERIOD * math.sin(q[2])
        q[2] += turn * PERIOD
        robot.send(_command(q, seq=k))
        robot.step(STEPS)
        if k > 50:  # cruising: the velocity servos track the feed-forward
            np.testing.assert_allclose(robot.base_pose(), q[:3], atol=0.01)
    state = robot.read_state()
    assert np.hypot(*state.velocities[:2]) == pytest.approx(speed, abs=0.02)
    assert state.velocities[2] == pytest.approx(turn, abs=0.03)
    _drive(robot, q, 50)  # targets held: the base settles on them
    np.testing.assert_allclose(robot.base_pose(), q[:3], atol=1e-3)
    np.testing.assert_allclose(robot.read_state().positions[3:], q[3:], atol=2e-3)


def test_send_base_drives_in_the_base_frame_and_stops_without_jumping_back(
    robot: MujocoTiago, scene: TiagoScene
) -> None:
    q = scene.home.copy()
    robot.send(_command(q))
    applied = robot.send_base(BaseVelocity(Stamp("test", 0, 0, 0), vx=-0.2, vy=0.0, wz=5.0))
    assert (applied.vx, applied.vy, applied.wz) == (-0.2, 0.0, 1.5)  # yaw rate clipped to its limit
    _drive(robot, q, 100)  # position targets held while the base drives: it keeps driving
    robot.send_base(BaseVelocity(Stamp("test", 1, 0, 0), 0.0, 0.0, 0.0))
    _drive(robot, q, 50)  # the base settles where the velocity took it, not back at the old targets
    stopped = robot.base_pose()
    assert stopped[2] == pytest.approx(1.5, abs=0.01)  # 1 s at 1.5 rad/s
    chord = 0.2 * 2 / 1.5 * math.sin(0.75)  # 0.2 m/s backwards along an arc turning 1.5 rad
    assert np.hypot(*stopped[:2]) == pytest.approx(chord, abs=0.01)
    _drive(robot, q, 50)
    np.testing.assert_allclose(robot.base_pose(), stopped, atol=1e-3)  # and stays there
    q[0] += 0.05  # a later 5 cm step of the target moves the base 5 cm along its heading at that time
    _drive(robot, q, 100)
    moved = robot.base_pose() - stopped
    heading = np.array([math.cos(stopped[2]), math.sin(stopped[2])])
    np.testing.assert_allclose(moved[:2], 0.05 * heading, atol=3e-3)


def test_estop_latches_holds_the_arm_and_stops_the_base(robot: MujocoTiago, scene: TiagoScene) -> None:
    q = scene.home.copy()
    robot.send_base(BaseVelocity(Stamp("test", 0, 0, 0), vx=-0.3, vy=0.0, wz=0.0))
    _drive(robot, q, 30)
    robot.estop()
    assert robot.estopped
    target = q.copy()
    target[3:] += 0.2
    target[0] -= 1.0
    sent = robot.send(_command(target))
    base = robot.send_base(BaseVelocity(Stamp("test", 1, 0, 0), vx=0.5, vy=0.0, wz=0.0))
    assert (base.vx, base.vy, base.wz) == (0.0, 0.0, 0.0)
    robot.step(250)  # 0.5 s
    state = robot.read_state()
    np.testing.assert_allclose(state.velocities, 0.0, atol=1e-3)
    np.testing.assert_allclose(sent.positions[3:], state.positions[3:], atol=5e-3)  # held, not the target
    robot.reset_estop()
    assert not robot.estopped


def test_gripper_opening_is_clipped_and_returned(robot: MujocoTiago) -> None:
    sent = robot.send_gripper(GripperCommand(Stamp("test", 0, 0, 0), opening=1.7))
    assert sent.opening == pytest.approx(1.0)
    sent = robot.send_gripper(GripperCommand(Stamp("test", 1, 0, 0), opening=0.25))
    assert sent.opening == pytest.approx(0.25)


def test_real_time_physics_runs_on_its_thread(scene: TiagoScene) -> None:
    with MujocoTiago(scene, realtime=True) as driver:
        first = driver.read_state().stamp.device_ns
        deadline = first + 20_000_000
        while driver.read_state().stamp.device_ns < deadline:
            pass
    assert driver.stats().steps >= 10


def test_config_builds_the_driver_with_its_rates() -> None:
    with pytest.raises(ValueError, match="whole multiple of control_rate_hz"):
        MujocoTiagoConfig(id="t", physics_rate_hz=500, control_rate_hz=300)
    with pytest.raises(ValueError, match="base_gain"):
        MujocoTiagoConfig(id="t", control_rate_hz=10, physics_rate_hz=500, base_gain=20)
    driver = MujocoTiagoConfig(id="tiago0", with_cup=False).build()
    try:
        assert driver.name == "tiago0"
        assert driver.joint_names == TIAGO_JOINTS
    finally:
        driver.close()
