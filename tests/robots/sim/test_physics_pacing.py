"""The physics thread's pacing: ``steps_per_wake`` steps per wake-up, set from a rig's ``physics_wake_hz``,
and kept half a wake period away from the control loop's state reads."""

from __future__ import annotations

import statistics
import time

import mujoco
import pytest

from telerig.robots.sim.arm import SimPhysics, between_reads
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
            assert physics.wakes_between_reads  # the control rate is the wake rate
        finally:
            physics.steps_per_wake = 1  # a bimanual bench's physics is shared by the whole process
            physics.wakes_between_reads = False


def test_by_default_the_physics_wakes_every_step() -> None:
    physics = MujocoArmConfig(id="arm", realtime=False).build().physics
    assert physics.steps_per_wake == 1
    assert not physics.wakes_between_reads


def test_the_wakes_keep_between_the_reads_only_where_the_control_rate_fits_whole_wake_periods() -> None:
    twice = MujocoArmConfig(id="arm", realtime=False, physics_wake_hz=250.0, control_rate_hz=125.0)
    assert twice.build().physics.wakes_between_reads  # a read every second wake, at one phase
    off_grid = MujocoArmConfig(id="arm", realtime=False, physics_wake_hz=250.0, control_rate_hz=100.0)
    assert not off_grid.build().physics.wakes_between_reads  # a read every 2.5 wakes has no phase


W = 10_000_000  # a wake period of 10 ms [ns]


def test_a_wake_in_the_middle_between_two_reads_stays_there() -> None:
    assert between_reads(1_000 + W // 2, 1_000, W) == 1_000 + W // 2
    assert between_reads(1_000 + W // 2 + 7 * W, 1_000, W) == 1_000 + W // 2 + 7 * W  # any later wake


@pytest.mark.parametrize("after_read_ns", [300_000, W - 300_000, 0, W // 2 + 1])
@pytest.mark.parametrize("reads_every", [1, 2])
def test_a_wake_next_to_the_reads_moves_to_the_middle(after_read_ns: int, reads_every: int) -> None:
    # The wakes and the reads of a control loop at the same rate (or half of it), the wakes next to
    # the reads: each wake moves a quarter of the way, so within ~20 wakes they are in the middle.
    deadline, read = 50 * W + after_read_ns, 50 * W
    first = abs(deadline % W - W // 2)
    for wake in range(20):
        if wake % reads_every == 0:
            read += reads_every * W
        deadline = between_reads(deadline, read - reads_every * W, W) + W
    assert abs((deadline - read) % W - W // 2) <= max(1, first // 50)


def test_the_physics_thread_wakes_between_the_reads_of_one_control_loop() -> None:
    # A reader at 100 Hz that starts 0.5 ms after a wake of a physics waking at 100 Hz (the worst
    # phase: a read that jitters by a millisecond repeats a state or skips one). How old the state
    # each read finds is [ms]: kept between the reads, half a period; left alone, next to 0 or 10.
    def ages_ms(align: bool) -> list[float]:
        physics = SimPhysics(mujoco.MjModel.from_xml_string(_XML), name="aligned", steps_per_wake=5)
        physics.wakes_between_reads = align
        physics.acquire()
        try:
            first = physics.step_ns
            while physics.step_ns == first:
                time.sleep(0.0001)
            ages = []
            next_read = time.monotonic() + 0.0005
            for _ in range(150):
                next_read += 0.010
                time.sleep(max(0.0, next_read - time.monotonic()))
                with physics.lock:
                    stamp = physics.read_stamp()
                ages.append((time.time_ns() - stamp) / 1e6)
            return ages[50:]  # after 0.5 s: ~50 wakes to settle in
        finally:
            physics.release()

    def next_to_a_wake(ages: list[float]) -> float:
        return sum(not 2.0 < a < 8.0 for a in ages) / len(ages)

    aligned, alone = ages_ms(True), ages_ms(False)
    assert 3.0 < statistics.median(aligned) < 7.0, aligned
    assert next_to_a_wake(aligned) <= 0.2, aligned
    assert next_to_a_wake(alone) >= 0.5, alone  # the test tells one from the other
