"""Arm pose retargeting in relative mode: clutch re-anchoring, frame rotation, motion scale, fixtures."""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np
import pytest

from telerig.config.schema import AlignmentConfig
from telerig.ir.frames import quat_angle, quat_from_axis_angle, quat_multiply
from telerig.ir.types import ControllerState, Stamp
from telerig.retarget.alignment import Alignment
from telerig.retarget.arm import ArmPoseRetargeter
from telerig.retarget.arm_ik import ArmIK
from telerig.retarget.clutch import Clutch
from telerig.retarget.config import ArmPoseConfig, FixtureConfig, FixturesConfig, MotionScaleConfig
from telerig.retarget.fixtures import Fixture, FixtureSet
from telerig.retarget.scaling import ScaleKnob
from telerig.robots.models.arm import build_arm_kinematics

IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])
Z = np.array([0.0, 0.0, 1.0])
YAW90 = quat_from_axis_angle(Z, math.pi / 2)
HAND0 = np.array([0.4, 0.0, 1.1])
DT = 0.01


@pytest.fixture(scope="module")
def ik() -> ArmIK:
    return ArmIK(build_arm_kinematics())


def _sample(
    p: Iterable[float], *, held: bool, q: np.ndarray = IDENTITY, seq: int = 0, buttons: Iterable[str] = ()
) -> ControllerState:
    names = {*buttons, "a"} if held else set(buttons)
    return ControllerState(
        Stamp("vr0", seq, seq * 10_000_000, seq * 10_000_000),
        "right",
        np.array(p),
        q,
        "operator",
        buttons=frozenset(names),
    )


def _relative(ik: ArmIK, **kwargs: object) -> ArmPoseRetargeter:
    alignment = kwargs.pop("alignment", Alignment(IDENTITY, np.zeros(3), np.zeros(3)))
    assert isinstance(alignment, Alignment)
    return ArmPoseRetargeter(alignment, ik, ik.joint_names, mode="relative", clutch=Clutch("a"), **kwargs)  # type: ignore[arg-type]


def test_released_clutch_holds_the_current_joints(ik: ArmIK) -> None:
    r = _relative(ik)
    q = ik.home + 0.05
    command, residual = r(_sample(HAND0, held=False), q, DT)
    assert command is not None
    assert residual is None
    np.testing.assert_array_equal(command.positions, q)
    assert not r.engaged


def test_press_anchors_at_the_end_effector_pose(ik: ArmIK) -> None:
    r = _relative(ik)
    q = ik.home.copy()
    ee_p, ee_q = ik.forward(q)
    r(_sample(HAND0 + np.array([0.3, 0.0, 0.0]), held=True), q, DT)
    assert r.target is not None
    np.testing.assert_allclose(r.target[0], ee_p, atol=1e-12)
    assert quat_angle(r.target[1], ee_q) < 1e-12


def test_hold_moves_by_the_hand_displacement_rotated_into_the_base_frame(ik: ArmIK) -> None:
    r = _relative(ik, alignment=Alignment(YAW90, np.zeros(3), np.zeros(3)))
    q = ik.home.copy()
    ee_p, ee_q = ik.forward(q)
    r(_sample(HAND0, held=True), q, DT)
    turn = quat_from_axis_angle(Z, 0.2)
    r(_sample(HAND0 + np.array([0.05, 0.0, 0.0]), held=True, q=turn), q, DT)
    assert r.target is not None
    # Operator +x is robot +y under a 90° yaw alignment; the hand's yaw is the same yaw in the base frame.
    np.testing.assert_allclose(r.target[0], ee_p + np.array([0.0, 0.05, 0.0]), atol=1e-12)
    assert quat_angle(r.target[1], quat_multiply(turn, ee_q)) < 1e-12


def test_release_then_press_reanchors_and_ignores_motion_while_released(ik: ArmIK) -> None:
    r = _relative(ik)
    q = ik.home.copy()
    r(_sample(HAND0, held=True), q, DT)
    r(_sample(HAND0 + np.array([0.05, 0.0, 0.0]), held=True), q, DT)
    r(_sample(HAND0 + np.array([0.05, 0.0, 0.0]), held=False), q, DT)
    r(_sample(HAND0 + np.array([0.25, 0.1, 0.0]), held=False), q, DT)  # repositioning the hand: no motion
    q_moved = ik.home + np.array([0.1, -0.1, 0.1, 0.0, 0.0, 0.0])
    ee_p, _ = ik.forward(q_moved)
    r(_sample(HAND0 + np.array([0.25, 0.1, 0.0]), held=True), q_moved, DT)
    assert r.target is not None
    np.testing.assert_allclose(r.target[0], ee_p, atol=1e-12)
    r(_sample(HAND0 + np.array([0.25, 0.1, 0.02]), held=True), q_moved, DT)
    np.testing.assert_allclose(r.target[0], ee_p + np.array([0.0, 0.0, 0.02]), atol=1e-12)


