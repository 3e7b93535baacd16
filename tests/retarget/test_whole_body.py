"""Whole-body teleoperation adapter: switches, pose-derived twist, the 8-D action, binding a rig."""

from __future__ import annotations

import numpy as np
import pytest

from telerig.errors import ConfigError
from telerig.ir.frames import quat_from_axis_angle
from telerig.ir.types import ControllerState, GripperCommand, Pose, Stamp, Twist
from telerig.retarget.binding import BindContext
from telerig.retarget.config import WholeBodyConfig
from telerig.retarget.wbc import EE_MODE, WHOLE_BODY_MODE, WholeBodyController
from telerig.retarget.whole_body import (
    PoseTwist,
    WholeBodyGripper,
    WholeBodyRetargeter,
    WholeBodySwitches,
)
from telerig.robots.models.tiago import TIAGO_JOINTS, TiagoScene, build_tiago_kinematics
from telerig.robots.sim.tiago_driver import MujocoTiago

pytestmark = pytest.mark.sim

DT = 0.01  # [s]


@pytest.fixture(scope="module")
def scene() -> TiagoScene:
    return build_tiago_kinematics()


def _buttons(*held: str, t_ns: int = 0) -> ControllerState:
    return ControllerState(
        Stamp("sm0/buttons", 0, t_ns, t_ns),
        "right",
        np.zeros(3),
        np.array([1.0, 0, 0, 0]),
        "operator",
        buttons=frozenset(held),
    )


def _twist(
    linear: tuple[float, float, float], angular: tuple[float, float, float] = (0, 0, 0), k: int = 0
) -> Twist:
    t_ns = k * 10_000_000
    return Twist(Stamp("sm0", k, t_ns, t_ns), np.array(linear, float), np.array(angular, float), "operator")


def test_buttons_toggle_mode_and_gripper_on_press_edges() -> None:
    switches = WholeBodySwitches(mode_button="left", gripper_button="right")
    assert (switches.mode, switches.gripper) == (EE_MODE, 0.0)
    assert switches.update(_buttons("left"))
    assert not switches.update(_buttons("left"))  # held: no second toggle
    assert switches.mode == WHOLE_BODY_MODE
    assert not switches.update(_buttons())
    assert switches.update(_buttons("left", "right"))
    assert (switches.mode, switches.gripper) == (EE_MODE, 1.0)
    assert switches.state() == {"mode": "ee", "gripper": 1.0}


def test_bus_commands_set_mode_and_gripper_and_bad_ones_say_what_is_valid() -> None:
    switches = WholeBodySwitches()
    assert switches.command("whole_body")
    assert switches.mode == WHOLE_BODY_MODE
    assert switches.command("toggle")
    assert switches.mode == EE_MODE
    assert switches.command("close")
    assert switches.gripper == 1.0
    assert not switches.command("close")
    with pytest.raises(ValueError, match="ee, whole_body, toggle, open or close"):
        switches.command("fly")


