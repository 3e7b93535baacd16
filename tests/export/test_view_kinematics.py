"""The end-effector path of ``telerig view``: forward kinematics through the robot model agrees with
the simulated arm scene (a different model build: actuated fingers, base on a table) at the same
joint positions, for prefixed joint names too."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from telerig.errors import ExportError
from telerig.export.view_base import end_effector_path
from telerig.robots.models import ARM_MODELS
from telerig.robots.sim.scene import TABLE_TOP, build_arm_scene

pytestmark = pytest.mark.sim


@pytest.mark.parametrize("model", ["ur5e_robotiq85", "panda"])
def test_path_matches_the_simulated_scene_at_the_same_joints(model: str) -> None:
    scene = build_arm_scene(model, with_cube=False)
    data = mujoco.MjData(scene.model)
    rng = np.random.default_rng(0)
    joints = scene.arm_joints
    q = scene.home + rng.uniform(-0.6, 0.6, size=(5, len(joints)))
    expected = []
    for row in q:
        for name, value in zip(joints, row, strict=True):
            data.qpos[scene.model.jnt_qposadr[scene.model.joint(name).id]] = value
        mujoco.mj_kinematics(scene.model, data)
        expected.append(data.site_xpos[scene.model.site(scene.ee_site).id] - [0.0, 0.0, TABLE_TOP])
    for names in (joints, tuple(f"left_{j}" for j in joints), tuple(f"arm0.{j}" for j in joints)):
        # Columns in another order than the model's: matched by name.
        order = np.arange(len(joints))[::-1]
        path = end_effector_path(model, tuple(names[i] for i in order), q[:, order])
        np.testing.assert_allclose(path, np.array(expected), atol=1e-9)
    assert len(ARM_MODELS[model].joints) == len(joints)


def test_a_missing_joint_is_one_line() -> None:
    names = ("shoulder_pan_joint", "shoulder_lift_joint")
    with pytest.raises(ExportError, match="elbow_joint"):
        end_effector_path("ur5e_robotiq85", names, np.zeros((3, 2)))
