"""Tests of the differential arm IK."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import mink
import mujoco
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from telerig.config.schema import AlignmentConfig
from telerig.devices.validate import SampleGate
from telerig.errors import RobotError
from telerig.ir.types import ControllerState, GripperCommand, JointCommand, Stamp
from telerig.retarget.alignment import Alignment
from telerig.retarget.arm import AbsolutePoseRetargeter
from telerig.retarget.arm_ik import ArmIK, MinkReference
from telerig.robots.models.arm import ArmScene, build_arm_kinematics
from telerig.robots.sim.arm import MujocoArm
from telerig.robots.sim.scene import build_arm_scene

pytestmark = pytest.mark.sim


@pytest.fixture(scope="module")
def kinematics() -> ArmScene:
    return build_arm_kinematics()


@pytest.fixture(scope="module")
def ik(kinematics: ArmScene) -> ArmIK:
    return ArmIK(kinematics)


def _rotated(wxyz: np.ndarray, axis: np.ndarray, angle: float) -> np.ndarray:
    turn = mink.SO3.exp(np.asarray(axis) * angle)
    return np.asarray((mink.SO3(wxyz) @ turn).wxyz)


def test_reaches_reachable_target(ik: ArmIK) -> None:
    home_pos, home_quat = ik.forward(ik.home)
    target_pos = home_pos + np.array([0.1, -0.15, -0.2])
    target_quat = _rotated(home_quat, np.array([0.0, 0.0, 1.0]), 0.4)
    q = np.array(ik.home)
    for _ in range(200):
        result = ik.solve(target_pos, target_quat, q, dt=0.01)
        q = result.q
    assert result.position_error < 2e-3
    assert result.orientation_error < 0.02
    assert not result.flagged
    reached_pos, _ = ik.forward(q)
    np.testing.assert_allclose(reached_pos, target_pos, atol=2e-3)


def test_unreachable_target_is_flagged(ik: ArmIK) -> None:
    home_pos, home_quat = ik.forward(ik.home)
    q = np.array(ik.home)
    for _ in range(100):
        result = ik.solve(home_pos + np.array([2.0, 0.0, 0.0]), home_quat, q, dt=0.01)
        q = result.q
    assert result.flagged
    assert result.position_error > 1.0
    assert np.all(np.isfinite(q))


def test_step_respects_velocity_and_joint_limits(kinematics: ArmScene) -> None:
    ik = ArmIK(kinematics, velocity_limit=1.0)
    lower = kinematics.model.jnt_range[:, 0]
    upper = kinematics.model.jnt_range[:, 1]
    home_pos, home_quat = ik.forward(ik.home)
    dt = 0.01
    q = np.array(ik.home)
    for _ in range(50):
        result = ik.solve(home_pos + np.array([-0.3, 0.4, 0.1]), home_quat, q, dt=dt)
        assert np.all(np.abs(result.q - q) <= 1.0 * dt + 1e-9)
        assert np.all(result.q >= lower - 1e-9)
        assert np.all(result.q <= upper + 1e-9)
        q = result.q


def test_targets_are_in_the_base_frame(kinematics: ArmScene) -> None:
    model = build_arm_kinematics().model
    model.body_pos[model.body(kinematics.base_body).id] = [1.0, -2.0, 0.5]
    shifted = ArmIK(dataclasses.replace(kinematics, model=model))
    reference = ArmIK(kinematics)
    target_pos, target_quat = reference.forward(reference.home)
    target_pos = target_pos + np.array([0.05, 0.05, -0.05])
    q_ref = q_shift = np.array(kinematics.home)
    for _ in range(20):
        q_ref = reference.solve(target_pos, target_quat, q_ref, dt=0.01).q
        q_shift = shifted.solve(target_pos, target_quat, q_shift, dt=0.01).q
    np.testing.assert_allclose(q_shift, q_ref, atol=1e-9)


def _unlimited_shoulder() -> ArmScene:
    scene = build_arm_kinematics()
    scene.model.jnt_limited[0] = 0  # its range now reads as [0, 0]
    return scene


_CASES: dict[str, tuple[Callable[[], ArmScene], dict[str, float]]] = {
    "ur5e kinematics": (build_arm_kinematics, {}),
    "ur5e scene": (build_arm_scene, {}),  # finger joints and a free cube: frozen in mink's QP
    "panda": (lambda: build_arm_kinematics("panda"), {}),
    "ur5e, other costs": (
        build_arm_kinematics,
        {"velocity_limit": 0.5, "posture_cost": 0.2, "lm_damping": 1.0},
    ),
    "ur5e, shoulder unlimited": (_unlimited_shoulder, {}),
}


@pytest.mark.parametrize("name", sorted(_CASES))
def test_one_step_is_the_qp_mink_builds(name: str) -> None:
    """The hand-built box QP is mink's problem: same step from any joints to any target, to 1e-8 rad,
    near the joint limits (the bounds bind), far out of reach (the LM damping grows), at any dt."""
    build, settings = _CASES[name]
    scene = build()
    ik = ArmIK(scene, iterations=1, **settings)
    reference = MinkReference(ik)
    lower, upper = ik._lower, ik._upper
    rng = np.random.default_rng(7)
    home_p, _ = ik.forward(scene.home)
    span_lower, span_upper = np.maximum(lower, -2 * np.pi), np.minimum(upper, 2 * np.pi)
    for k in range(60):
        q = span_lower + rng.uniform(0.0, 1.0, ik._n) * (span_upper - span_lower)
        if k % 4 == 0:  # on a limit
            joint = rng.integers(ik._n)
            q[joint] = span_upper[joint] if k % 8 == 0 else span_lower[joint]
        position = home_p + rng.normal(0.0, 0.3 if k % 3 else 1.5, 3)
        orientation = rng.normal(size=4)
        orientation /= np.linalg.norm(orientation)
        dt = float(rng.choice([0.001, 0.01, 0.05]))
        expected = reference.solve(position, orientation, q, dt)
        got = ik.solve(position, orientation, q, dt)
        np.testing.assert_allclose(got.q, expected.q, atol=1e-8, err_msg=f"case {k}: q={q} dt={dt}")
        assert got.position_error == pytest.approx(expected.position_error, abs=1e-7)
        assert got.orientation_error == pytest.approx(expected.orientation_error, abs=1e-7)
        assert got.flagged == expected.flagged


def test_a_ball_joint_is_refused_in_one_line() -> None:
    scene = build_arm_kinematics()
    scene.model.jnt_type[2] = mujoco.mjtJoint.mjJNT_BALL
    with pytest.raises(RobotError, match="hinge or slide joints"):
        ArmIK(scene)


def test_an_infinite_speed_limit_is_refused(kinematics: ArmScene) -> None:
    with pytest.raises(ValueError, match="velocity_limit must be positive and finite"):
        ArmIK(kinematics, velocity_limit=np.inf)


def test_full_scene_solves_like_the_kinematic_model(kinematics: ArmScene) -> None:
    full = ArmIK(build_arm_scene())  # base 0.8 m up, finger joints and a free cube
    reference = ArmIK(kinematics)
    target_pos, target_quat = reference.forward(reference.home)
    target_pos = target_pos + np.array([0.05, -0.05, 0.05])
    q_ref = q_full = np.array(kinematics.home)
    for _ in range(20):
        q_ref = reference.solve(target_pos, target_quat, q_ref, dt=0.01).q
        q_full = full.solve(target_pos, target_quat, q_full, dt=0.01).q
    np.testing.assert_allclose(q_full, q_ref, atol=1e-6)


def test_unknown_site_names_available_ones(kinematics: ArmScene) -> None:
    with pytest.raises(RobotError, match=r"site 'nope' not found\. Available: "):
        ArmIK(dataclasses.replace(kinematics, ee_site="nope"))


def test_rejects_a_wrongly_shaped_target(ik: ArmIK) -> None:
    with pytest.raises(ValueError, match="target_position"):
        ik.solve(np.zeros(2), np.array([1.0, 0, 0, 0]), ik.home, dt=0.01)


def test_sim_arm_tracks_a_moving_target_through_ik(kinematics: ArmScene) -> None:
    ik = ArmIK(kinematics)
    home_pos, home_quat = ik.forward(ik.home)
    dt = 0.01  # control period [s] = 5 physics steps
    with MujocoArm(realtime=False) as arm:
        q = arm.read_state().positions
        for k in range(300):
            t = k * dt
            # A 6 cm circle in the horizontal plane, 0.2 rad/s.
            target = home_pos + 0.06 * np.array([np.cos(0.2 * t) - 1.0, np.sin(0.2 * t), 0.0])
            result = ik.solve(target, home_quat, q, dt)
            arm.send(JointCommand(Stamp.now("test", k), ik.joint_names, result.q))
            arm.step(5)
            q = arm.read_state().positions
        reached_pos, _ = ik.forward(q)
    assert not result.flagged
    assert np.linalg.norm(reached_pos - target) < 5e-3


def test_sim_arm_picks_up_the_cube_through_ik(kinematics: ArmScene) -> None:
    ik = ArmIK(kinematics)
    _, down = ik.forward(ik.home)
    dt = 0.01
    with MujocoArm(realtime=False) as arm:
        with arm.locked() as (_, data):
            cube_start = data.body("cube").xpos.copy()
            base = data.body(kinematics.base_body).xpos.copy()
        q = arm.read_state().positions

        def move_to(position: np.ndarray, n: int) -> None:
            nonlocal q
            for k in range(n):
                result = ik.solve(position, down, q, dt)
                arm.send(JointCommand(Stamp.now("test", k), ik.joint_names, result.q))
                arm.step(5)
                q = arm.read_state().positions

        cube = cube_start - base  # base frame (axes aligned with the world)
        move_to(cube + np.array([0.0, 0.0, 0.1]), 150)
        move_to(cube, 100)
        arm.send_gripper(GripperCommand(Stamp.now("test", 0), opening=0.0))
        arm.step(200)
        move_to(cube + np.array([0.0, 0.0, 0.15]), 150)
        with arm.locked() as (_, data):
            lifted = data.body("cube").xpos[2] - cube_start[2]
    assert lifted > 0.12


# -- what a control node's gate admits, the arm retargeter computes with (issue 11, finding 1) ----

_EXTREME = st.one_of(
    st.sampled_from([math.nan, math.inf, -math.inf, 1e300, -1e300, 1e154, 5e-324, 0.0]), st.floats()
)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    position=st.lists(st.one_of(_EXTREME, st.floats(-3.0, 3.0)), min_size=3, max_size=3),
    orientation=st.lists(st.one_of(_EXTREME, st.floats(-2.0, 2.0)), min_size=4, max_size=4),
)
def test_whatever_the_gate_admits_the_arm_retargeter_turns_into_finite_joints(
    ik: ArmIK, position: list[float], orientation: list[float]
) -> None:
    now = 1_800_000_000_000_000_000
    sample = ControllerState(Stamp("vr0/right", 1, now, now), "right", position, orientation, "operator")
    admitted = SampleGate().admit("vr0/right_controller", sample, now)
    if isinstance(admitted, str):
        return  # rejected and counted: nothing downstream sees it
    alignment = Alignment.from_config(AlignmentConfig(operator_origin=(0.4, 0.0, 1.1)))
    retargeter = AbsolutePoseRetargeter(alignment, ik, ik.joint_names)
    command, _ = retargeter(admitted, np.array(ik.home), 0.01)
    assert command is not None
    assert np.all(np.isfinite(command.positions))