def test_15_cm_hand_motion_at_scale_0_005_moves_the_tool_0_75_mm(ik: ArmIK) -> None:
    r = _relative(ik, scale=ScaleKnob(0.005))
    q = ik.home.copy()
    ee0, _ = ik.forward(q)
    r(_sample(HAND0, held=True), q, DT)
    for k in range(20):  # let IK converge on the new target
        command, _ = r(_sample(HAND0 + np.array([0.15, 0.0, 0.0]), held=True, seq=k + 1), q, DT)
        assert command is not None
        q = command.positions
    ee, _ = ik.forward(q)
    np.testing.assert_allclose(ee - ee0, [0.00075, 0.0, 0.0], atol=1e-5)


def test_changing_the_scale_mid_motion_does_not_jump_the_target(ik: ArmIK) -> None:
    knob = ScaleKnob(1.0, step_factor=10.0)
    r = _relative(ik, scale=knob)
    q = ik.home.copy()
    r(_sample(HAND0, held=True), q, DT)
    r(_sample(HAND0 + np.array([0.1, 0.0, 0.0]), held=True), q, DT)
    assert r.target is not None
    before = r.target[0].copy()
    knob.step(-1)
    r(_sample(HAND0 + np.array([0.1, 0.0, 0.0]), held=True), q, DT)
    np.testing.assert_allclose(r.target[0], before, atol=1e-12)
    r(_sample(HAND0 + np.array([0.2, 0.0, 0.0]), held=True), q, DT)
    np.testing.assert_allclose(r.target[0], before + np.array([0.01, 0.0, 0.0]), atol=1e-12)


def test_axis_fixture_keeps_only_motion_along_its_axis(ik: ArmIK) -> None:
    fixtures = FixtureSet([Fixture("x", "axis", (1.0, 0.0, 0.0), keep_orientation=True)])
    r = _relative(ik, fixtures=fixtures)
    q = ik.home.copy()
    ee_p, ee_q = ik.forward(q)
    r(_sample(HAND0, held=True), q, DT)
    r(_sample(HAND0 + np.array([0.03, 0.04, -0.05]), held=True, q=quat_from_axis_angle(Z, 0.4)), q, DT)
    assert r.target is not None
    np.testing.assert_allclose(r.target[0], ee_p + np.array([0.03, 0.0, 0.0]), atol=1e-12)
    assert quat_angle(r.target[1], ee_q) < 1e-12


def test_absolute_mode_with_fixture_constrains_from_where_it_was_switched_on(ik: ArmIK) -> None:
    fixtures = FixtureSet([Fixture("free", "free"), Fixture("table", "plane", (0.0, 0.0, 1.0))])
    r = ArmPoseRetargeter(
        Alignment(IDENTITY, np.zeros(3), np.zeros(3)), ik, ik.joint_names, fixtures=fixtures
    )
    q = ik.home.copy()
    r(_sample([0.4, 0.1, 0.3], held=False), q, DT)
    fixtures.select("table")
    r(_sample([0.4, 0.1, 0.3], held=False), q, DT)
    r(_sample([0.45, 0.12, 0.5], held=False), q, DT)
    assert r.target is not None
    np.testing.assert_allclose(r.target[0], [0.45, 0.12, 0.3], atol=1e-12)


def test_absolute_mode_without_aids_is_the_aligned_pose(ik: ArmIK) -> None:
    alignment = AlignmentConfig(operator_origin=(0.4, 0.0, 1.1), robot_origin=(0.5, 0.1, 0.3))
    r = ArmPoseConfig(alignment=alignment).build(ik, ik.joint_names)
    command, residual = r(_sample([0.42, 0.0, 1.1], held=False), ik.home, DT)
    assert command is not None
    assert residual is not None
    assert r.target is not None
    np.testing.assert_allclose(r.target[0], [0.52, 0.1, 0.3], atol=1e-12)


def test_config_builds_a_relative_retargeter_with_its_aids(ik: ArmIK) -> None:
    cfg = ArmPoseConfig(
        mode="relative",
        clutch_button="grip",
        scale=MotionScaleConfig(initial=0.1, up_button="b", down_button="a"),
        fixtures=FixturesConfig(options=[FixtureConfig(name="free", kind="free")], cycle_button="thumbstick"),
    )
    r = cfg.build(ik, ik.joint_names, frame="arm0/base")
    assert r.mode == "relative"
    assert r.motion_scale is not None
    assert r.motion_scale.scale == pytest.approx(0.1)
    assert r.fixtures is not None
    assert r.fixtures.state()["frame"] == "arm0/base"


def test_grip_axis_counts_as_the_grip_button() -> None:
    clutch = Clutch("grip")
    s = ControllerState(Stamp("vr0", 0, 0, 0), "right", np.zeros(3), IDENTITY, "operator", grip=0.8)
    assert clutch.update(s) == "press"
    assert clutch.update(s) == "hold"
    released = ControllerState(Stamp("vr0", 1, 0, 0), "right", np.zeros(3), IDENTITY, "operator", grip=0.1)
    assert clutch.update(released) == "release"
    assert clutch.update(released) == "idle"
