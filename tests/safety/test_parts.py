"""Gripper and base limits alone, and RobotSafety sending through them (injected times, no sleeps)."""

from __future__ import annotations

import math
from collections.abc import Iterator

import pytest

from telerig.config.safety import BaseSafetyConfig, RobotSafetyConfig
from telerig.errors import ConfigError
from telerig.ir.types import BaseVelocity, GripperCommand, Stamp
from telerig.robots.sim.arm import MujocoArm
from telerig.safety import SafetyChain, SafetyEvent, SafetySupervisor
from telerig.safety.parts import BaseLimit, GripperLimit

MS = 1_000_000  # ns
T0 = 1_000_000_000_000  # common-clock origin [ns]
STAMP = Stamp("op", 0, T0, T0)


def grip(opening: float, force: float = 0.0) -> GripperCommand:
    return GripperCommand(STAMP, opening, force)


def vel(vx: float, vy: float = 0.0, wz: float = 0.0) -> BaseVelocity:
    return BaseVelocity(STAMP, vx, vy, wz)


# --- gripper -------------------------------------------------------------------------------


def test_a_gripper_command_within_the_limits_passes_as_is() -> None:
    command = grip(0.4, 20.0)
    assert GripperLimit(50.0).apply(command) is command


@pytest.mark.parametrize("command", [grip(math.nan), grip(0.5, math.inf)], ids=["nan opening", "inf force"])
def test_a_non_finite_gripper_command_is_rejected(command: GripperCommand) -> None:
    event = GripperLimit().apply(command)
    assert isinstance(event, SafetyEvent)
    assert event.code == "invalid_input"


def test_the_gripper_opening_and_force_are_clamped() -> None:
    out = GripperLimit(50.0).apply(grip(-0.3, 80.0))
    assert isinstance(out, GripperCommand)
    assert (out.opening, out.max_force, out.stamp) == (0.0, 50.0, STAMP)


def test_without_a_force_cap_only_a_negative_force_is_clamped() -> None:
    out = GripperLimit().apply(grip(0.5, -1.0))
    assert isinstance(out, GripperCommand)
    assert out.max_force == 0.0


def test_a_gripper_limit_refuses_a_zero_force_cap() -> None:
    with pytest.raises(ConfigError, match="max_force_n must be a finite value > 0"):
        GripperLimit(0.0)


# --- base ----------------------------------------------------------------------------------


def test_a_gentle_base_command_passes_as_is() -> None:
    command = vel(0.1, wz=0.2)
    assert BaseLimit().apply(command, T0) == (command, None)


def test_the_planar_speed_is_scaled_down_keeping_its_direction() -> None:
    limit = BaseLimit(1.0, 2.0, 100.0, 100.0)
    out, event = limit.apply(vel(3.0, 4.0), T0)
    assert (out.vx, out.vy) == pytest.approx((0.6, 0.8))
    assert event is not None
    assert event.code == "velocity_limit"


def test_the_yaw_rate_is_clamped() -> None:
    out, _ = BaseLimit(1.0, 2.0, 100.0, 100.0).apply(vel(0.0, wz=-5.0), T0)
    assert out.wz == -2.0


def test_the_velocity_changes_at_most_by_the_acceleration_over_the_elapsed_time() -> None:
    limit = BaseLimit(1.0, 2.0, 2.0, 4.0)
    first, _ = limit.apply(vel(0.5, wz=1.0), T0)  # from rest, credited the longest gap (0.1 s)
    second, event = limit.apply(vel(0.5, wz=1.0), T0 + 10 * MS)
    assert (first.vx, first.wz, second.vx, second.wz) == pytest.approx((0.2, 0.4, 0.22, 0.44))
    assert event is not None
    assert event.code == "acceleration_limit"


def test_a_long_pause_is_no_bigger_step() -> None:
    limit = BaseLimit(1.0, 2.0, 2.0, 4.0)
    limit.apply(vel(0.2), T0)
    out, _ = limit.apply(vel(1.0), T0 + 5_000 * MS)
    assert out.vx == pytest.approx(0.4)


def test_a_stop_passes_at_once() -> None:
    limit = BaseLimit(1.0, 2.0, 2.0, 4.0)
    for k in range(20):
        limit.apply(vel(0.8), T0 + k * 10 * MS)
    stop = vel(0.0)
    assert limit.apply(stop, T0 + 200 * MS) == (stop, None)


def test_a_non_finite_base_command_becomes_a_stop() -> None:
    limit = BaseLimit()
    limit.apply(vel(0.2), T0)
    out, event = limit.apply(vel(math.nan), T0 + 10 * MS)
    assert event is not None
    assert ((out.vx, out.vy, out.wz), event.code) == ((0.0, 0.0, 0.0), "invalid_input")


def test_a_base_limit_from_the_rigs_settings_takes_every_value() -> None:
    limit = BaseLimit.from_config(BaseSafetyConfig(max_linear_m_s=0.5, max_angular_accel_rad_s2=3.0))
    got = (
        limit.max_linear_m_s,
        limit.max_angular_rad_s,
        limit.max_linear_accel_m_s2,
        limit.max_angular_accel_rad_s2,
    )
    assert got == (0.5, 2.0, 2.0, 3.0)


def test_a_robot_without_base_settings_gets_the_defaults() -> None:
    assert RobotSafetyConfig().base == BaseSafetyConfig()


# --- through RobotSafety -------------------------------------------------------------------


class _Arm(MujocoArm):
    def __init__(self) -> None:
        super().__init__(name="arm0")
        self.base_in: list[BaseVelocity] = []
        self.gripper_in: list[GripperCommand] = []

    def send_gripper(self, command: GripperCommand) -> GripperCommand:
        self.gripper_in.append(command)
        return super().send_gripper(command)

    def send_base(self, command: BaseVelocity) -> BaseVelocity:
        self.base_in.append(command)
        return command


@pytest.fixture
def arm() -> Iterator[_Arm]:
    robot = _Arm()
    robot.connect()
    yield robot
    robot.close()


@pytest.mark.sim
def test_a_halted_robot_sends_no_gripper_command(arm: _Arm) -> None:
    robot = SafetySupervisor("pause_affected").add("arm0", arm, SafetyChain.default(arm.limits))
    robot.halt("another robot faulted")  # e.g. from another thread, between step and send
    assert (robot.send_gripper(grip(0.0)), arm.gripper_in) == (None, [])


@pytest.mark.sim
def test_a_halted_robot_sends_its_base_a_stop(arm: _Arm) -> None:
    robot = SafetySupervisor("pause_affected").add("arm0", arm, SafetyChain.default(arm.limits))
    robot.halt("operator e-stop")
    sent = robot.send_base(vel(0.3), now_ns=T0)
    assert sent is not None
    assert (sent.vx, sent.vy, sent.wz) == (0.0, 0.0, 0.0)


@pytest.mark.sim
def test_rejected_part_commands_count_in_the_robots_safety_counts(arm: _Arm) -> None:
    chain = SafetyChain.default(arm.limits)
    robot = SafetySupervisor("pause_affected").add("arm0", arm, chain)
    robot.send_gripper(grip(math.nan))
    robot.send_base(vel(math.inf), now_ns=T0)
    assert chain.counts["invalid_input"] == 2
