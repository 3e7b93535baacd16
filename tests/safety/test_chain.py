"""Tests for the safety chain and its filters, driven with injected times (no sleeps)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from telerig.errors import ConfigError
from telerig.ir.types import JointCommand, JointState, Stamp
from telerig.robots.base import JointLimits
from telerig.safety import (
    AccelerationLimit,
    InputWatchdog,
    PositionClamp,
    PositionRangeCheck,
    SafetyChain,
    SafetyOutput,
    StartupRamp,
    VelocityLimit,
)

NAMES = ("j1", "j2", "j3")
VMAX = 1.0  # rad/s
AMAX = 20.0  # rad/s^2
MS = 1_000_000  # ns
T0 = 1_000_000_000_000  # arbitrary common-clock origin [ns]
LIMITS = JointLimits(
    names=NAMES,
    lower=[-2.0, -2.0, -2.0],
    upper=[2.0, 2.0, 2.0],
    velocity=[VMAX] * 3,
    acceleration=[AMAX] * 3,
)


def cmd(q: list[float] | np.ndarray, t_ns: int, seq: int = 0, names: tuple[str, ...] = NAMES) -> JointCommand:
    return JointCommand(Stamp("retarget", seq, t_ns, t_ns), names, q)


def state(q: list[float] | np.ndarray, t_ns: int = T0) -> JointState:
    return JointState(Stamp("robot", 0, t_ns, t_ns), NAMES, q, np.zeros(len(NAMES)))


def velocity_only() -> SafetyChain:
    """Clamp + velocity limit, no ramp, default watchdog: makes rate assertions exact."""
    return SafetyChain(LIMITS, checks=[PositionRangeCheck(0.05)], filters=[PositionClamp(), VelocityLimit()])


class Loop:
    """Steps a chain at 100 Hz with the measured state following the output exactly."""

    def __init__(self, chain: SafetyChain, q0: list[float] | None = None) -> None:
        self.chain = chain
        self.t = T0
        self.seq = 0
        self.q = np.array(q0 if q0 is not None else [0.0, 0.0, 0.0])

    def step(
        self, q: list[float] | np.ndarray | None, dt_ns: int = 10 * MS, names: tuple[str, ...] = NAMES
    ) -> SafetyOutput:
        self.t += dt_ns
        request = None
        if q is not None:
            self.seq += 1
            request = cmd(q, self.t, self.seq, names)
        out = self.chain.step(request, now_ns=self.t, measured=state(self.q, self.t))
        if out.command is not None:
            self.q = out.command.positions.copy()
        return out

    def track(self, q: list[float], ticks: int) -> list[SafetyOutput]:
        return [self.step(q) for _ in range(ticks)]


def test_first_tick_commands_the_measured_state() -> None:
    chain = SafetyChain.default(LIMITS)
    out = chain.step(None, now_ns=T0, measured=state([0.3, -0.2, 0.1]))
    assert out.status == "stopped"
    assert out.command is not None
    np.testing.assert_array_equal(out.command.positions, [0.3, -0.2, 0.1])


def test_first_valid_input_starts_from_the_measured_state() -> None:
    loop = Loop(velocity_only(), q0=[0.5, 0.5, 0.5])
    out = loop.step([1.5, 1.5, 1.5])
    assert out.command is not None
    np.testing.assert_allclose(out.command.positions, [0.5 + VMAX * 0.01] * 3)


def test_nan_burst_never_reaches_output() -> None:
    loop = Loop(SafetyChain.default(LIMITS))
    loop.track([0.1, 0.1, 0.1], 20)
    outs = [loop.step([math.nan, 0.0, math.inf]) for _ in range(8)]
    assert all(o.command is not None and np.isfinite(o.command.positions).all() for o in outs)


def test_nan_input_is_rejected_and_counted_as_invalid() -> None:
    loop = Loop(SafetyChain.default(LIMITS))
    loop.track([0.1, 0.1, 0.1], 5)
    out = loop.step([math.nan, 0.0, 0.0])
    assert out.events[0].code == "invalid_input"
    assert out.status == "holding"
    assert loop.chain.counts["invalid_input"] == 1


def test_one_radian_jump_is_rate_limited_every_tick() -> None:
    loop = Loop(velocity_only())
    loop.track([0.0, 0.0, 0.0], 2)
    prev = loop.q.copy()
    for dt_ns in [10 * MS, 5 * MS, 10 * MS, 13 * MS] * 30:
        out = loop.step([1.0, -1.0, 0.0], dt_ns=dt_ns)
        assert out.command is not None
        step = np.abs(out.command.positions - prev)
        assert (step <= VMAX * dt_ns * 1e-9 + 1e-12).all()
        prev = out.command.positions
    np.testing.assert_allclose(prev, [1.0, -1.0, 0.0])


def test_late_tick_step_is_bounded_by_two_periods() -> None:
    loop = Loop(velocity_only())
    loop.track([0.0, 0.0, 0.0], 2)
    before = loop.q.copy()
    out = loop.step([1.0, 1.0, 1.0], dt_ns=80 * MS)
    assert out.command is not None
    np.testing.assert_allclose(out.command.positions - before, [VMAX * 0.02] * 3)


def test_rate_limited_tick_reports_limited_status() -> None:
    loop = Loop(velocity_only())
    loop.track([0.0, 0.0, 0.0], 2)
    out = loop.step([1.0, 0.0, 0.0])
    assert out.status == "limited"
    assert [e.code for e in out.events] == ["velocity_limit"]


def test_ramp_limits_early_steps_to_initial_fraction() -> None:
    chain = SafetyChain(LIMITS, filters=[VelocityLimit()], ramp=StartupRamp(0.1, 3.0))
    loop = Loop(chain)
    outs = loop.track([2.0, 2.0, 2.0], 10)
    steps = np.diff([o.command.positions[0] for o in outs if o.command is not None])
    assert (steps <= 0.1 * VMAX * 0.01 * 1.3 + 1e-12).all()


def test_ramp_relaxes_linearly_to_full_speed() -> None:
    chain = SafetyChain(LIMITS, filters=[VelocityLimit()], ramp=StartupRamp(0.1, 3.0))
    loop = Loop(chain, q0=[-2.0, -2.0, -2.0])
    loop.step([2.0, 2.0, 2.0])
    scales = []
    for _ in range(400):
        loop.step([2.0, 2.0, 2.0])
        scales.append(chain.speed_scale)
    assert scales[149] == pytest.approx(0.1 + 0.9 * 1.51 / 3.0, abs=0.01)
    assert scales[-1] == 1.0


def test_ramp_restarts_after_watchdog_stop() -> None:
    chain = SafetyChain.default(LIMITS)
    loop = Loop(chain)
    loop.track([0.0, 0.0, 0.0], 400)
    assert chain.speed_scale == 1.0
    loop.step(None, dt_ns=300 * MS)
    assert chain.speed_scale == pytest.approx(0.1)


def test_a_tick_gap_longer_than_the_hold_restarts_from_the_measured_state_at_the_ramp_start() -> None:
    # The loop itself stalled 150 ms (a starved thread) while the operator moved on: the robot held
    # its last command all that while, so the chain resumes as after a watchdog stop, slowly.
    chain = SafetyChain.default(LIMITS)
    loop = Loop(chain)
    loop.track([0.0, 0.0, 0.0], 400)
    assert chain.speed_scale == 1.0
    out = loop.step([1.0, 0.0, 0.0], dt_ns=150 * MS)
    assert out.events[0].code == "input_stale"  # then the limits slowing the step to the goal
    assert "no control tick for 150 ms" in out.events[0].reason
    assert chain.speed_scale == pytest.approx(0.1, abs=0.01)
    assert out.command is not None
    step = out.command.positions[0]
    assert 0.0 < step <= 0.1 * VMAX * 0.01 + 1e-12


def test_a_tick_gap_within_the_hold_keeps_full_speed() -> None:
    chain = SafetyChain.default(LIMITS)
    loop = Loop(chain)
    loop.track([0.0, 0.0, 0.0], 400)
    out = loop.step([1.0, 0.0, 0.0], dt_ns=90 * MS)
    assert "input_stale" not in [e.code for e in out.events]
    assert chain.speed_scale == 1.0


def test_hold_on_50ms_loss_keeps_last_command() -> None:
    loop = Loop(SafetyChain.default(LIMITS))
    loop.track([0.0, 0.0, 0.0], 5)
    last = loop.q.copy()
    outs = [loop.step(None) for _ in range(5)]
    assert [o.status for o in outs] == ["holding"] * 5
    assert all(o.events == () for o in outs)
    for o in outs:
        assert o.command is not None
        np.testing.assert_array_equal(o.command.positions, last)


def test_hold_continues_towards_last_valid_command() -> None:
    loop = Loop(velocity_only())
    loop.track([0.0, 0.0, 0.0], 2)
    loop.step([1.0, 1.0, 1.0])
    before = loop.q.copy()
    out = loop.step(None)
    assert out.command is not None
    np.testing.assert_allclose(out.command.positions - before, [VMAX * 0.01] * 3)


def test_holding_output_gets_the_chains_own_stamp() -> None:
    chain = SafetyChain.default(LIMITS, source_id="arm/safety")
    loop = Loop(chain)
    loop.track([0.0, 0.0, 0.0], 3)
    out = loop.step(None)
    assert out.command is not None
    assert out.command.stamp.source_id == "arm/safety"
    assert out.command.stamp.capture_ns == loop.t


def test_tracking_output_keeps_the_request_stamp() -> None:
    chain = SafetyChain.default(LIMITS)
    chain.step(None, now_ns=T0, measured=state([0, 0, 0]))
    request = JointCommand(Stamp("vr0/right", 42, 7, T0 + 5 * MS, T0 + 8 * MS), NAMES, [0.0, 0.0, 0.0])
    out = chain.step(request, now_ns=T0 + 10 * MS, measured=state([0, 0, 0]))
    assert out.command is not None
    assert out.command.stamp == request.stamp


def test_stale_input_warns_once_while_holding() -> None:
    loop = Loop(SafetyChain.default(LIMITS))
    loop.track([0.0, 0.0, 0.0], 5)
    outs = [loop.step(None) for _ in range(20)]  # 10 .. 200 ms without input
    assert [o.status for o in outs] == ["holding"] * 20
    assert sum(e.code == "input_stale" for o in outs for e in o.events) == 1


def test_watchdog_stops_after_250ms_at_measured_position() -> None:
    chain = SafetyChain.default(LIMITS)
    loop = Loop(chain)
    loop.track([0.0, 0.0, 0.0], 5)
    last_input = loop.t
    chain.step(None, now_ns=last_input + 240 * MS, measured=state([0.0, 0.0, 0.0]))
    out = chain.step(None, now_ns=last_input + 251 * MS, measured=state([0.05, -0.03, 0.02]))
    assert out.status == "stopped"
    assert [e.code for e in out.events] == ["watchdog_stop"]
    assert out.command is not None
    np.testing.assert_array_equal(out.command.positions, [0.05, -0.03, 0.02])


def test_watchdog_does_not_stop_before_250ms() -> None:
    chain = SafetyChain.default(LIMITS)
    loop = Loop(chain)
    loop.track([0.0, 0.0, 0.0], 5)
    out = chain.step(None, now_ns=loop.t + 240 * MS, measured=state(loop.q))
    assert out.status == "holding"


def test_old_capture_time_trips_watchdog_even_when_delivered_every_tick() -> None:
    loop = Loop(SafetyChain.default(LIMITS))
    loop.track([0.0, 0.0, 0.0], 5)
    captured = loop.t
    outs = []
    for k in range(1, 31):
        out = loop.chain.step(
            cmd([0.0, 0.0, 0.0], captured), now_ns=captured + k * 10 * MS, measured=state(loop.q)
        )
        outs.append(out.status)
    assert outs[-1] == "stopped"


def test_stopped_chain_ignores_stale_valid_input() -> None:
    chain = SafetyChain.default(LIMITS)
    loop = Loop(chain)
    loop.track([0.0, 0.0, 0.0], 5)
    loop.step(None, dt_ns=300 * MS)
    stale = cmd([0.5, 0.5, 0.5], loop.t + 10 * MS - 150 * MS)
    out = chain.step(stale, now_ns=loop.t + 10 * MS, measured=state(loop.q))
    assert out.status == "stopped"


def test_resume_after_watchdog_starts_where_the_arm_is() -> None:
    chain = SafetyChain(LIMITS, filters=[VelocityLimit()], ramp=StartupRamp(0.1, 3.0))
    loop = Loop(chain)
    loop.track([0.0, 0.0, 0.0], 5)
    loop.step(None, dt_ns=300 * MS)
    loop.q = np.array([0.4, -0.4, 0.2])  # the arm drifted while stopped
    out = loop.step([1.0, -1.0, 1.0])
    assert out.status == "limited"
    assert out.command is not None
    np.testing.assert_allclose(out.command.positions, [0.4 + 0.001, -0.4 - 0.001, 0.2 + 0.001])


def test_hand_over_keeps_tracking_from_the_last_command_and_restarts_the_ramp() -> None:
    chain = SafetyChain(LIMITS, filters=[VelocityLimit()], ramp=StartupRamp(0.1, 3.0))
    loop = Loop(chain)
    loop.track([0.5, 0.5, 0.5], 400)
    commanded = loop.q.copy()
    assert chain.speed_scale == 1.0
    chain.hand_over()
    sagged = commanded - 0.06  # a position-controlled arm under gravity sits below its command
    loop.t += 10 * MS
    loop.seq += 1
    out = chain.step(cmd([1.0, 1.0, 1.0], loop.t, loop.seq), now_ns=loop.t, measured=state(sagged, loop.t))
    assert out.status == "limited"
    assert out.command is not None
    # From the last command at 10 % speed: never down to the sagged measured pose.
    np.testing.assert_allclose(out.command.positions, commanded + 0.1 * VMAX * 0.01)
    assert chain.speed_scale == pytest.approx(0.1, abs=0.01)


def test_hand_over_of_a_stopped_chain_restarts_from_the_measured_state() -> None:
    chain = SafetyChain(LIMITS, filters=[VelocityLimit()], ramp=StartupRamp(0.1, 3.0))
    loop = Loop(chain)
    loop.track([0.0, 0.0, 0.0], 5)
    loop.step(None, dt_ns=300 * MS)  # the watchdog stopped it
    chain.hand_over()
    loop.q = np.array([0.4, -0.4, 0.2])
    out = loop.step([1.0, -1.0, 1.0])
    assert out.command is not None
    np.testing.assert_allclose(out.command.positions, [0.4 + 0.001, -0.4 - 0.001, 0.2 + 0.001])


def test_estop_latches_with_no_command() -> None:
    chain = SafetyChain.default(LIMITS)
    loop = Loop(chain)
    loop.track([0.0, 0.0, 0.0], 5)
    chain.estop("operator pressed e-stop")
    outs = loop.track([0.1, 0.1, 0.1], 10)
    assert all(o.status == "estopped" and o.command is None for o in outs)
    assert [e.code for o in outs for e in o.events] == ["estop"]
    assert outs[0].events[0].reason == "operator pressed e-stop"


def test_reset_releases_estop_through_stop_and_ramp() -> None:
    chain = SafetyChain.default(LIMITS)
    loop = Loop(chain)
    loop.track([0.0, 0.0, 0.0], 400)
    chain.estop("test")
    loop.step([0.0, 0.0, 0.0])
    chain.reset()
    first = loop.step(None)
    second = loop.step([0.5, 0.5, 0.5])
    assert (first.status, second.status, chain.estopped) == ("stopped", "limited", False)
    assert chain.speed_scale < 0.11


def test_reset_frees_the_order_check_from_a_request_stamped_in_the_future() -> None:
    # Issue 11 finding 2: one sample stamped an hour ahead made every real one "out of order" for
    # the rest of the episode, and reset did not free it.
    chain = SafetyChain.default(LIMITS)
    loop = Loop(chain)
    loop.track([0.0, 0.0, 0.0], 400)
    chain.step(cmd([0.0, 0.0, 0.0], loop.t + 3600 * 10**9, 10**6), now_ns=loop.t, measured=state(loop.q))
    assert "invalid_input" in [e.code for e in loop.step([0.1, 0.0, 0.0]).events]  # held by the future
    chain.estop("operator")
    loop.step(None)
    chain.reset()
    loop.step(None)
    outs = loop.track([0.1, 0.0, 0.0], 50)
    assert "invalid_input" not in [e.code for o in outs for e in o.events]
    assert outs[-1].status in ("ok", "limited")


def test_measured_nan_latches_estop() -> None:
    chain = SafetyChain.default(LIMITS)
    chain.step(None, now_ns=T0, measured=state([0.0, 0.0, 0.0]))
    out = chain.step(None, now_ns=T0 + 10 * MS, measured=state([0.0, math.nan, 0.0]))
    assert (out.status, out.command, chain.estopped) == ("estopped", None, True)


def test_target_slightly_beyond_limit_is_clamped() -> None:
    loop = Loop(velocity_only(), q0=[1.99, 0.0, 0.0])
    outs = loop.track([2.03, 0.0, 0.0], 5)
    assert outs[-1].command is not None
    assert outs[-1].command.positions[0] == 2.0
    assert "position_limit" in [e.code for e in outs[-1].events]


def test_target_far_beyond_limit_is_rejected() -> None:
    loop = Loop(velocity_only())
    loop.track([0.0, 0.0, 0.0], 3)
    out = loop.step([0.0, 2.5, 0.0])
    assert [e.code for e in out.events] == ["out_of_range"]
    assert "'j2'" in out.events[0].reason
    assert out.command is not None
    np.testing.assert_array_equal(out.command.positions, [0.0, 0.0, 0.0])


def test_clamp_never_pulls_an_out_of_range_arm_back_in_a_jump() -> None:
    loop = Loop(velocity_only(), q0=[2.04, 0.0, 0.0])
    out = loop.step([2.04, 0.0, 0.0])
    assert out.command is not None
    assert out.command.positions[0] == pytest.approx(2.04)


def test_wrong_joint_names_are_rejected() -> None:
    loop = Loop(SafetyChain.default(LIMITS))
    loop.track([0.0, 0.0, 0.0], 3)
    out = loop.step([0.0, 0.0, 0.0], names=("j1", "j3", "jx"))
    assert [e.code for e in out.events] == ["invalid_input"]
    assert "missing ['j2'], unknown ['jx']" in out.events[0].reason


def test_wrong_joint_count_is_rejected() -> None:
    loop = Loop(SafetyChain.default(LIMITS))
    loop.track([0.0, 0.0, 0.0], 3)
    out = loop.step([0.0, 0.0], names=("j1", "j2"))
    assert [e.code for e in out.events] == ["invalid_input"]


def test_out_of_order_input_is_rejected() -> None:
    chain = SafetyChain.default(LIMITS)
    chain.step(cmd([0, 0, 0], T0), now_ns=T0, measured=state([0, 0, 0]))
    out = chain.step(cmd([0.1, 0, 0], T0 - MS), now_ns=T0 + 10 * MS, measured=state([0, 0, 0]))
    assert [e.code for e in out.events] == ["invalid_input"]


def test_counters_count_each_event_code() -> None:
    chain = SafetyChain.default(LIMITS)
    loop = Loop(chain)
    loop.track([0.0, 0.0, 0.0], 3)
    for _ in range(3):
        loop.step([math.nan, 0.0, 0.0])
    loop.step([0.0, 3.0, 0.0])
    loop.step(None, dt_ns=300 * MS)  # no tick for 300 ms: held (input_stale), then the watchdog stop
    chain.estop("test")
    loop.step(None)
    loop.step(None)
    counts = dict(chain.counts)
    assert counts == {
        "invalid_input": 3,
        "out_of_range": 1,
        "position_limit": 0,
        "velocity_limit": 0,
        "acceleration_limit": 0,
        "workspace": 0,
        "self_collision": 0,
        "deadman": 0,
        "input_stale": 1,
        "watchdog_stop": 1,
        "joint_limit_fault": 0,
        "driver_fault": 0,
        "estop": 1,
    }


def test_acceleration_limit_bounds_velocity_change() -> None:
    chain = SafetyChain(LIMITS, filters=[AccelerationLimit(), VelocityLimit()])
    loop = Loop(chain)
    loop.track([0.0, 0.0, 0.0], 2)
    positions = [o.command.positions[0] for o in loop.track([1.0, 0.0, 0.0], 200) if o.command is not None]
    v = np.diff([0.0, *positions]) / 0.01
    assert (np.abs(np.diff([0.0, *v])) <= AMAX * 0.01 + 1e-9).all()


def test_acceleration_limit_reaches_target_without_overshoot() -> None:
    chain = SafetyChain(LIMITS, filters=[AccelerationLimit(), VelocityLimit()])
    loop = Loop(chain)
    loop.track([0.0, 0.0, 0.0], 2)
    positions = [o.command.positions[0] for o in loop.track([1.0, 0.0, 0.0], 200) if o.command is not None]
    assert max(positions) <= 1.0 + 1e-9
    assert positions[-1] == pytest.approx(1.0)


@pytest.mark.parametrize(
    "build",
    [
        lambda: StartupRamp(initial_fraction=0.0),
        lambda: InputWatchdog(hold_timeout_s=0.3, stop_timeout_s=0.25),
        lambda: VelocityLimit(fraction=1.5),
        lambda: PositionRangeCheck(tolerance=-1.0),
    ],
)
def test_bad_filter_parameters_raise_config_error(build: object) -> None:
    with pytest.raises(ConfigError):
        build()  # type: ignore[operator]


def test_acceleration_limit_tracks_a_smooth_moving_target_without_lag() -> None:
    chain = SafetyChain(LIMITS, filters=[AccelerationLimit(), VelocityLimit()])
    loop = Loop(chain)
    errors = []
    for k in range(300):
        goal = 0.3 * math.sin(2.0 * math.pi * 0.5 * k * 0.01)  # peak 0.94 rad/s, 3 rad/s^2
        out = loop.step([goal, 0.0, 0.0])
        assert out.command is not None
        if k > 50:
            errors.append(abs(out.command.positions[0] - goal))
    assert max(errors) < 1e-9
