"""The physics thread's pacing: ``steps_per_wake`` steps per wake-up, set from a rig's ``physics_wake_hz``."""

from __future__ import annotations

import time

import mujoco
import pytest

from telerig.robots.sim.arm import SimPhysics
from telerig.robots.sim.config import MujocoArmConfig, shipped_scenes

pytestmark = pytest.mark.sim

_XML = """
<mujoco>
  <option timestep="0.002"/>
  <worldbody>
    <body><joint name="hinge" type="hinge"/><geom type="capsule" size="0.02" fromto="0 0 0 0.2 0 0"/></body>
  </worldbody>
</mujoco>
"""


@pytest.mark.parametrize("steps_per_wake", [1, 5])
def test_the_thread_takes_its_steps_per_wake_up_and_never_runs_ahead_of_the_clock(
    steps_per_wake: int,
) -> None:
    physics = SimPhysics(mujoco.MjModel.from_xml_string(_XML), name="paced", steps_per_wake=steps_per_wake)
    physics.acquire()
    try:
        time.sleep(1.0)
    finally:
        physics.release()
    stats = physics.stats()
    assert stats.steps == steps_per_wake * stats.wakes
    assert stats.wakes >= 10, stats  # it ran (1 s of wall time is 500 steps; a loaded host may lag)
    # ... and never ahead of the wall clock by more than one wake-up's steps.
    assert stats.sim_time <= stats.wall_time + steps_per_wake * 0.002 + 1e-9


def test_zero_steps_per_wake_is_refused() -> None:
    with pytest.raises(ValueError, match="steps_per_wake must be >= 1, got 0"):
        SimPhysics(mujoco.MjModel.from_xml_string(_XML), name="paced", steps_per_wake=0)


@pytest.mark.parametrize("name", sorted(shipped_scenes()))
def test_every_simulated_robot_wakes_at_its_configs_wake_rate(name: str) -> None:
    for config in shipped_scenes(realtime=False)[name]:
        paced = type(config).model_validate(
            {**config.model_dump(), "physics_wake_hz": config.control_rate_hz}
        )
        physics = paced.build().physics  # type: ignore[attr-defined]
        try:
            assert physics.steps_per_wake == round(config.physics_rate_hz / config.control_rate_hz)
        finally:
            physics.steps_per_wake = 1  # a bimanual bench's physics is shared by the whole process


def test_by_default_the_physics_wakes_every_step() -> None:
    assert MujocoArmConfig(id="arm", realtime=False).build().physics.steps_per_wake == 1


@pytest.mark.parametrize(
    ("wake_hz", "problem"),
    [
        (50.0, "physics_wake_hz \\(50\\) must be at least control_rate_hz \\(100\\)"),
        (300.0, "divide physics_rate_hz \\(500\\) into whole steps, e.g. 100"),
    ],
)
def test_a_wake_rate_below_the_control_rate_or_off_the_step_grid_is_refused(
    wake_hz: float, problem: str
) -> None:
    with pytest.raises(ValueError, match=problem):
        MujocoArmConfig(id="arm", physics_wake_hz=wake_hz)
