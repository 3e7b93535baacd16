"""TIAGo models: the kinematic model matches the physics scene, the servos hold and follow, frozen joints."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from telerig.robots.models import tiago
from telerig.robots.models.mjcf import load_spec, robosuite_assets
from telerig.robots.models.tiago import TIAGO_JOINTS, TiagoScene, build_tiago_kinematics
from telerig.robots.sim.tiago import build_tiago_scene

pytestmark = pytest.mark.sim


@pytest.fixture(scope="module")
def kinematics() -> TiagoScene:
    return build_tiago_kinematics()


@pytest.fixture(scope="module")
def physics() -> TiagoScene:
    return build_tiago_scene()


def _random_q(scene: TiagoScene, rng: np.random.Generator) -> np.ndarray:
    lo = np.where(np.isfinite(scene.limits.lower), scene.limits.lower, -2.0)
    hi = np.where(np.isfinite(scene.limits.upper), scene.limits.upper, 2.0)
    return rng.uniform(lo, hi)


def test_kinematic_model_has_exactly_the_ten_controlled_joints(kinematics: TiagoScene) -> None:
    model = kinematics.model
    assert tuple(model.joint(i).name for i in range(model.njnt)) == TIAGO_JOINTS
    assert model.nq == model.nv == 10
    assert kinematics.qpos_indices().tolist() == list(range(10))


def test_limits_are_infinite_for_the_base_and_the_joint_range_elsewhere(kinematics: TiagoScene) -> None:
    limits = kinematics.limits
    assert np.all(np.isinf(limits.lower[:3]))
    assert np.all(np.isinf(limits.upper[:3]))
    assert (limits.lower[3], limits.upper[3]) == (0.0, 0.35)  # torso lift [m]
    assert np.all(limits.lower[3:] <= kinematics.home[3:])
    assert np.all(kinematics.home[3:] <= limits.upper[3:])


def test_sites_are_where_the_physics_scene_has_them(kinematics: TiagoScene, physics: TiagoScene) -> None:
    rng = np.random.default_rng(0)
    kd, pd = mujoco.MjData(kinematics.model), mujoco.MjData(physics.model)
    for _ in range(5):
        q = _random_q(kinematics, rng)
        kd.qpos[:] = q
        pd.qpos[physics.qpos_indices()] = q
        mujoco.mj_kinematics(kinematics.model, kd)
        mujoco.mj_kinematics(physics.model, pd)
        for site in (kinematics.ee_site, kinematics.elbow_site):
            k_id, p_id = kinematics.model.site(site).id, physics.model.site(site).id
            np.testing.assert_allclose(kd.site_xpos[k_id], pd.site_xpos[p_id], atol=1e-9)
            np.testing.assert_allclose(kd.site_xmat[k_id], pd.site_xmat[p_id], atol=1e-9)


def test_base_joints_move_the_base_frame_by_x_y_yaw(kinematics: TiagoScene) -> None:
    data = mujoco.MjData(kinematics.model)
    data.qpos[:] = kinematics.home
    data.qpos[:3] = (1.0, -0.5, np.pi / 2)
    mujoco.mj_kinematics(kinematics.model, data)
    base = kinematics.model.body(kinematics.base_body).id
    np.testing.assert_allclose(data.xpos[base], [1.0, -0.5, 0.0], atol=1e-12)
    np.testing.assert_allclose(data.xmat[base].reshape(3, 3)[:, 0], [0.0, 1.0, 0.0], atol=1e-12)


def test_frozen_joints_keep_the_pose_of_the_original_model(kinematics: TiagoScene) -> None:
    original = load_spec(robosuite_assets() / "robots" / "tiago" / "robot.xml").compile()
    data = mujoco.MjData(original)
    for name, angle in tiago._FROZEN.items():
        data.qpos[original.joint(name).qposadr[0]] = angle
    mujoco.mj_kinematics(original, data)
    ours = mujoco.MjData(kinematics.model)
    ours.qpos[:] = 0.0
    mujoco.mj_kinematics(kinematics.model, ours)
    for body in ("left_hand", "head_2_link", "right_hand"):
        np.testing.assert_allclose(
            ours.xpos[kinematics.model.body(body).id], data.xpos[original.body(body).id], atol=1e-9
        )
        np.testing.assert_allclose(
            ours.xmat[kinematics.model.body(body).id], data.xmat[original.body(body).id], atol=1e-9
        )


def _start(scene: TiagoScene) -> tuple[mujoco.MjData, np.ndarray, np.ndarray]:
    model = scene.model
    data = mujoco.MjData(model)
    data.qpos[scene.qpos_indices()] = scene.home
    arm = np.array([model.actuator(a).id for a in scene.arm_actuators])
    base = np.array([model.actuator(a).id for a in scene.base_actuators])
    data.ctrl[arm] = scene.home[3:]
    mujoco.mj_forward(model, data)
    return data, arm, base


def test_servos_hold_home_without_contacts(physics: TiagoScene) -> None:
    data, _, _ = _start(physics)
    model = physics.model
    cup = model.joint("cup_free").qposadr[0]
    cup_start = data.qpos[cup : cup + 3].copy()
    for _ in range(500):
        mujoco.mj_step(model, data)
    np.testing.assert_allclose(data.qpos[physics.qpos_indices()], physics.home, atol=1e-3)
    np.testing.assert_allclose(data.qpos[cup : cup + 3], cup_start, atol=1e-3)  # the cup rests on the table
    cup_id = model.body("cup").id
    others = [
        c
        for c in data.contact[: data.ncon]
        if cup_id not in (model.geom_bodyid[c.geom1], model.geom_bodyid[c.geom2])
    ]
    assert others == []  # only the cup touches something (the table)


def test_base_velocity_servos_track_the_commanded_velocity(physics: TiagoScene) -> None:
    data, _, base = _start(physics)
    data.ctrl[base] = (0.3, -0.2, 0.5)  # world-frame x, y [m/s], yaw rate [rad/s]
    for _ in range(500):
        mujoco.mj_step(physics.model, data)
    np.testing.assert_allclose(data.qvel[physics.dof_indices()[:3]], (0.3, -0.2, 0.5), atol=0.02)
    np.testing.assert_allclose(data.qpos[physics.qpos_indices()[3:]], physics.home[3:], atol=0.01)


def test_arm_position_servos_reach_a_step_target(physics: TiagoScene) -> None:
    data, arm, _ = _start(physics)
    target = physics.home[3:] + np.array([0.05, 0.1, -0.1, 0.1, -0.1, 0.1, -0.1])
    data.ctrl[arm] = target
    for _ in range(400):
        mujoco.mj_step(physics.model, data)
    np.testing.assert_allclose(data.qpos[physics.qpos_indices()[3:]], target, atol=5e-3)


def test_gripper_closes_on_its_servos(physics: TiagoScene) -> None:
    data, _, _ = _start(physics)
    model = physics.model
    fingers = [model.actuator(a).id for a in physics.gripper_actuators]
    data.ctrl[fingers] = physics.gripper_closed
    for _ in range(500):
        mujoco.mj_step(model, data)
    closed = [data.qpos[model.joint(j).qposadr[0]] for j in physics.gripper_joints]
    np.testing.assert_allclose(closed, physics.gripper_closed, atol=0.05)


def test_kinematic_scene_has_no_actuators_or_world(kinematics: TiagoScene) -> None:
    assert kinematics.model.nu == 0
    assert kinematics.arm_actuators == kinematics.base_actuators == kinematics.gripper_actuators == ()
    assert kinematics.objects == ()


def test_bad_timestep_is_rejected_in_one_line() -> None:
    with pytest.raises(ValueError, match=r"timestep must be in \(0, 0.005\] s") as info:
        build_tiago_scene(timestep=0.02)
    assert "\n" not in str(info.value)
