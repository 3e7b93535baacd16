"""Each safety chain stage alone (measured checks, gates, input checks, the goal hold), then composed."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest

from telerig.errors import ConfigError
from telerig.ir.types import JointCommand, JointState, Stamp
from telerig.robots.base import JointLimits
from telerig.safety import Deadman, SafetyChain, SafetyEvent, Tick, VelocityLimit
from telerig.safety.stages import (
    DeadmanGate,
    DriverStateCheck,
    FiniteCheck,
    GoalHold,
    JointNamesCheck,
    MeasuredLimitCheck,
)

NAMES = ("j1", "j2", "j3")
MS = 1_000_000  # ns
T0 = 1_000_000_000_000  # common-clock origin [ns]
LIMITS = JointLimits(NAMES, [-2.0] * 3, [2.0] * 3, [1.0] * 3, [20.0] * 3)


def cmd(
    q: list[float], t_ns: int, names: tuple[str, ...] = NAMES, velocities: list[float] | None = None
) -> JointCommand:
    v = np.zeros(0) if velocities is None else np.array(velocities)
    return JointCommand(Stamp("retarget", 0, t_ns, t_ns), names, q, v)


def state(q: list[float], names: tuple[str, ...] = NAMES) -> JointState:
    return JointState(Stamp("robot", 0, T0, T0), names, q, np.zeros(len(names)))


# --- measured checks -----------------------------------------------------------------------


def test_driver_state_check_passes_a_sound_state() -> None:
    assert DriverStateCheck().check(state([0.0, 1.0, -1.0]), LIMITS) is None


@pytest.mark.parametrize(
    ("measured", "words"),
    [
        (None, "no measured state"),
        (state([0.0, 0.0], ("j1", "j2")), "do not match"),
        (state([0.0, math.nan, 0.0]), "not finite"),
        (state([0.0, math.inf, 0.0]), "not finite"),
    ],
)
def test_driver_state_check_faults_a_missing_or_malformed_state(
    measured: JointState | None, words: str
) -> None:
    event = DriverStateCheck().check(measured, LIMITS)
    assert event is not None
    assert (event.code, words in event.reason) == ("driver_fault", True)


def test_measured_limit_check_tolerates_the_excess_it_is_given() -> None:
    assert MeasuredLimitCheck(0.05).check(state([2.04, -2.04, 0.0]), LIMITS) is None


def test_measured_limit_check_names_the_worst_joint_beyond_the_tolerance() -> None:
    event = MeasuredLimitCheck(0.05).check(state([2.06, -2.2, 0.0]), LIMITS)
    assert event is not None
    assert (event.code, "'j2'" in event.reason) == ("joint_limit_fault", True)


def test_measured_limit_check_follows_new_limits() -> None:
    check = MeasuredLimitCheck(0.0)
    assert check.check(state([1.5, 0.0, 0.0]), LIMITS) is None
    tight = JointLimits(NAMES, [-1.0] * 3, [1.0] * 3, [1.0] * 3, [20.0] * 3)
    assert check.check(state([1.5, 0.0, 0.0]), tight) is not None


def test_measured_limit_check_refuses_a_negative_tolerance() -> None:
    with pytest.raises(ConfigError, match="measured_tolerance must be a finite value >= 0 rad"):
        MeasuredLimitCheck(-0.1)


# --- gates ---------------------------------------------------------------------------------


def test_deadman_gate_passes_while_held() -> None:
    deadman = Deadman(signal_timeout_s=0.1)
    deadman.update(True, T0)
    assert DeadmanGate(deadman).admit(T0 + 10 * MS, Tick(LIMITS)) is True


def test_deadman_gate_reports_a_release_once_then_drops_silently() -> None:
    deadman = Deadman(signal_timeout_s=0.1)
    gate, tick = DeadmanGate(deadman), Tick(LIMITS)
    deadman.update(False, T0)
    verdicts = [gate.admit(T0 + k * MS, tick) for k in range(3)]
    assert isinstance(verdicts[0], SafetyEvent)
    assert (verdicts[0].code, verdicts[1:]) == ("deadman", [False, False])


def test_deadman_gate_stops_the_held_goal_moving_on_release() -> None:
    deadman = Deadman(signal_timeout_s=0.1)
    gate, tick = DeadmanGate(deadman), Tick(LIMITS)
    tick.goal_velocity[:] = [0.5, -0.5, 0.1]
    gate.admit(T0, tick)
    assert not tick.goal_velocity.any()


def test_deadman_gate_reports_each_new_release() -> None:
    deadman = Deadman(signal_timeout_s=0.1)
    gate, tick = DeadmanGate(deadman), Tick(LIMITS)
    gate.admit(T0, tick)
    deadman.update(True, T0 + MS)
    assert gate.admit(T0 + MS, tick) is True
    assert isinstance(gate.admit(T0 + 200 * MS, tick), SafetyEvent)  # silent device: released


# --- input checks --------------------------------------------------------------------------


def test_joint_names_check_says_what_is_missing_and_unknown() -> None:
    event = JointNamesCheck().check(cmd([0.0] * 3, T0, ("j1", "jx", "j3")), LIMITS)
    assert event is not None
    assert (event.code, "missing ['j2'], unknown ['jx']" in event.reason) == ("invalid_input", True)


def test_joint_names_check_refuses_the_wrong_order() -> None:
    event = JointNamesCheck().check(cmd([0.0] * 3, T0, ("j2", "j1", "j3")), LIMITS)
    assert event is not None
    assert "wrong order" in event.reason


def test_joint_names_check_passes_the_robots_joints() -> None:
    assert JointNamesCheck().check(cmd([0.0] * 3, T0), LIMITS) is None


@pytest.mark.parametrize(
    "command",
    [cmd([0.0, math.nan, 0.0], T0), cmd([0.0, 0.0, 0.0], T0, velocities=[0.0, -math.inf, 0.0])],
    ids=["nan position", "infinite velocity"],
)
def test_finite_check_rejects_nan_and_inf(command: JointCommand) -> None:
    event = FiniteCheck().check(command, LIMITS)
    assert event is not None
    assert event.code == "invalid_input"


def test_finite_check_passes_finite_values() -> None:
    assert FiniteCheck().check(cmd([0.1, 0.2, 0.3], T0, velocities=[1.0, 1.0, 1.0]), LIMITS) is None


# --- the goal hold -------------------------------------------------------------------------


@dataclass
class Refuse:
    """A policy check that refuses every request with ``code`` and records what it saw."""

    code: str
    seen: int = 0

    def check(self, command: JointCommand, limits: JointLimits) -> SafetyEvent | None:
        self.seen += 1
        return SafetyEvent(self.code, "refused", "none")  # type: ignore[arg-type]


def test_goal_hold_keeps_an_accepted_request() -> None:
    goal = GoalHold(LIMITS)
    assert goal.offer(cmd([0.1, 0.2, 0.3], T0), Tick(LIMITS)) is None
    assert (goal.valid, goal.capture_ns, goal.positions.tolist()) == (True, T0, [0.1, 0.2, 0.3])


def test_goal_hold_estimates_the_goal_velocity_within_the_speed_limits() -> None:
    goal, tick = GoalHold(LIMITS), Tick(LIMITS)
    goal.offer(cmd([0.0, 0.0, 0.0], T0), tick)
    goal.offer(cmd([0.005, -0.05, 0.0], T0 + 10 * MS), tick)
    assert tick.goal_velocity.tolist() == pytest.approx([0.5, -1.0, 0.0])


def test_goal_hold_estimates_no_velocity_across_a_gap() -> None:
    goal, tick = GoalHold(LIMITS, max_gap_s=0.1), Tick(LIMITS)
    goal.offer(cmd([0.0, 0.0, 0.0], T0), tick)
    goal.offer(cmd([0.05, 0.0, 0.0], T0 + 150 * MS), tick)
    assert not tick.goal_velocity.any()


def test_goal_hold_rejects_a_request_older_than_the_goal() -> None:
    goal = GoalHold(LIMITS)
    goal.offer(cmd([0.0, 0.0, 0.0], T0), Tick(LIMITS))
    event = goal.offer(cmd([0.5, 0.0, 0.0], T0 - MS), Tick(LIMITS))
    assert event is not None
    assert ("out of order" in event.reason, goal.positions.tolist()) == (True, [0.0, 0.0, 0.0])


def test_goal_hold_stops_the_goal_moving_on_a_rejection() -> None:
    goal, tick = GoalHold(LIMITS), Tick(LIMITS)
    tick.goal_velocity[:] = 0.3
    goal.offer(cmd([math.nan, 0.0, 0.0], T0), tick)
    assert not tick.goal_velocity.any()


def test_goal_hold_runs_structural_checks_before_policy_checks() -> None:
    policy = Refuse("out_of_range")
    event = GoalHold(LIMITS, [policy]).offer(cmd([math.nan, 0.0, 0.0], T0), Tick(LIMITS))
    assert event is not None
    assert (event.code, policy.seen) == ("invalid_input", 0)


def test_goal_hold_counts_a_workspace_refusal_as_live_input() -> None:
    goal = GoalHold(LIMITS, [Refuse("workspace")])
    goal.valid, goal.capture_ns = True, T0
    goal.offer(cmd([0.1, 0.0, 0.0], T0 + 30 * MS), Tick(LIMITS))
    assert (goal.capture_ns, goal.positions.tolist()) == (T0 + 30 * MS, [0.0, 0.0, 0.0])


def test_goal_hold_does_not_count_a_range_rejection_as_live_input() -> None:
    goal = GoalHold(LIMITS, [Refuse("out_of_range")])
    goal.valid, goal.capture_ns = True, T0
    goal.offer(cmd([0.1, 0.0, 0.0], T0 + 30 * MS), Tick(LIMITS))
    assert goal.capture_ns == T0


# --- composed into a chain -----------------------------------------------------------------


class Closed:
    """A gate that drops every request without a word."""

    def admit(self, now_ns: int, tick: Tick) -> bool | SafetyEvent:
        return False


class Overheated:
    """A measured check that faults once the first joint passes 1 rad (a stand-in for a sensor)."""

    def check(self, measured: JointState | None, limits: JointLimits) -> SafetyEvent | None:
        if measured is not None and measured.positions[0] > 1.0:
            return SafetyEvent("driver_fault", "motor 1 overheated", "let it cool")
        return None


def test_a_chain_with_a_closed_gate_never_starts() -> None:
    chain = SafetyChain(LIMITS, gates=[Closed()])
    outs = [
        chain.step(cmd([0.1, 0, 0], T0 + k * 10 * MS), now_ns=T0 + k * 10 * MS, measured=state([0, 0, 0]))
        for k in range(5)
    ]
    assert {o.status for o in outs} == {"stopped"}


def test_a_chain_latches_the_fault_of_an_added_measured_check() -> None:
    chain = SafetyChain(LIMITS, measured=[Overheated()])
    assert chain.step(None, now_ns=T0, measured=state([0.5, 0, 0])).status == "stopped"
    out = chain.step(None, now_ns=T0 + 10 * MS, measured=state([1.5, 0, 0]))
    assert (out.status, out.events[0].reason, chain.counts["driver_fault"]) == (
        "estopped",
        "motor 1 overheated",
        1,
    )


@dataclass(frozen=True)
class Settings:
    start_velocity_fraction: float = 0.2
    start_ramp_s: float = 2.0
    hold_timeout_ms: float = 50.0
    watchdog_timeout_ms: float = 400.0
    velocity_scale: float = 0.5
    measured_tolerance_rad: float = 0.1


def test_a_chain_from_the_rigs_settings_takes_every_value() -> None:
    chain = SafetyChain.from_config(LIMITS, Settings(), rate_hz=200.0, source_id="arm0/safety")
    ramp = chain.ramp
    assert ramp is not None
    got = (
        ramp.initial_fraction,
        ramp.duration_s,
        chain.watchdog.hold_timeout_ns,
        chain.watchdog.stop_timeout_ns,
        chain.period_s,
        chain.source_id,
        chain.measured_tolerance,
    )
    assert got == (0.2, 2.0, 50 * MS, 400 * MS, 0.005, "arm0/safety", 0.1)


def test_a_chain_from_the_rigs_settings_scales_the_speed_limit() -> None:
    chain = SafetyChain.from_config(LIMITS, Settings(), rate_hz=100.0, source_id="arm0/safety")
    speeds = [f.fraction for f in chain.filters if isinstance(f, VelocityLimit)]
    assert speeds == [0.5]


def test_a_chain_from_the_rigs_settings_refuses_a_zero_rate() -> None:
    with pytest.raises(ConfigError, match="control rate must be > 0 Hz"):
        SafetyChain.from_config(LIMITS, Settings(), rate_hz=0.0, source_id="arm0/safety")


def test_notes_from_other_parts_count_with_the_chains_own() -> None:
    chain = SafetyChain.default(LIMITS)
    chain.note(SafetyEvent("invalid_input", "gripper opening nan", "check the gripper input"))
    assert chain.counts["invalid_input"] == 1
