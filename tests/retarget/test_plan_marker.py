"""The plan marker (issue 17): "plan here" plans a reach to the operator's marker, aligned into the
robot's world; garbage, out-of-range and stale marker poses are dropped or refused in one line."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from pydantic import ValidationError

from telerig.config.schema import AlignmentConfig
from telerig.errors import ConfigError
from telerig.ir.types import ControllerState, JointState, Pose, Stamp, Twist
from telerig.retarget.alignment import Alignment
from telerig.retarget.binding import BindContext
from telerig.retarget.config import WholeBodyConfig
from telerig.retarget.reach_plan import PlanMarker, ReachPlanAid
from telerig.retarget.wbc import WholeBodyController
from telerig.robots.models.tiago import TiagoScene, build_tiago_kinematics
from telerig.robots.sim.tiago_driver import MujocoTiago

pytestmark = pytest.mark.sim

NOW_NS = 1_800_000_000_000_000_000
#: Operator frame -> robot world: a quarter turn about z, the operator's desk origin on the table.
ALIGN = AlignmentConfig(
    rotation=(math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)),
    operator_origin=(0.3, -0.1, 1.0),
    robot_origin=(1.0, 0.0, 0.85),
)
HAND = np.array([0.1, -0.25, 1.0])  # operator frame [m]: maps onto (1.15, -0.2, 0.85) in the world
DOWN = np.array([0.0, 1.0, 0.0, 0.0])


class _Clock:
    def __init__(self) -> None:
        self.ns = NOW_NS

    def __call__(self) -> int:
        return self.ns


@pytest.fixture(scope="module")
def scene() -> TiagoScene:
    return build_tiago_kinematics()


def _controller(position: np.ndarray, capture_ns: int = NOW_NS, seq: int = 1) -> ControllerState:
    return ControllerState(
        Stamp("vr0/right", seq, capture_ns, capture_ns), "right", position, DOWN, "operator"
    )


def _target(aid: ReachPlanAid) -> np.ndarray:
    """The staged plan's target position [m]."""
    state: Any = aid.state()
    return np.array(state["target"]["position"])


def _aid(scene: TiagoScene, clock: _Clock) -> tuple[ReachPlanAid, PlanMarker]:
    marker = PlanMarker("vr0.right_controller", Alignment.from_config(ALIGN), max_age_s=0.5, clock_ns=clock)
    aid = ReachPlanAid(WholeBodyController(scene), max_age_s=5.0, marker=marker)
    aid.observe(scene.home.copy())
    return aid, marker


def test_plan_here_plans_to_the_aligned_marker_pose(scene: TiagoScene) -> None:
    clock = _Clock()
    aid, marker = _aid(scene, clock)
    marker.take(_controller(HAND))
    expected = np.array([1.15, -0.2, 0.85])
    assert np.allclose(marker.target(), expected, atol=1e-9)
    assert aid.command("plan")
    aid.join()
    state = aid.state()
    assert state["status"] == "staged", state["reason"]
    assert np.linalg.norm(_target(aid) - expected) < 1e-3
    assert np.linalg.norm(np.array(state["ee_path"][-1]) - expected) < 0.01  # type: ignore[index]
    assert state["marker"] == "vr0.right_controller"
    # A text designation is used once; the marker stays the standing one.
    aid.cancel("test")
    assert aid.command("target 1.0 -0.3 0.9")
    assert aid.command("plan")
    aid.join()
    assert np.allclose(_target(aid), [1.0, -0.3, 0.9])
    assert aid.state()["designated"] is None
    aid.cancel("test")
    assert aid.command("plan")
    aid.join()
    assert np.allclose(_target(aid), expected, atol=1e-3)


def test_the_marker_can_give_the_orientation_too() -> None:
    marker = PlanMarker(
        "vr0.right_controller", Alignment.from_config(ALIGN), orientation=True, clock_ns=_Clock()
    )
    marker.take(_controller(HAND))
    target = marker.target()
    assert target.shape == (7,)
    assert np.isclose(np.linalg.norm(target[3:]), 1.0)


