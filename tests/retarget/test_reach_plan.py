"""ReachPlanAid: plan on a worker, preview, execute only the staged plan from where it was made."""

from __future__ import annotations

import json
from typing import Any

import numpy as np
import pytest

from telerig.ir.types import Stamp, Twist
from telerig.retarget.reach_plan import MAX_PREVIEW_POINTS, ReachPlanAid
from telerig.retarget.wbc import WholeBodyController
from telerig.retarget.whole_body import WholeBodyRetargeter, WholeBodySwitches
from telerig.robots.models.tiago import TiagoScene, build_tiago_kinematics

pytestmark = pytest.mark.sim

TARGET = "1.15 -0.2 0.85"
DT = 0.01


class _Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture(scope="module")
def scene() -> TiagoScene:
    return build_tiago_kinematics()


def _aid(scene: TiagoScene, clock: _Clock | None = None) -> tuple[ReachPlanAid, WholeBodyController]:
    wbc = WholeBodyController(scene)
    aid = ReachPlanAid(wbc, max_age_s=5.0, clock=clock or _Clock())
    aid.observe(scene.home.copy())
    return aid, wbc


def _staged(aid: ReachPlanAid, command: str = f"plan {TARGET}") -> dict[str, Any]:
    assert aid.command(command)
    aid.join()
    state = aid.state()
    assert state["status"] == "staged", state["reason"]
    return state


def test_plan_is_staged_with_a_bounded_finite_preview_and_fits_the_stream(scene: TiagoScene) -> None:
    aid, _ = _aid(scene)
    assert aid.state()["status"] == "none"
    state = _staged(aid)
    ee, base = np.array(state["ee_path"]), np.array(state["base_path"])
    assert 2 <= len(ee) <= MAX_PREVIEW_POINTS
    assert len(base) == len(ee)
    assert np.all(np.isfinite(ee))
    assert np.all(np.isfinite(base))
    assert np.linalg.norm(ee[-1] - np.array([1.15, -0.2, 0.85])) < 0.01
    assert state["base_moves"] is True
    assert isinstance(state["planned_ms"], float)
    assert len(json.dumps(state)) < 16 << 10  # the catalogue's JSON limit is 64 KiB
    assert aid.update(Twist(Stamp("sm0", 1, 0, 0), np.zeros(3), np.zeros(3), "base"))  # publish once
    assert not aid.update(Twist(Stamp("sm0", 2, 0, 0), np.zeros(3), np.zeros(3), "base"))


def test_nothing_moves_until_executed_then_the_plan_drives_to_the_target(scene: TiagoScene) -> None:
    clock = _Clock()
    aid, wbc = _aid(scene, clock)
    state = _staged(aid)
    q = scene.home.copy()
    assert aid.action(q, 0.0) is None  # staged only
    assert aid.command(f"execute {state['id']}")
    for _ in range(3000):
        action = aid.action(q, 0.0)
        if action is None:
            break
        q = np.array(wbc.step(action, q, DT).q)
        aid.observe(q)
        clock.t += DT
    assert aid.status == "done"
    assert aid.instructions == 1
    assert aid.manual_instructions == state["manual"]


@pytest.mark.parametrize(
    ("text", "why"),
    [
        ("", "plan command must be"),
        ("plan", "no target designated"),
        ("plan 1 2", "needs X Y Z"),
        ("plan nan 0 1", "finite"),
        ("plan inf 0 1", "finite"),
        ("plan 1e300 0 1", "from the origin"),
        ("plan 1 0 1 0 0 0 0", "non-zero quaternion"),
        ("plan one two three", "takes numbers"),
        ("target 1 0", "needs X Y Z"),
        ("execute", "needs the staged plan's id"),
        ("execute 1-abc", "no plan is staged"),
        ("launch 1 2 3", "plan command must be"),
        ("x " * 600, "plan command must be"),
        ("\x00\xff", "plan command must be"),
    ],
)
def test_garbage_is_refused_in_one_line_and_counted(scene: TiagoScene, text: str, why: str) -> None:
    aid, _ = _aid(scene)
    with pytest.raises(ValueError, match=why) as err:
        aid.command(text)
    assert "\n" not in str(err.value)
    assert aid.counts["refused"] == 1
    assert aid.state()["refused"] == 1
    assert aid.status == "none"