def test_pose_twist_differentiates_clutched_controller_poses() -> None:
    estimator = PoseTwist("grip")
    axis = np.array([0.0, 0.0, 1.0])

    def controller(k: int, grip: float) -> ControllerState:
        t_ns = k * 10_000_000
        position = np.array([0.2 * k * DT, 0.0, 1.0])  # 0.2 m/s forward
        orientation = quat_from_axis_angle(axis, 0.5 * k * DT)  # 0.5 rad/s about z
        return ControllerState(
            Stamp("vr0/right", k, t_ns, t_ns), "right", position, orientation, "operator", grip=grip
        )

    linear, angular = estimator(controller(0, 1.0))
    assert not np.any(linear)
    assert not np.any(angular)
    linear, angular = estimator(controller(1, 1.0))
    np.testing.assert_allclose(linear, [0.2, 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(angular, [0.0, 0.0, 0.5], atol=1e-9)
    linear, _ = estimator(controller(2, 0.0))  # released: no motion ...
    assert not np.any(linear)
    linear, _ = estimator(controller(9, 1.0))  # ... and pressing again re-anchors instead of jumping
    assert not np.any(linear)


def test_twist_moves_the_hand_in_ee_mode_and_records_the_action(scene: TiagoScene) -> None:
    switches = WholeBodySwitches(mode_button="left", gripper_button="right")
    retargeter = WholeBodyRetargeter(WholeBodyController(scene), switches, TIAGO_JOINTS)
    q = scene.home.copy()
    wbc = WholeBodyController(scene)
    p0, _ = wbc.hand_in_base(q)
    for k in range(100):
        command, residual = retargeter(_twist((0.0, 0.0, 0.05), k=k), q, DT)
        assert command is not None
        assert residual is not None
        assert command.names == TIAGO_JOINTS
        q = command.positions
    p1, _ = wbc.hand_in_base(q)
    assert p1[2] - p0[2] == pytest.approx(0.05 * 100 * DT, abs=0.01)
    np.testing.assert_array_equal(q[:3], scene.home[:3])  # EE mode: the base stood still
    metrics = residual.metrics()
    assert metrics["a_vz"] == 0.05
    assert metrics["a_mode"] == 0.0
    assert metrics["mode"] == 0.0
    assert metrics["hand_position"] < 0.01
    assert not residual.flagged


def test_twist_drives_the_base_in_whole_body_mode(scene: TiagoScene) -> None:
    switches = WholeBodySwitches(mode=WHOLE_BODY_MODE)
    retargeter = WholeBodyRetargeter(WholeBodyController(scene), switches, TIAGO_JOINTS)
    q = scene.home.copy()
    for k in range(200):
        command, _ = retargeter(_twist((-0.2, 0.0, 0.0), k=k), q, DT)
        assert command is not None
        q = command.positions
    assert q[0] < -0.25  # 2 s at 0.2 m/s after accelerating at 1 m/s^2
    assert command.velocities[0] == pytest.approx(-0.2, abs=1e-6)


def test_mode_button_mid_motion_changes_velocities_within_the_acceleration_limits(scene: TiagoScene) -> None:
    switches = WholeBodySwitches(mode_button="left")
    retargeter = WholeBodyRetargeter(WholeBodyController(scene), switches, TIAGO_JOINTS)
    amax = scene.limits.acceleration
    q, previous = scene.home.copy(), np.zeros(10)
    base_speeds = []
    for k in range(300):
        if k in (100, 200):  # press: EE → whole body while the hand moves, then back while the base drives
            switches.update(_buttons("left"))
        elif k in (101, 201):
            switches.update(_buttons())
        command, _ = retargeter(_twist((-0.1, 0.0, 0.0), (0.0, 0.0, 0.2), k=k), q, DT)
        assert command is not None
        assert np.all(np.abs(command.velocities - previous) <= amax * DT + 1e-9)
        q, previous = command.positions, command.velocities
        base_speeds.append(float(np.hypot(*command.velocities[:2])))
    assert base_speeds[99] == 0.0
    assert base_speeds[199] == pytest.approx(0.1, abs=1e-3)  # driving in whole-body mode
    assert 0.0 < base_speeds[201] < 0.1  # braking after the switch back, not stopped at once
    assert base_speeds[-1] == 0.0


def test_operator_rotation_and_norm_limits_shape_the_action(scene: TiagoScene) -> None:
    turn = tuple(quat_from_axis_angle(np.array([0.0, 0.0, 1.0]), np.pi / 2))  # operator x → base y
    retargeter = WholeBodyRetargeter(
        WholeBodyController(scene), WholeBodySwitches(), TIAGO_JOINTS, rotation=turn, max_linear_m_s=0.1
    )
    _, residual = retargeter(_twist((1.0, 0.0, 0.0)), scene.home.copy(), DT)
    assert residual is not None
    metrics = residual.metrics()
    assert metrics["a_vx"] == pytest.approx(0.0, abs=1e-12)
    assert metrics["a_vy"] == pytest.approx(0.1)


def test_a_command_held_by_the_safety_chain_restarts_acceleration_from_rest(scene: TiagoScene) -> None:
    limits = scene.limits
    retargeter = WholeBodyRetargeter(WholeBodyController(scene), WholeBodySwitches(mode=1), TIAGO_JOINTS)
    q = scene.home.copy()
    for k in range(100):  # cruising backwards at 0.2 m/s
        command, _ = retargeter(_twist((-0.2, 0.0, 0.0), k=k), q, DT)
        assert command is not None
        q = command.positions
    held = q - command.velocities * DT  # the chain held the previous command instead of this one
    command, _ = retargeter(_twist((-0.2, 0.0, 0.0), k=100), held, DT)
    assert command is not None
    # From the held (still) command, the base may only speed up by its acceleration limit.
    assert np.all(np.abs(command.velocities) <= limits.acceleration * DT + 1e-9)


def test_gripper_follows_the_switches_on_every_sample() -> None:
    switches = WholeBodySwitches(gripper_button="right")
    gripper = WholeBodyGripper(switches)
    first = gripper(_twist((0, 0, 0)))
    switches.update(_buttons("right"))
    second = gripper(_twist((0, 0, 0), k=1))
    assert isinstance(first, GripperCommand)
    assert isinstance(second, GripperCommand)
    assert (first.opening, second.opening) == (1.0, 0.0)
    assert gripper(Pose(Stamp("p", 0, 0, 0), np.zeros(3), np.array([1.0, 0, 0, 0]), "w")) is None


@pytest.fixture(scope="module")
def tiago() -> MujocoTiago:
    from telerig.robots.sim.tiago import build_tiago_scene

    return MujocoTiago(build_tiago_scene(with_cup=False), name="tiago0", realtime=False)


def _context(robot: object, target: str = "whole_body") -> BindContext:
    return BindContext("rig", "tiago0", robot, target, "sm0", "twist", ("sm0",))  # type: ignore[arg-type]


def test_bind_gives_joints_gripper_and_the_switches_on_the_buttons_stream(tiago: MujocoTiago) -> None:
    config = WholeBodyConfig.model_validate({"type": "wbc", "buttons": {"part": "right_controller"}})
    bound = config.bind(_context(tiago))
    assert isinstance(bound.joints, WholeBodyRetargeter)
    assert isinstance(bound.gripper, WholeBodyGripper)
    (topic, aid), (plan_topic, plan) = bound.aids
    assert topic.endswith("/rig/sm0/right_controller")
    assert aid is bound.joints.switches
    # The reach planner ticks with the driving stream; ``plan: false`` leaves it out.
    assert plan_topic.endswith("/rig/sm0/twist")
    assert plan is bound.joints.plan
    bare = WholeBodyConfig.model_validate({"type": "wbc", "plan": False}).bind(_context(tiago))
    assert len(bare.aids) == 1


def test_bind_rejects_another_target_and_another_robot(tiago: MujocoTiago) -> None:
    config = WholeBodyConfig()
    with pytest.raises(ConfigError, match=r"cannot drive target 'arm'\. Valid: whole_body"):
        config.bind(_context(tiago, "arm"))

    class Arm:
        joint_names = ("shoulder",)

    with pytest.raises(ConfigError, match="use a mujoco_tiago robot"):
        config.bind(_context(Arm()))


def test_config_rejects_one_button_for_two_switches() -> None:
    with pytest.raises(ValueError, match="must differ"):
        WholeBodyConfig(mode_button="left", gripper_button="left")
