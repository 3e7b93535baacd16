"""Robot hand kinematic models: loading, hand frame, couplings, limits and the URDF export."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from telerig.errors import RobotError
from telerig.robots.models.hands import HAND_MODELS, HandKinematics, kinematic_urdf, load_hand

pytestmark = pytest.mark.sim

_CACHE: dict[tuple[str, str], HandKinematics] = {}


def _hand(name: str, side: str = "right") -> HandKinematics:
    key = (name, side)
    if key not in _CACHE:
        _CACHE[key] = load_hand(name, side)  # type: ignore[arg-type]
    return _CACHE[key]


@pytest.mark.parametrize("side", ["right", "left"])
@pytest.mark.parametrize("name", HAND_MODELS)
def test_every_hand_loads_without_geometry(name: str, side: str) -> None:
    hand = _hand(name, side)
    assert hand.model.ngeom == 0
    assert hand.model.nmesh == 0
    assert hand.fingertips[0] == "kp4"
    assert len(hand.fingertips) == (4 if name == "allegro" else 5)
    assert np.all(hand.lower <= hand.upper)


@pytest.mark.parametrize("side", ["right", "left"])
@pytest.mark.parametrize("name", HAND_MODELS)
def test_hand_frame_points_fingers_along_x_and_thumb_to_the_thumb_side(name: str, side: str) -> None:
    hand = _hand(name, side)
    kp = dict(zip(sorted(hand.keypoints), hand.keypoint_positions(hand.neutral()), strict=True))
    np.testing.assert_allclose(kp[0], 0.0, atol=1e-9)
    assert kp[9][0] > 0.05
    assert abs(kp[9][1]) < 1e-9
    assert abs(kp[9][2]) < 1e-9
    thumb_side = 1.0 if side == "right" else -1.0
    assert thumb_side * kp[4][1] > 0.0
    assert thumb_side * (kp[5][1] - kp[13][1]) > 0.0  # index knuckle nearer the thumb than ring


@pytest.mark.parametrize("name", HAND_MODELS)
def test_flexing_the_fingers_moves_the_tips_to_the_palm_side(name: str) -> None:
    hand = _hand(name)
    open_tips = hand.keypoint_positions(hand.neutral(), (8, 12))
    closed = hand.lower + 0.8 * (hand.upper - hand.lower)
    closed_tips = hand.keypoint_positions(closed, (8, 12))
    assert np.all(closed_tips[:, 2] < open_tips[:, 2] - 0.02)
    assert np.all(closed_tips[:, 0] < open_tips[:, 0])


def test_inspire_couplings_are_the_hardware_linkages() -> None:
    hand = _hand("inspire")
    assert hand.actuated == (
        "joint_r_thumb_proximal_1",
        "joint_r_thumb_proximal_2",
        "joint_r_index_proximal",
        "joint_r_middle_proximal",
        "joint_r_ring_proximal",
        "joint_r_pinky_proximal",
    )
    q = np.array([0.3, 0.4, 1.0, 0.5, 0.2, 0.1])
    full = dict(zip(hand.joint_names, hand.full(q), strict=True))
    assert full["joint_r_index_distal"] == pytest.approx(1.06399 * 1.0 - 0.04545)
    assert full["joint_r_thumb_middle"] == pytest.approx(1.334 * 0.4)
    assert full["joint_r_thumb_distal"] == pytest.approx(0.667 * 0.4)


def test_coupled_bounds_keep_every_joint_in_its_range() -> None:
    for name in HAND_MODELS:
        hand = _hand(name)
        lo, hi = hand.model.jnt_range[:, 0], hand.model.jnt_range[:, 1]
        for q in (hand.lower, hand.upper):
            full = hand.full(q)
            assert np.all(full >= lo - 1e-9), name
            assert np.all(full <= hi + 1e-9), name
    # Inspire thumb pitch stops where the middle joint (x1.334) reaches its 0.68 rad limit.
    assert _hand("inspire").upper[1] == pytest.approx(0.68 / 1.334)


def test_without_couplings_every_joint_is_actuated() -> None:
    hand = load_hand("ability", couplings=False)
    assert hand.actuated == hand.joint_names
    np.testing.assert_array_equal(hand.coupling, np.eye(hand.model.nq))


def test_urdf_mimic_tags_become_couplings() -> None:
    urdf = """<robot name="r">
      <link name="base"/><link name="a"/><link name="b"/>
      <joint name="j1" type="revolute"><parent link="base"/><child link="a"/><axis xyz="0 0 1"/>
        <limit lower="0" upper="1" effort="1" velocity="1"/></joint>
      <joint name="j2" type="revolute"><parent link="a"/><child link="b"/><origin xyz="0.1 0 0"/>
        <axis xyz="0 0 1"/><limit lower="0" upper="1" effort="1" velocity="1"/>
        <mimic joint="j1" multiplier="2" offset="0.1"/></joint>
    </robot>"""
    from telerig.robots.models import hands

    spec = mujoco.MjSpec.from_string(urdf)
    for body in spec.bodies:
        if body.name != "world":
            body.mass, body.inertia, body.explicitinertial = 1e-3, [1e-7] * 3, True
    model = spec.compile()
    assert hands._couplings(model) == {1: (0, 2.0, 0.1)}


def test_unknown_model_names_the_available_ones() -> None:
    with pytest.raises(RobotError, match="Available: inspire, ability, allegro"):
        load_hand("shadow")  # type: ignore[arg-type]


@pytest.mark.parametrize("name", HAND_MODELS)
def test_urdf_export_has_the_same_forward_kinematics(name: str) -> None:
    hand = _hand(name)
    text = kinematic_urdf(hand).replace("</robot>", '<mujoco><compiler fusestatic="false"/></mujoco></robot>')
    model = mujoco.MjModel.from_xml_string(text)
    assert model.neq == model.nq - len(hand.actuated)
    data = mujoco.MjData(model)
    q = hand.lower + np.linspace(0.1, 0.9, len(hand.actuated)) * (hand.upper - hand.lower)
    for name_, value in zip(hand.joint_names, hand.full(q), strict=True):
        data.qpos[model.jnt_qposadr[model.joint(name_).id]] = value
    mujoco.mj_kinematics(model, data)
    got = np.array([data.body(hand.keypoints[i]).xpos for i in sorted(hand.keypoints)])
    np.testing.assert_allclose(got, hand.keypoint_positions(q), atol=1e-8)
