"""Configuration guard, workspace shapes, deadman and settings, on tiny models (no sleeps)."""

from __future__ import annotations

import numpy as np
import pytest

from telerig.errors import ConfigError
from telerig.ir.types import FloatArray, JointCommand, JointState, Stamp
from telerig.robots.base import JointLimits
from telerig.robots.models.arm import build_arm_kinematics
from telerig.safety import (
    Box,
    ConfigurationGuard,
    Deadman,
    KinematicsModel,
    RobotSafetyConfig,
    SafetyChain,
    SafetyOutput,
    SelfCollision,
    Sphere,
    Tick,
    Violation,
    WorkspaceBounds,
    arm_guard,
)
from telerig.safety.settings import BoxZoneConfig, SphereZoneConfig, WorkspaceConfig

MS = 1_000_000
T0 = 1_000_000_000_000
WALL = 0.5  # rad
LIMITS = JointLimits(("j",), [-2.0], [2.0], [1.0], [4.0])


class Wall:
    """Forbids q > WALL on the single joint (a model-free configuration check)."""

    def __init__(self) -> None:
        self.calls = 0

    def violation(self, q: FloatArray) -> Violation | None:
        self.calls += 1
        excess = float(q[0]) - WALL
        return (
            Violation("workspace", excess, f"past the wall by {excess:.3f}", "back off")
            if excess > 0
            else None
        )


def run_chain(chain: SafetyChain, path: list[float], q0: float = 0.0) -> list[SafetyOutput]:
    t, q, outs = T0, np.array([q0]), []
    for k, target in enumerate(path):
        t += 10 * MS
        request = JointCommand(Stamp("r", k, t, t), ("j",), [target])
        out = chain.step(request, now_ns=t, measured=JointState(Stamp("m", k, t, t), ("j",), q, [0.0]))
        if out.command is not None:
            q = out.command.positions.copy()
        outs.append(out)
    return outs


def test_stop_point_matches_discrete_braking() -> None:
    guard = ConfigurationGuard([Wall()])
    tick = Tick(LIMITS)
    tick.dt_s = 0.01
    tick.previous[:] = 0.0
    tick.target[:] = 0.009  # 0.9 rad/s
    guard._a = LIMITS.acceleration.copy()
    stop = guard.stop_point(tick, np.zeros(1))
    q, v = 0.009, 0.9
    while v > 0:
        v = max(v - 4.0 * 0.01, 0.0)
        q += v * 0.01
    assert stop[0] == pytest.approx(q, abs=1e-12)


def test_guard_brakes_before_the_wall_within_the_acceleration_limit() -> None:
    chain = SafetyChain.default(LIMITS, ramp_duration_s=0.0, guard=ConfigurationGuard([Wall()]))
    outs = run_chain(chain, [min(0.02 * k, 1.5) for k in range(200)])
    q = np.array([o.command.positions[0] for o in outs if o.command is not None])
    assert q.max() <= WALL
    assert q.max() > WALL - 0.02  # it got close: the wall, not the speed, stopped it
    v = np.diff(q) / 0.01
    assert np.abs(v).max() <= 1.0 + 1e-9
    assert np.abs(np.diff(v) / 0.01).max() <= 4.0 + 1e-6
    assert chain.counts["workspace"] > 0


def test_without_the_guard_the_same_path_crosses_the_wall() -> None:
    outs = run_chain(
        SafetyChain.default(LIMITS, ramp_duration_s=0.0), [min(0.02 * k, 1.5) for k in range(200)]
    )
    assert max(o.command.positions[0] for o in outs if o.command is not None) > WALL


def test_robot_inside_a_forbidden_zone_may_move_out_but_not_deeper() -> None:
    chain = SafetyChain.default(LIMITS, ramp_duration_s=0.0, guard=ConfigurationGuard([Wall()]))
    out_of_it = run_chain(chain, [0.0] * 150, q0=0.8)
    assert out_of_it[-1].command is not None
    assert out_of_it[-1].command.positions[0] == pytest.approx(0.0)
    chain.reset()
    deeper = run_chain(chain, [1.0] * 50, q0=0.8)
    assert all(o.command is not None and o.command.positions[0] <= 0.8 for o in deeper)


