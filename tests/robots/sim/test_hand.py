"""Simulated dexterous hand: scene, driver contract, synergy, e-stop, and the mimic joints in the physics."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from telerig.errors import RobotError
from telerig.ir.types import GripperCommand, JointCommand, Stamp
from telerig.robots.base import RobotDriver
from telerig.robots.sim.config import MujocoHandConfig
from telerig.robots.sim.hand import (
    SIM_HAND_MODELS,
    HandScene,
    MujocoHand,
    build_hand_scene,
    measure_mimic_error,
)

pytestmark = pytest.mark.sim

#: Largest allowed deviation of a mimic joint from its coupling in the physics [rad]. The
#: equality constraints are soft; closing onto the can and the table measured under 4 mrad.
MIMIC_TOLERANCE = 0.02

_SCENES: dict[str, HandScene] = {}


def _scene(model: str) -> HandScene:
    if model not in _SCENES:
        _SCENES[model] = build_hand_scene(model)  # type: ignore[arg-type]
    return _SCENES[model]


def _stamp() -> Stamp:
    return Stamp("test", 0, 0, 0)


@pytest.fixture
def hand() -> MujocoHand:
    driver = MujocoHand(_scene("inspire"), name="hand0", realtime=False)
    driver.connect()
    yield driver  # type: ignore[misc]
    driver.close()


@pytest.mark.parametrize(("model", "motors", "joints"), [("inspire", 6, 12), ("ability", 6, 10)])
def test_hand_commands_its_motors_and_the_linkage_moves_the_rest(
    model: str, motors: int, joints: int
) -> None:
    scene = _scene(model)
    assert len(scene.arm_joints) == motors
    assert scene.kinematics is not None
    assert len(scene.kinematics.joint_names) == joints
    assert len(scene.mimic) == joints - motors
    assert scene.arm_joints == scene.kinematics.actuated


def test_config_builds_the_driver_with_its_id_and_rejects_a_physics_rate_off_the_control_rate() -> None:
    driver = MujocoHandConfig(id="hand0", model="ability").build()
    try:
        assert isinstance(driver, RobotDriver)
        assert driver.name == "hand0"
        assert driver.joint_names[0] == "thumb_q1"
    finally:
        driver.close()
    with pytest.raises(ValueError, match="whole multiple of control_rate_hz"):
        MujocoHandConfig(id="h", physics_rate_hz=500, control_rate_hz=300)


def test_connect_and_close_are_idempotent_and_a_closed_driver_cannot_reconnect() -> None:
    driver = MujocoHand(_scene("inspire"), realtime=False)
    driver.connect()
    driver.connect()
    driver.close()
    driver.close()
    with pytest.raises(RobotError, match="closed"):
        driver.connect()


def test_read_state_is_stamped_with_the_sim_clock_and_starts_at_the_open_hand(hand: MujocoHand) -> None:
    hand.step(50)
    first = hand.read_state()
    hand.step(50)
    second = hand.read_state()
    assert first.names == hand.joint_names
    assert second.stamp.seq == first.stamp.seq + 1
    assert second.stamp.device_ns - first.stamp.device_ns == 100_000_000  # 50 steps of 2 ms
    assert second.stamp.capture_ns >= first.stamp.capture_ns > 0
    np.testing.assert_allclose(second.positions, hand.scene.home, atol=0.01)


def test_send_clips_to_the_coupled_range_and_returns_what_was_applied(hand: MujocoHand) -> None:
    names = hand.joint_names
    request = JointCommand(_stamp(), names, np.full(len(names), 5.0))
    applied = hand.send(request)
    assert applied.names == names
    np.testing.assert_allclose(applied.positions, hand.limits.upper)
    assert applied.stamp.source_id == "hand0"
    # The index motor keeps the MJCF range (1.62 rad): its coupled distal joint stays inside its own.
    assert hand.limits.upper[names.index("joint_r_index_proximal")] == pytest.approx(1.62)
    with pytest.raises(RobotError, match=r"not found\. Available"):
        hand.send(JointCommand(_stamp(), ("joint_r_index_distal",), np.zeros(1)))


def test_gripper_synergy_closes_every_finger_and_reports_the_opening(hand: MujocoHand) -> None:
    applied = hand.send_gripper(GripperCommand(_stamp(), opening=-1.0))
    assert applied.opening == pytest.approx(0.0)
    hand.step(750)
    closed = hand.read_state().positions
    assert np.all(np.abs(closed - hand.scene.home) > 0.3)  # every motor moved toward the grasp
    half = hand.send_gripper(GripperCommand(_stamp(), opening=0.5))
    assert half.opening == pytest.approx(0.5)


def test_estop_latches_ignores_commands_and_keeps_a_grasp(hand: MujocoHand) -> None:
    scene = hand.scene
    assert scene.gripper_open is not None
    assert scene.gripper_closed is not None
    closing = np.sign(scene.gripper_closed - scene.gripper_open)
    hand.send_gripper(GripperCommand(_stamp(), opening=0.0))
    hand.step(750)  # the fingers close on the can; some are blocked short of their target
    with hand.locked() as (_, data):
        target = data.ctrl[:6].copy()
    q = hand.read_state().positions
    blocked = closing * (target - q) > 0.05
    assert blocked.any()
    hand.estop()
    assert hand.estopped
    with hand.locked() as (_, data):
        held = data.ctrl[:6].copy()
    np.testing.assert_allclose(held[blocked], target[blocked])  # pressing fingers keep pressing
    np.testing.assert_allclose(held[~blocked], q[~blocked], atol=0.05)  # the others stop where they are
    ignored = hand.send(JointCommand(_stamp(), hand.joint_names, scene.home))
    np.testing.assert_allclose(ignored.positions, held)
    assert hand.send_gripper(GripperCommand(_stamp(), opening=1.0)).opening < 0.5
    hand.reset_estop()
    assert not hand.estopped
    np.testing.assert_allclose(
        hand.send(JointCommand(_stamp(), hand.joint_names, scene.home)).positions, scene.home
    )


@pytest.mark.parametrize("model", SIM_HAND_MODELS)
def test_mimic_joints_follow_their_coupling_in_free_motion_and_in_contact(model: str) -> None:
    driver = MujocoHand(_scene(model), realtime=False)
    with driver:
        model_, data = driver.scene.model, driver.physics.data
        worst = measure_mimic_error(model_, data, driver.hand_scene.mimic)
        driver.send_gripper(GripperCommand(_stamp(), opening=0.0))  # closes onto the can
        for _ in range(400):
            driver.step(2)
            worst = max(worst, driver.mimic_error())
        with driver.locked() as (m, d):
            touching = {m.geom(d.contact[i].geom1).name for i in range(d.ncon)} | {
                m.geom(d.contact[i].geom2).name for i in range(d.ncon)
            }
        driver.send_gripper(GripperCommand(_stamp(), opening=1.0))
        for _ in range(250):
            driver.step(2)
            worst = max(worst, driver.mimic_error())
    assert any(name.startswith(("r_", "index", "middle", "ring", "pinky", "thumb")) for name in touching)
    assert worst < MIMIC_TOLERANCE


def test_physics_fingertips_match_the_retargeters_kinematic_model() -> None:
    scene = _scene("inspire")
    kin = scene.kinematics
    assert kin is not None
    q = (kin.lower + kin.upper) / 2
    data = mujoco.MjData(scene.model)
    for name, value in zip(kin.joint_names, kin.full(q), strict=True):
        data.qpos[scene.model.joint(name).qposadr[0]] = value
    mujoco.mj_kinematics(scene.model, data)
    wrist = data.site(kin.keypoints[0]).xpos
    physics = np.array([data.site(s).xpos - wrist for s in kin.fingertips])
    np.testing.assert_allclose(physics, kin.keypoint_positions(q, (4, 8, 12, 16, 20)), atol=1e-6)


def test_unknown_model_names_the_available_ones() -> None:
    with pytest.raises(RobotError, match=r"no simulated hand 'allegro'\. Available: inspire, ability"):
        build_hand_scene("allegro")