@pytest.mark.parametrize(
    ("sample", "reason"),
    [
        (_controller(np.array([np.nan, 0.0, 1.0])), "non_finite"),
        (_controller(np.array([np.inf, 0.0, 1.0])), "non_finite"),
        (_controller(np.array([1e9, 0.0, 1.0])), "out_of_range"),
        (Pose(Stamp("p", 1, NOW_NS, NOW_NS), HAND, np.zeros(4), "operator"), "out_of_range"),
        (Twist(Stamp("sm0", 1, NOW_NS, NOW_NS), np.zeros(3), np.zeros(3), "base"), "wrong_type"),
        (JointState(Stamp("j", 1, NOW_NS, NOW_NS), ("a",), np.zeros(1), np.zeros(1)), "wrong_type"),
    ],
)
def test_garbage_marker_samples_are_dropped_and_counted(
    scene: TiagoScene, sample: object, reason: str
) -> None:
    clock = _Clock()
    aid, marker = _aid(scene, clock)
    marker.take(_controller(HAND))  # a good pose first: garbage never replaces it
    marker.take(sample)  # type: ignore[arg-type]
    assert marker.counts[reason] == 1
    assert marker.counts["taken"] == 1
    assert np.allclose(marker.target(), [1.15, -0.2, 0.85])
    assert aid.state()["marker_dropped"] == 1


def test_stale_missing_or_far_markers_are_refused_in_one_line(scene: TiagoScene) -> None:
    clock = _Clock()
    aid, marker = _aid(scene, clock)
    with pytest.raises(ValueError, match=r"no pose from the plan marker vr0\.right_controller yet") as err:
        aid.command("plan")
    marker.take(_controller(HAND, capture_ns=NOW_NS - 600_000_000))  # 0.6 s old, the limit is 0.5
    with pytest.raises(ValueError, match=r"stale \(last pose 0.6 s old, at most 0.5 s\)") as err:
        aid.command("plan")
    assert "\n" not in str(err.value)
    # 70 m in the operator frame is a valid tracker reading, but maps beyond the planner's 50 m.
    marker.take(_controller(np.array([70.0, 0.0, 1.0])))
    with pytest.raises(ValueError, match="more than 50 m from the origin"):
        aid.command("plan")
    assert aid.counts["refused"] == 3
    assert aid.status == "none"


def test_without_a_marker_or_target_plan_says_what_to_configure(scene: TiagoScene) -> None:
    aid = ReachPlanAid(WholeBodyController(scene))
    aid.observe(scene.home.copy())
    with pytest.raises(ValueError, match=r"configure a plan marker \(plan_marker .*\) or send target X Y Z"):
        aid.command("plan")
    assert aid.state()["marker"] is None


@pytest.fixture(scope="module")
def tiago() -> MujocoTiago:
    from telerig.robots.sim.tiago import build_tiago_scene

    return MujocoTiago(build_tiago_scene(with_cup=False), name="tiago0", realtime=False)


def _context(robot: MujocoTiago, drives: tuple[tuple[str, str], ...] = (("sm0", "tiago0"),)) -> BindContext:
    return BindContext("rig", "tiago0", robot, "whole_body", "sm0", "twist", ("sm0", "vr0", "vr1"), drives)


def _config(**marker: object) -> WholeBodyConfig:
    return WholeBodyConfig.model_validate(
        {"type": "wbc", "plan_marker": {"device": "vr0", "part": "right_controller", **marker}}
    )


def test_bind_feeds_the_marker_stream_to_the_plan(tiago: MujocoTiago) -> None:
    bound = _config(alignment=ALIGN.model_dump()).bind(_context(tiago))
    ((topic, take),) = bound.feeds
    assert topic.endswith("/rig/vr0/right_controller")
    plan = bound.joints.plan  # type: ignore[union-attr]
    assert plan is not None
    assert plan.marker is not None
    take(_controller(HAND, capture_ns=0))
    assert plan.marker.counts["taken"] == 1
    assert not _config().model_copy(update={"plan_marker": None}).bind(_context(tiago)).feeds


def test_bad_marker_configs_fail_with_the_fix(tiago: MujocoTiago) -> None:
    with pytest.raises(
        ConfigError, match=r"plan_marker.device 'vr9' is not a device of this rig\. Available"
    ):
        WholeBodyConfig.model_validate(
            {"type": "wbc", "plan_marker": {"device": "vr9", "part": "right_controller"}}
        ).bind(_context(tiago))
    drives = (("sm0", "tiago0"), ("vr1", "arm0"))
    with pytest.raises(ConfigError, match=r"plan_marker\.device 'vr1' drives arm0, not 'tiago0'"):
        WholeBodyConfig.model_validate(
            {"type": "wbc", "plan_marker": {"device": "vr1", "part": "right_controller"}}
        ).bind(_context(tiago, drives))
    with pytest.raises(ValidationError, match="set plan: true"):
        WholeBodyConfig.model_validate(
            {"type": "wbc", "plan": False, "plan_marker": {"part": "right_controller"}}
        )
    for bad in ({"max_age_s": 0}, {"max_age_s": math.nan}, {"part": "a/b"}, {"alignment": {"scale": -1}}):
        with pytest.raises(ValidationError):
            _config(**bad)
