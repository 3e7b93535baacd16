"""Every shipped simulated scene builds and holds still for 1 s of simulated time with the robot at home."""

from __future__ import annotations

import importlib
import pkgutil

import mujoco
import numpy as np
import pytest

import telerig.robots.sim as sim_package
from telerig.robots.sim.scene import SIM_SCENES, SimRobot

pytestmark = pytest.mark.sim

# Scene modules register themselves on import (``register_sim_scene``): import them all, so a new
# module joins this test without editing it.
for _module in pkgutil.iter_modules(sim_package.__path__):
    importlib.import_module(f"{sim_package.__name__}.{_module.name}")

_SIM_SECONDS = 1.0
_MAX_JOINT_DRIFT = 0.05  # [rad] or [m]: how far a joint may sag from where it started while holding
_MAX_OBJECT_SPEED = 0.01  # [m/s]
_PENETRATION = 1e-3  # [m]: soft contacts let a resting object sink a little into the table


def test_the_registry_lists_the_arm_gripper_and_bimanual_scenes() -> None:
    assert {"ur5e_robotiq85", "panda", "robotiq_2f85_bench", "bimanual_ur5e_robotiq85"} <= set(SIM_SCENES)


@pytest.mark.parametrize("name", sorted(SIM_SCENES))
def test_scene_holds_home_for_one_second(name: str) -> None:
    robot: SimRobot = SIM_SCENES[name]()
    robot.connect()
    try:
        with robot.locked() as (model, data):
            steps = round(_SIM_SECONDS / model.opt.timestep)
            free = {
                int(model.jnt_bodyid[j])
                for j in range(model.njnt)
                if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE
            }
            hinges = [j for j in range(model.njnt) if model.jnt_type[j] != mujoco.mjtJoint.mjJNT_FREE]
            start = data.qpos[model.jnt_qposadr[hinges]].copy()
        robot.step(steps)
        with robot.locked() as (model, data):
            assert np.all(np.isfinite(data.qpos))
            assert np.all(np.isfinite(data.qvel))
            drift = np.abs(data.qpos[model.jnt_qposadr[hinges]] - start)
            assert drift.max(initial=0.0) < _MAX_JOINT_DRIFT, model.joint(hinges[int(np.argmax(drift))]).name
            table = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "table_top")
            top = data.geom_xpos[table][2] + model.geom_size[table][2] if table >= 0 else -np.inf
            for body in free:
                name_ = model.body(body).name
                velocity = np.zeros(6)
                mujoco.mj_objectVelocity(model, data, mujoco.mjtObj.mjOBJ_BODY, body, velocity, 0)
                assert np.linalg.norm(velocity[3:]) < _MAX_OBJECT_SPEED, f"{name_} still moving"
                assert data.xpos[body][2] > top - _PENETRATION, f"{name_} fell through or off the table"
    finally:
        robot.close()