def test_forged_stale_or_moved_plans_are_refused(scene: TiagoScene) -> None:
    clock = _Clock()
    aid, _ = _aid(scene, clock)
    state = _staged(aid)
    with pytest.raises(ValueError, match="is not the staged plan"):
        aid.command("execute 1-00000000")
    assert aid.status == "staged"  # a forged id changes nothing
    clock.t += 6.0
    with pytest.raises(ValueError, match="s old"):
        aid.command(f"execute {state['id']}")
    assert aid.state()["status"] == "failed"
    assert "stale" in str(aid.state()["reason"])

    state = _staged(aid)
    moved = scene.home.copy()
    moved[0] += 0.2  # the base was driven since planning
    aid.observe(moved)
    with pytest.raises(ValueError, match="robot moved"):
        aid.command(f"execute {state['id']}")
    assert aid.state()["status"] == "failed"
    assert aid.counts["refused"] == 3
    assert aid.counts["executed"] == 0


def test_designated_target_cancel_and_a_robot_held_by_safety(scene: TiagoScene) -> None:
    clock = _Clock()
    aid, _ = _aid(scene, clock)
    assert aid.command(f"target {TARGET}")
    state = _staged(aid, "plan")
    assert state["designated"] == [1.15, -0.2, 0.85]
    assert aid.command("cancel")
    assert aid.status == "cancelled"
    assert not aid.command("cancel")  # nothing left to cancel
    state = _staged(aid, "plan")
    assert aid.command(f"execute {state['id']}")
    q = scene.home.copy()
    assert aid.action(q, 0.0) is not None
    for _ in range(60):  # the chain holds the robot: the command it starts from never changes
        clock.t += DT
        aid.action(q, 0.0)
    assert aid.state()["status"] == "failed"
    assert "safety" in str(aid.state()["reason"])


def test_unreachable_target_fails_with_the_reason(scene: TiagoScene) -> None:
    aid, _ = _aid(scene)
    assert aid.command("plan 1.0 0.0 3.5")  # far above what the torso and arm reach
    aid.join()
    state = aid.state()
    assert state["status"] == "failed"
    assert "out of reach" in str(state["reason"])


def test_the_retargeter_follows_the_plan_until_the_operator_takes_over(scene: TiagoScene) -> None:
    wbc = WholeBodyController(scene)
    retargeter = WholeBodyRetargeter(wbc, WholeBodySwitches(), scene.joints)
    aid = retargeter.plan = ReachPlanAid(wbc, max_age_s=5.0)
    q = scene.home.copy()
    still = Twist(Stamp("sm0", 1, 0, 0), np.zeros(3), np.zeros(3), "base")
    command, _ = retargeter(still, q, DT)
    assert command is not None
    state = _staged(aid)
    assert aid.command(f"execute {state['id']}")
    for seq in range(2, 60):  # the operator's SpaceMouse at rest: the plan drives the base forward
        command, _ = retargeter(Twist(Stamp("sm0", seq, 0, 0), np.zeros(3), np.zeros(3), "base"), q, DT)
        assert command is not None
        q = np.array(command.positions)
    assert q[0] > 0.005
    assert aid.state()["status"] == "executing"
    push = Twist(Stamp("sm0", 99, 0, 0), np.array([0.0, 0.1, 0.0]), np.zeros(3), "base")
    retargeter(push, q, DT)
    assert aid.state()["status"] == "cancelled"
    assert aid.state()["reason"] == "the operator took over"
