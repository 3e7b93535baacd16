"""Mobile reach: base-joint IK for out-of-reach targets, base-then-arm execution, instruction counting."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from telerig.retarget.mobile_reach import MobileReachExecutor, MobileReachPlanner, manual_instructions
from telerig.retarget.wbc import EE_MODE, WHOLE_BODY_MODE, WholeBodyController, _rotvec
from telerig.robots.models.tiago import TiagoScene, build_tiago_kinematics

pytestmark = pytest.mark.sim

DT = 0.002  # [s]


@pytest.fixture(scope="module")
def scene() -> TiagoScene:
    return build_tiago_kinematics()


def _world_hand(scene: TiagoScene, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    data = mujoco.MjData(scene.model)
    data.qpos[:] = q
    mujoco.mj_kinematics(scene.model, data)
    site = scene.model.site(scene.ee_site).id
    return data.site_xpos[site].copy(), data.site_xmat[site].reshape(3, 3).copy()


def _quat(rotation: np.ndarray) -> np.ndarray:
    out = np.empty(4)
    mujoco.mju_mat2Quat(out, rotation.ravel())
    return out


def _turned_home_hand(scene: TiagoScene, yaw: float) -> np.ndarray:
    """The home hand orientation turned by ``yaw`` about world z, as (w, x, y, z)."""
    _, r = _world_hand(scene, scene.home.copy())
    c, s = np.cos(yaw), np.sin(yaw)
    return _quat(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ r)


def test_reachable_target_plans_no_base_motion(scene: TiagoScene) -> None:
    p, r = _world_hand(scene, scene.home.copy())
    plan = MobileReachPlanner(scene).plan(p + np.array([0.05, 0.0, -0.03]), _quat(r), scene.home)
    assert not plan.base_moves
    assert plan.reachable
    np.testing.assert_array_equal(plan.base_goal, scene.home[:3])
    assert plan.manual_instructions == 1


def test_target_out_of_reach_is_solved_with_the_base(scene: TiagoScene) -> None:
    target, orientation = np.array([0.0, 1.5, 0.95]), _turned_home_hand(scene, np.pi / 2)
    plan = MobileReachPlanner(scene).plan(target, orientation, scene.home)
    assert plan.base_moves
    assert plan.reachable
    p, _r = _world_hand(scene, plan.q_goal)
    assert np.linalg.norm(p - target) < 5e-3
    assert plan.base_goal[2] == pytest.approx(np.pi / 2, abs=0.3)  # turned to face the target
    lims = scene.limits
    assert np.all(plan.arm_goal >= lims.lower[3:])
    assert np.all(plan.arm_goal <= lims.upper[3:])


def test_target_1p5_m_away_is_reached_base_first_with_one_instruction(scene: TiagoScene) -> None:
    wbc = WholeBodyController(scene)
    executor = MobileReachExecutor(wbc)
    q = scene.home.copy()
    target, orientation = np.array([0.0, 1.5, 0.95]), _turned_home_hand(scene, np.pi / 2)
    assert np.hypot(*(target[:2] - q[:2])) == pytest.approx(1.5)
    plan = executor.instruct(target, orientation, q)
    assert executor.phase == "base"

    hand0, _ = wbc.hand_in_base(q)
    phases: list[str] = []
    for _ in range(int(20.0 / DT)):
        action = executor.action(q)
        phases.append(executor.phase)
        if executor.phase == "base":
            assert action[7] == WHOLE_BODY_MODE
        else:
            assert action[7] == EE_MODE
        before = q
        q = np.array(wbc.step(action, q, DT).q)
        if executor.phase == "base":  # driving: the hand rides on the base
            assert np.hypot(*(wbc.hand_in_base(q)[0] - hand0)[:2]) < 5e-3
        elif executor.phase == "arm":  # finishing: the base stands (after braking from its slow approach)
            assert np.hypot(*(q[:2] - before[:2])) < 1e-4
        if executor.phase == "done":
            break
    assert executor.phase == "done"
    assert phases.index("arm") > 0
    assert "base" not in phases[phases.index("arm") :]
    p, r = _world_hand(scene, q)
    assert np.linalg.norm(p - target) < 5e-3
    assert np.linalg.norm(_rotvec(r @ _world_hand(scene, plan.q_goal)[1].T)) < 0.02
    assert np.hypot(*(q[:2] - plan.base_goal[:2])) < 0.02
    # Without the planner: translate, turn, switch mode, reach. With it: one instruction.
    assert plan.manual_instructions == 4
    assert executor.instructions == 1
    assert executor.efficiency == 4.0


def test_run_reports_the_outcome(scene: TiagoScene) -> None:
    wbc = WholeBodyController(scene)
    executor = MobileReachExecutor(wbc)
    target, orientation = np.array([1.4, -0.3, 0.9]), _turned_home_hand(scene, 0.0)
    executor.instruct(target, orientation, scene.home)
    outcome = executor.run(scene.home, DT, max_time=20.0)
    assert outcome.reached
    assert outcome.position_error < 5e-3
    assert outcome.orientation_error < 0.02
    assert outcome.instructions == 1
    assert outcome.manual_instructions == 3
    assert outcome.efficiency == 3.0
    assert np.linalg.norm(_world_hand(scene, outcome.q)[0] - target) < 5e-3


def test_target_out_of_every_reach_is_flagged(scene: TiagoScene) -> None:
    plan = MobileReachPlanner(scene, max_iterations=100).plan(
        [2.0, 0.0, 2.5], _turned_home_hand(scene, 0.0), scene.home
    )
    assert not plan.reachable
    assert plan.position_error > 0.3


@pytest.mark.parametrize(
    ("goal", "expected"),
    [
        ((0.0, 0.0, 0.0), 1),
        ((1.0, 0.0, 0.0), 3),
        ((0.0, 0.0, 1.0), 3),
        ((1.0, 1.0, 1.0), 4),
        ((0.0, 0.0, 2 * np.pi), 1),
    ],
)
def test_manual_instruction_count(goal: tuple[float, float, float], expected: int) -> None:
    assert manual_instructions((0.0, 0.0, 0.0), goal) == expected


def test_bad_target_is_rejected_in_one_line(scene: TiagoScene) -> None:
    planner = MobileReachPlanner(scene)
    with pytest.raises(ValueError, match=r"target_position must be finite with shape \(3,\)") as info:
        planner.plan([1.0, np.nan, 0.9], [1, 0, 0, 0], scene.home)
    assert "\n" not in str(info.value)
    with pytest.raises(ValueError, match="non-zero quaternion"):
        planner.plan([1.0, 0.0, 0.9], [0, 0, 0, 0], scene.home)


def test_run_without_instruction_says_what_to_do(scene: TiagoScene) -> None:
    with pytest.raises(ValueError, match=r"call instruct\(target_position, target_orientation, q\) first"):
        MobileReachExecutor(WholeBodyController(scene)).run(scene.home)