def test_box_and_sphere_depths() -> None:
    box = Box([0, 0, 0], [1, 1, 1])
    pts = np.array([[0.5, 0.5, 0.5], [1.3, 0.5, 1.4], [0.1, 0.5, 0.5]])
    np.testing.assert_allclose(box.outside(pts), [0.0, 0.5, 0.0])
    np.testing.assert_allclose(box.inside(pts), [0.5, 0.0, 0.1])
    np.testing.assert_allclose(
        Sphere([0, 0, 0], 1.0).inside(np.array([[0.25, 0, 0], [2, 0, 0]])), [0.75, 0.0]
    )


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: Box([0, 0, 0], [1, 0, 1]), "must be below upper"),
        (lambda: Sphere([0, 0, 0], 0.0), "radius must be > 0"),
        (lambda: Box([0, 0], [1, 1]), "must be 3 finite values"),
    ],
)
def test_invalid_zones_say_what_to_fix(make: object, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        make()  # type: ignore[operator]


def test_unknown_point_names_what_exists() -> None:
    s = build_arm_kinematics()
    kin = KinematicsModel(s.model, s.arm_joints, base_body=s.base_body)
    with pytest.raises(ConfigError, match=r"'tool0' does not exist\. Available sites: .*grip_site"):
        WorkspaceBounds(kin, ["tool0"], box=Box([-1, -1, 0], [1, 1, 1]))


def test_keep_out_sphere_and_margin_on_the_ur5e_tool() -> None:
    s = build_arm_kinematics()
    kin = KinematicsModel(s.model, s.arm_joints, base_body=s.base_body)
    home = np.array(s.home)
    tool = WorkspaceBounds(kin, [s.ee_site], keep_out=[Sphere([0, 0, 0], 0.1)]).points(home)[0].copy()
    hit = WorkspaceBounds(kin, [s.ee_site], keep_out=[Sphere(tool + np.array([0.05, 0, 0]), 0.1, "fixture")])
    v = hit.violation(home)
    assert v is not None
    assert v.depth_m == pytest.approx(0.05)
    assert "fixture" in v.reason
    near = WorkspaceBounds(
        kin, [s.ee_site], keep_out=[Sphere(tool + np.array([0.15, 0, 0]), 0.1)], margin_m=0.06
    )
    assert near.violation(home) is not None
    assert (
        WorkspaceBounds(kin, [s.ee_site], keep_out=[Sphere(tool + np.array([0.15, 0, 0]), 0.1)]).violation(
            home
        )
        is None
    )


def test_self_collision_allows_home_and_names_the_pair() -> None:
    s = build_arm_kinematics()
    sc = SelfCollision(KinematicsModel(s.model, s.arm_joints, base_body=s.base_body), allowed=[s.home])
    assert sc.violation(np.array(s.home)) is None
    folded = np.array(s.home)
    folded[2] = 3.0
    v = sc.violation(folded)
    assert v is not None
    assert v.code == "self_collision"
    assert "links '" in v.reason


def test_deadman_counts_a_silent_device_as_released() -> None:
    deadman = Deadman(signal_timeout_s=0.1)
    assert not deadman.enabled(0)
    deadman.update(True, 0)
    assert deadman.enabled(100 * MS)
    assert not deadman.enabled(101 * MS)
    deadman.update(True, 200 * MS)
    deadman.release()
    assert not deadman.enabled(200 * MS)


def test_measured_state_slightly_past_a_limit_is_tolerated() -> None:
    chain = SafetyChain.default(LIMITS, measured_tolerance=0.05)
    out = chain.step(None, now_ns=T0, measured=JointState(Stamp("m", 0, T0, T0), ("j",), [2.04], [0.0]))
    assert out.status == "stopped"
    out = chain.step(
        None, now_ns=T0 + 10 * MS, measured=JointState(Stamp("m", 1, T0, T0), ("j",), [2.06], [0.0])
    )
    assert out.status == "estopped"
    assert out.events[0].code == "joint_limit_fault"


def test_arm_guard_builds_the_configured_checks() -> None:
    s = build_arm_kinematics()
    assert arm_guard(s, RobotSafetyConfig()) is None
    config = RobotSafetyConfig(
        workspace=WorkspaceConfig(
            box=BoxZoneConfig(lower=(-1, -1, 0.05), upper=(1, 1, 1.2)),
            keep_out=[SphereZoneConfig(center=(0, 0, 0.3), radius_m=0.12, name="column")],
        ),
        self_collision=True,
    )
    guard = arm_guard(s, config)
    assert guard is not None
    assert [type(c).__name__ for c in guard.checks] == ["WorkspaceBounds", "SelfCollision"]
    assert guard.worst(np.array(s.home)) is None
