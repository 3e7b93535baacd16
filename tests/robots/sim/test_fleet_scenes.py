"""Every shipped simulated scene builds and holds still for 1 s of simulated time with the robot at home."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from telerig.registry import ROBOTS
from telerig.robots.sim.config import SimRobotConfig, shipped_scenes
from telerig.robots.sim.scene import SimRobot

pytestmark = pytest.mark.sim

# Every scene of every registered simulated robot type, as the robot configs that build it: a new
# type or scene joins this test through its config, without editing it.
_SCENES = shipped_scenes(realtime=False)

_SIM_SECONDS = 1.0
_MAX_JOINT_DRIFT = 0.05  # [rad] or [m]: how far a joint may sag from where it started while holding
_MAX_OBJECT_SPEED = 0.01  # [m/s]
_PENETRATION = 1e-3  # [m]: soft contacts let a resting object sink a little into the table


def test_every_simulated_robot_type_ships_a_scene_and_tiago_and_the_humanoid_are_built() -> None:
    sim_types = {n for n in ROBOTS.names() if issubclass(ROBOTS.get(n), SimRobotConfig)}
    built_types = {c.type for configs in _SCENES.values() for c in configs}
    assert sim_types == built_types
    assert {"mujoco_tiago", "mujoco_humanoid", "mujoco_hand", "mujoco_bimanual_arm"} <= built_types
    assert {"ur5e_robotiq85", "panda", "robotiq_2f85_bench", "bimanual_ur5e_robotiq85", "tiago"} <= set(
        _SCENES
    )


@pytest.mark.parametrize("name", sorted(_SCENES))
def test_scene_built_from_its_configs_holds_home_for_one_second(name: str) -> None:
    robots: list[SimRobot] = []
    for config in _SCENES[name]:
        built = config.build()
        assert isinstance(built, SimRobot)
        robots.append(built)
        built.connect()
    robot = robots[0]  # the robots of one scene share its physics: step it once
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
        for each in robots:
            each.close()
