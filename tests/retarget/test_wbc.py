"""Whole-body controller: hard limits, still base in EE mode, hand held on the base, smooth mode switch."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from telerig.errors import RobotError
from telerig.retarget.wbc import EE_MODE, WHOLE_BODY_MODE, WholeBodyController, _rotvec
from telerig.robots.models.tiago import TiagoScene, build_tiago_kinematics
from telerig.robots.sim.tiago import build_tiago_scene

pytestmark = pytest.mark.sim

DT = 0.002  # [s]


@pytest.fixture(scope="module")
def scene() -> TiagoScene:
    return build_tiago_kinematics()


@pytest.fixture
def wbc(scene: TiagoScene) -> WholeBodyController:
    return WholeBodyController(scene)


def _action(twist: tuple[float, ...] = (0.0,) * 6, gripper: float = 0.0, mode: int = EE_MODE) -> np.ndarray:
    return np.array([*twist, gripper, mode], dtype=np.float64)


def test_limits_are_never_exceeded_under_random_actions(wbc: WholeBodyController, scene: TiagoScene) -> None:
    rng = np.random.default_rng(1)
    limits = scene.limits
    q = scene.home.copy()
    prev = np.zeros(10)
    mode = EE_MODE
    for tick in range(3000):
        if tick % 150 == 0:  # a new operator command: fast, often pushing into the joint limits
            twist = rng.uniform(-1, 1, 6) * np.array([0.6, 0.6, 0.6, 2.0, 2.0, 2.0])
            mode = int(rng.integers(0, 2))
        result = wbc.step(_action(tuple(twist), float(rng.uniform()), mode), q, DT)
        assert np.all(result.q >= limits.lower - 1e-12)
        assert np.all(result.q <= limits.upper + 1e-12)
        assert np.all(np.abs(result.qdot) <= limits.velocity + 1e-12)
        assert np.all(np.abs(result.qdot - prev) <= limits.acceleration * DT + 1e-12)
        prev, q = result.qdot, result.q
    assert np.any(
        np.isclose(q[3:], limits.lower[3:], atol=0.05) | np.isclose(q[3:], limits.upper[3:], atol=0.05)
    )


def test_base_does_not_move_in_ee_mode(wbc: WholeBodyController, scene: TiagoScene) -> None:
    rng = np.random.default_rng(2)
    q = scene.home.copy()
    for _ in range(500):
        result = wbc.step(_action(tuple(rng.uniform(-0.5, 0.5, 6))), q, DT)
        q = result.q
        assert np.all(result.qdot[:3] == 0.0)
    assert np.all(q[:3] == scene.home[:3])
    assert np.linalg.norm(q[3:] - scene.home[3:]) > 0.05  # the arm did move


@pytest.mark.parametrize("axis", range(6))
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_ee_twist_is_tracked_in_ee_mode(
    wbc: WholeBodyController, scene: TiagoScene, axis: int, sign: float
) -> None:
    speed = 0.05 if axis < 3 else 0.2  # [m/s] or [rad/s]
    twist = np.zeros(6)
    twist[axis] = sign * speed
    q = scene.home.copy()
    p0, r0 = wbc.hand_in_base(q)
    duration = 0.4
    for _ in range(int(duration / DT)):
        q = wbc.step(_action(tuple(twist)), q, DT).q
    p1, r1 = wbc.hand_in_base(q)
    motion = p1 - p0 if axis < 3 else _rotvec(r1 @ r0.T)
    commanded = twist[:3] if axis < 3 else twist[3:]
    cosine = motion @ commanded / (np.linalg.norm(motion) * np.linalg.norm(commanded))
    assert cosine > 0.99
    assert np.linalg.norm(motion) == pytest.approx(speed * duration, rel=0.1)


def test_hand_pose_relative_to_base_is_held_in_whole_body_mode(
    wbc: WholeBodyController, scene: TiagoScene
) -> None:
    q = scene.home.copy()
    p0, r0 = wbc.hand_in_base(q)
    worst = 0.0
    for _ in range(int(3.0 / DT)):
        result = wbc.step(_action((0.4, 0.2, 0.0, 0.0, 0.0, 0.5), mode=WHOLE_BODY_MODE), q, DT)
        q = result.q
        worst = max(worst, result.errors.hand_position)
    p1, r1 = wbc.hand_in_base(q)
    assert np.hypot(*(q[:2] - scene.home[:2])) > 0.8  # the base drove ...
    assert abs(q[2] - scene.home[2]) > 1.0  # ... and turned
    assert np.hypot(*(p1 - p0)[:2]) < 2e-3  # while the hand stayed put on it
    assert np.linalg.norm(_rotvec(r1 @ r0.T)) < 5e-3
    assert worst < 2e-3


def test_base_follows_the_twist_in_its_own_frame(wbc: WholeBodyController, scene: TiagoScene) -> None:
    q = scene.home.copy()
    q[2] = np.pi / 2  # facing world +y: forward is +y, left is -x
    for _ in range(int(1.5 / DT)):
        result = wbc.step(_action((0.3, 0.1, 0.0, 0.0, 0.0, 0.0), mode=WHOLE_BODY_MODE), q, DT)
        q = result.q
    np.testing.assert_allclose(result.qdot[:3], (-0.1, 0.3, 0.0), atol=1e-6)
    assert result.errors.base_linear < 1e-6


def test_vertical_action_moves_the_hand_up_in_whole_body_mode(
    wbc: WholeBodyController, scene: TiagoScene
) -> None:
    q = scene.home.copy()
    p0, _ = wbc.hand_in_base(q)
    for _ in range(int(1.0 / DT)):
        q = wbc.step(_action((0.0, 0.0, 0.05, 0.0, 0.0, 0.0), mode=WHOLE_BODY_MODE), q, DT).q
    p1, _ = wbc.hand_in_base(q)
    assert p1[2] - p0[2] == pytest.approx(0.05, rel=0.15)
    assert np.hypot(*(p1 - p0)[:2]) < 2e-3


def test_elbow_keeps_its_place_on_the_base_in_whole_body_mode(
    wbc: WholeBodyController, scene: TiagoScene
) -> None:
    model, data = scene.model, mujoco.MjData(scene.model)
    elbow, base = model.site(scene.elbow_site).id, model.body(scene.base_body).id

    def elbow_in_base(q: np.ndarray) -> np.ndarray:
        data.qpos[:] = q
        mujoco.mj_kinematics(model, data)
        return data.xmat[base].reshape(3, 3).T @ (data.site_xpos[elbow] - data.xpos[base])

    q = scene.home.copy()
    e0 = elbow_in_base(q)
    for _ in range(int(2.0 / DT)):
        q = wbc.step(_action((0.3, 0.0, 0.0, 0.0, 0.0, 0.6), mode=WHOLE_BODY_MODE), q, DT).q
    assert np.hypot(*(elbow_in_base(q) - e0)[:2]) < 5e-3


def test_mode_switch_has_no_velocity_jump(wbc: WholeBodyController, scene: TiagoScene) -> None:
    acceleration = scene.limits.acceleration
    q = scene.home.copy()
    base_twist = _action((0.5, 0.0, 0.0, 0.0, 0.0, 0.8), mode=WHOLE_BODY_MODE)
    for _ in range(int(1.5 / DT)):
        result = wbc.step(base_twist, q, DT)
        q = result.q
    cruising = result.qdot.copy()
    assert np.hypot(*cruising[:2]) == pytest.approx(0.5, abs=1e-3)
    prev = cruising
    speeds = []
    for _ in range(int(1.0 / DT)):  # switch: the hand twists, the base must stop
        result = wbc.step(_action((0.0, 0.1, 0.0, 0.0, 0.0, 0.0), mode=EE_MODE), q, DT)
        assert np.all(np.abs(result.qdot - prev) <= acceleration * DT + 1e-12)
        speeds.append(np.hypot(*result.qdot[:2]))
        prev, q = result.qdot, result.q
    # The base braked over many ticks, not in one, then stood still.
    assert speeds[0] > 0.45
    assert speeds[-1] == 0.0
    braking_ticks = int(np.max(np.abs(cruising[:2]) / acceleration[:2]) / DT)
    assert sum(s > 0 for s in speeds) >= braking_ticks - 1
    for _ in range(int(0.5 / DT)):  # and back to whole-body mode
        result = wbc.step(base_twist, q, DT)
        assert np.all(np.abs(result.qdot - prev) <= acceleration * DT + 1e-12)
        prev, q = result.qdot, result.q


def test_task_errors_are_reported_every_tick(wbc: WholeBodyController, scene: TiagoScene) -> None:
    q = scene.home.copy()
    for mode in (EE_MODE, WHOLE_BODY_MODE):
        result = wbc.step(_action((0.1, 0.0, 0.0, 0.0, 0.0, 0.1), gripper=0.7, mode=mode), q, DT)
        errors = result.errors.as_dict()
        assert set(errors) == {
            "ee_linear", "ee_angular", "base_linear", "base_angular", "elbow", "hand_position",
            "hand_orientation",
        }  # fmt: skip
        assert all(np.isfinite(v) and v >= 0 for v in errors.values())
        assert result.mode == mode
        assert result.gripper == 0.7
        assert result.solved


def test_first_tick_residual_reflects_the_acceleration_limit(scene: TiagoScene) -> None:
    wbc = WholeBodyController(scene)
    result = wbc.step(_action((0.2, 0.0, 0.0, 0.0, 0.0, 0.0)), scene.home, DT)
    assert result.errors.ee_linear > 0.1  # asked 0.2 m/s from rest; one tick allows far less


@pytest.mark.parametrize(
    ("action", "message"),
    [
        (np.zeros(7), r"action must have shape \(8,\)"),
        (np.zeros((2, 8)), r"action must have shape \(8,\)"),
        (np.array([np.nan, 0, 0, 0, 0, 0, 0, 0]), "action must be finite"),
        (np.array([0, 0, 0, 0, 0, 0, 1.5, 0]), r"action\[6\] \(gripper closure\) must be in \[0, 1\]"),
        (np.array([0, 0, 0, 0, 0, 0, 0, 2]), r"action\[7\] \(mode\) must be 0 \(end effector\) or 1"),
        (np.array([0, 0, 0, 0, 0, 0, 0, 0.5]), r"action\[7\] \(mode\) must be 0"),
    ],
)
def test_bad_action_is_rejected_in_one_line(
    wbc: WholeBodyController, scene: TiagoScene, action: np.ndarray, message: str
) -> None:
    with pytest.raises(ValueError, match=message) as info:
        wbc.step(action, scene.home, DT)
    assert "\n" not in str(info.value)


def test_bad_q_and_dt_are_rejected(wbc: WholeBodyController, scene: TiagoScene) -> None:
    with pytest.raises(ValueError, match=r"q must be finite with shape \(10,\)"):
        wbc.step(_action(), scene.home[:7], DT)
    with pytest.raises(ValueError, match="dt must be positive"):
        wbc.step(_action(), scene.home, 0.0)


def test_physics_scene_is_rejected_as_the_controller_model() -> None:
    with pytest.raises(RobotError, match=r"build_tiago_kinematics\(\)"):
        WholeBodyController(build_tiago_scene(with_cup=False))


def test_commands_drive_the_physics_scene(scene: TiagoScene) -> None:
    """Closed through the servos: arm targets to position servos, base velocities to velocity servos."""
    sim = build_tiago_scene(with_cup=False)
    model, data = sim.model, mujoco.MjData(sim.model)
    qpos, dofs = sim.qpos_indices(), sim.dof_indices()
    arm = [model.actuator(a).id for a in sim.arm_actuators]
    base = [model.actuator(a).id for a in sim.base_actuators]
    data.qpos[qpos] = sim.home
    data.ctrl[arm] = sim.home[3:]
    wbc = WholeBodyController(scene)
    q = sim.home.copy()
    p0, _ = wbc.hand_in_base(q)
    for _ in range(int(2.0 / DT)):  # backwards and turning, away from the table
        result = wbc.step(_action((-0.3, 0.1, 0.0, 0.0, 0.0, 0.4), mode=WHOLE_BODY_MODE), q, DT)
        q = result.q
        data.ctrl[arm] = q[3:]
        data.ctrl[base] = result.qdot[:3]
        mujoco.mj_step(model, data)
    measured = data.qpos[qpos]
    np.testing.assert_allclose(data.qvel[dofs[:3]], result.qdot[:3], atol=0.03)
    np.testing.assert_allclose(measured[:3], q[:3], atol=0.03)
    p1, _ = wbc.hand_in_base(measured)
    assert np.hypot(*(p1 - p0)[:2]) < 0.01
