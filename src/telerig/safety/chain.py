"""The safety chain: the one gate between retargeting and every robot driver, stepped once per tick.

A chain is composed of small stages (:mod:`telerig.safety.stages`, :mod:`telerig.safety.filters`),
each with one method, run in this order every tick:

1. measured checks (:class:`~telerig.safety.stages.MeasuredCheck`): a fault latches the e-stop;
2. gates (:class:`~telerig.safety.stages.Gate`, e.g. the deadman): may drop the request;
3. the goal hold (:class:`~telerig.safety.stages.GoalHold`): input checks, the last valid request;
4. the watchdog (:class:`~telerig.safety.filters.InputWatchdog`): fresh, holding or stopped;
5. the start-up ramp (:class:`~telerig.safety.filters.StartupRamp`): the speed scale;
6. the limits (:class:`~telerig.safety.filters.Limit`), in order, on the goal.

The chain itself keeps only the state machine between them (e-stop latch, stopped / running /
holding) and the per-tick working state (:class:`~telerig.safety.filters.Tick`).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType
from typing import Literal, Protocol

import numpy as np

from telerig.errors import ConfigError
from telerig.ir.types import JointCommand, JointState, Stamp
from telerig.robots.base import JointLimits
from telerig.safety.deadman import Deadman
from telerig.safety.filters import (
    SAFETY_CODES,
    AccelerationLimit,
    InputCheck,
    InputWatchdog,
    Limit,
    PositionClamp,
    PositionRangeCheck,
    SafetyCode,
    SafetyEvent,
    StartupRamp,
    Tick,
    VelocityLimit,
)
from telerig.safety.guard import ConfigurationGuard
from telerig.safety.stages import (
    DeadmanGate,
    DriverStateCheck,
    Gate,
    GoalHold,
    MeasuredCheck,
    MeasuredLimitCheck,
)

__all__ = ["FAULT_CODES", "ChainSettings", "SafetyChain", "SafetyOutput", "SafetyStatus"]

#: What the chain did this tick, most severe first: ``estopped`` (latched, no command: call
#: ``driver.estop()``), ``stopped`` (input lost or never started: hold the measured position),
#: ``holding`` (no fresh input: keep going to the last valid command), ``limited`` (tracking, but a
#: limit changed the command), ``ok`` (tracking the request unchanged).
SafetyStatus = Literal["ok", "limited", "holding", "stopped", "estopped"]

_NO_EVENTS: tuple[SafetyEvent, ...] = ()
#: Codes that mean the robot itself is at fault (the fleet policy reacts to them).
FAULT_CODES: frozenset[SafetyCode] = frozenset({"joint_limit_fault", "driver_fault"})


class ChainSettings(Protocol):
    """The rig's safety settings a chain is built from (``safety:`` of a rig file; units in the names)."""

    @property
    def start_velocity_fraction(self) -> float: ...
    @property
    def start_ramp_s(self) -> float: ...
    @property
    def hold_timeout_ms(self) -> float: ...
    @property
    def watchdog_timeout_ms(self) -> float: ...
    @property
    def velocity_scale(self) -> float: ...
    @property
    def measured_tolerance_rad(self) -> float: ...


@dataclass(frozen=True, slots=True)
class SafetyOutput:
    """Result of one :meth:`SafetyChain.step`.

    Attributes:
        command: What to send to the driver, or ``None`` when e-stopped (call ``driver.estop()``).
            Stamped with the request's stamp when it tracks this tick's request, else with a new
            stamp from the chain (source id ``SafetyChain.source_id``, capture time = ``now_ns``).
        status: What the chain did (see :data:`SafetyStatus`).
        events: What happened this tick, in stage order; empty on a normal tick.
    """

    command: JointCommand | None
    status: SafetyStatus
    events: tuple[SafetyEvent, ...]


class SafetyChain:
    """Validates, limits and watches joint commands; stepped once per control tick (e.g. 100 Hz).

    Per tick: judge the measured state, let the gates drop the request, reject invalid requests
    (treated like no input) and keep the last valid one as goal, shape the goal with ``filters``
    (in order) starting from the previous output, and watch the input's age. Structural checks
    (joint names and order match ``limits.names``, all values finite, capture time not older than
    the last accepted request, a sound measured state) are always on because the chain's own state
    depends on them; ``checks`` and ``measured`` add policy on top.

    States: the chain starts *stopped*, commanding the measured position. Fresh valid input starts
    tracking from where the arm is, through the start-up ramp. Input older than the hold timeout
    makes it hold (going on to the last valid command); older than the stop timeout makes it stop
    (command the measured position) until fresh valid input arrives. The chain's own ticks count
    too: a tick later than the hold timeout after the last one (the loop was starved, and the robot
    held its last command meanwhile) resumes from the measured position at the start of the ramp,
    as after a stop. :meth:`estop` latches until
    :meth:`reset`. A missing or invalid measured state (``None``, wrong names, NaN) latches an e-stop
    by itself (``driver_fault``), as does a measured position beyond the joint limits by more than
    ``measured_tolerance`` (``joint_limit_fault``). With a ``deadman``, requests pass only while it
    is enabled; released, the chain holds and then stops as on input loss.

    Not thread-safe except :meth:`estop`, which any thread may call; call everything else from the
    control loop.
    """

    def __init__(
        self,
        limits: JointLimits,
        *,
        checks: Sequence[InputCheck] = (),
        filters: Sequence[Limit] = (),
        ramp: StartupRamp | None = None,
        watchdog: InputWatchdog | None = None,
        period_s: float = 0.01,
        source_id: str = "safety",
        deadman: Deadman | None = None,
        measured_tolerance: float | None = None,
        measured: Sequence[MeasuredCheck] = (),
        gates: Sequence[Gate] = (),
    ) -> None:
        """Args:
        limits: Joint limits of the robot part, in driver order (n joints).
        checks: Extra input checks, run in order after the structural ones.
        filters: Limits applied in order to the goal each tick (see :meth:`default` for an order).
        ramp: Start-up speed ramp; ``None`` means full speed at once.
        watchdog: Input age policy; ``None`` means ``InputWatchdog()`` (100 ms hold, 250 ms stop).
        period_s: Nominal tick period [s]; the measured dt between ticks is bounded to
            ``[0, 2 * period_s]`` so a late tick never allows a bigger step.
        source_id: Source id of the stamps the chain makes when it is not tracking a request.
        deadman: Enable switch; ``None`` means always enabled. Shorthand for a
            :class:`~telerig.safety.stages.DeadmanGate` first among ``gates``.
        measured_tolerance: Excess of a *measured* position beyond the joint limits that latches a
            ``joint_limit_fault`` e-stop [rad] (>= 0); ``None`` disables the check. Shorthand for a
            :class:`~telerig.safety.stages.MeasuredLimitCheck` first among ``measured``.
        measured: Extra measured-state checks, run in order after the structural one.
        gates: Gates run in order on every request.
        """
        if not (math.isfinite(period_s) and period_s > 0.0):
            raise ConfigError(f"period_s must be > 0 s, got {period_s}")
        limit_check = () if measured_tolerance is None else (MeasuredLimitCheck(measured_tolerance),)
        self.limits = limits
        self.measured: tuple[MeasuredCheck, ...] = (DriverStateCheck(), *limit_check, *measured)
        self.gates: tuple[Gate, ...] = (*(() if deadman is None else (DeadmanGate(deadman),)), *gates)
        self.goal = GoalHold(limits, checks, max_gap_s=10.0 * period_s)
        self.checks: tuple[InputCheck, ...] = tuple(checks)
        self.filters: tuple[Limit, ...] = tuple(filters)
        self.ramp = ramp
        self.watchdog = watchdog if watchdog is not None else InputWatchdog()
        self.period_s = float(period_s)
        self.source_id = source_id
        self.deadman = deadman
        self.measured_tolerance = measured_tolerance
        self._estop_lock = threading.Lock()
        self._names = limits.names
        self._max_dt_s = 2.0 * self.period_s
        self._tick = Tick(limits)
        self._stop_position = np.zeros(len(limits.names))
        self._counts: dict[str, int] = dict.fromkeys(SAFETY_CODES, 0)
        self._counts_view: Mapping[str, int] = MappingProxyType(self._counts)
        self._events: list[SafetyEvent] = []
        self._seq = 0
        self._seeded = False
        self._last_now_ns = 0
        self._running = False
        self._stale = False
        self._stable_s = 0.0
        self._status: SafetyStatus = "stopped"
        self._estop: SafetyEvent | None = None
        self._estop_reported = True

    @classmethod
    def default(
        cls,
        limits: JointLimits,
        *,
        position_tolerance: float = 0.05,
        velocity_fraction: float = 1.0,
        acceleration_fraction: float | None = 1.0,
        ramp_initial_fraction: float = 0.1,
        ramp_duration_s: float = 3.0,
        hold_timeout_s: float = 0.1,
        stop_timeout_s: float = 0.25,
        period_s: float = 0.01,
        source_id: str = "safety",
        guard: ConfigurationGuard | None = None,
        deadman: Deadman | None = None,
        measured_tolerance: float | None = 0.05,
    ) -> SafetyChain:
        """The recommended chain: range check, clamp, acceleration and velocity limits, ramp, watchdog.

        Filter order: ``PositionClamp`` (goal into the limits), ``AccelerationLimit`` (needs the
        goal for braking), ``VelocityLimit`` (keeps the result within the ramped speed), the
        ``guard`` if any (workspace / self-collision look-ahead), then ``PositionClamp`` again (a
        braking overshoot can never leave the limits). The guard also checks every request, after
        the range check.

        Args:
            limits: Joint limits of the robot part (n joints).
            position_tolerance: Excess beyond the position limits tolerated before rejecting [rad].
            velocity_fraction: Share of the rated joint speeds to allow, in (0, 1].
            acceleration_fraction: Share of the rated accelerations, in (0, 1]; ``None`` disables it.
            ramp_initial_fraction: Start-up speed scale, in (0, 1].
            ramp_duration_s: Stable control time until full speed [s].
            hold_timeout_s: Input age beyond which the chain holds and warns [s].
            stop_timeout_s: Input age beyond which the chain stops [s].
            period_s: Nominal tick period [s].
            source_id: Source id of the chain's own stamps.
            guard: Configuration checks (see :func:`telerig.safety.arm_guard`); ``None`` for none.
            deadman: Enable switch the control node feeds; ``None`` means always enabled.
            measured_tolerance: Measured excess beyond the joint limits that latches a
                ``joint_limit_fault`` e-stop [rad]; ``None`` disables it.
        """
        filters: list[Limit] = [PositionClamp()]
        if acceleration_fraction is not None:
            filters.append(AccelerationLimit(acceleration_fraction))
        filters.append(VelocityLimit(velocity_fraction))
        checks: list[InputCheck] = [PositionRangeCheck(position_tolerance)]
        if guard is not None:
            filters.append(guard)
            checks.append(guard)
        filters.append(PositionClamp())
        return cls(
            limits,
            checks=checks,
            filters=filters,
            ramp=StartupRamp(ramp_initial_fraction, ramp_duration_s),
            watchdog=InputWatchdog(hold_timeout_s, stop_timeout_s),
            period_s=period_s,
            source_id=source_id,
            deadman=deadman,
            measured_tolerance=measured_tolerance,
        )

    @classmethod
    def from_config(
        cls,
        limits: JointLimits,
        settings: ChainSettings,
        *,
        rate_hz: float,
        source_id: str,
        guard: ConfigurationGuard | None = None,
        deadman: Deadman | None = None,
    ) -> SafetyChain:
        """The :meth:`default` chain of one robot, configured from the rig's ``safety:`` settings.

        Args:
            limits: Joint limits of the robot part (n joints).
            settings: The rig's safety settings (:class:`telerig.config.schema.SafetyConfig`).
            rate_hz: The robot's control rate [Hz] (> 0).
            source_id: Source id of the chain's own stamps, e.g. ``"arm0/safety"``.
            guard: The robot's configuration guard (workspace, self-collision), if any.
            deadman: The robot's enable switch, if any.
        """
        if not (math.isfinite(rate_hz) and rate_hz > 0.0):
            raise ConfigError(f"control rate must be > 0 Hz, got {rate_hz}")
        return cls.default(
            limits,
            velocity_fraction=settings.velocity_scale,
            ramp_initial_fraction=settings.start_velocity_fraction,
            ramp_duration_s=settings.start_ramp_s,
            hold_timeout_s=settings.hold_timeout_ms / 1e3,
            stop_timeout_s=settings.watchdog_timeout_ms / 1e3,
            period_s=1.0 / rate_hz,
            source_id=source_id,
            guard=guard,
            deadman=deadman,
            measured_tolerance=settings.measured_tolerance_rad,
        )

    @property
    def status(self) -> SafetyStatus:
        """Status of the last :meth:`step` (``"stopped"`` before the first)."""
        return self._status

    @property
    def estopped(self) -> bool:
        """Whether an e-stop is latched."""
        return self._estop is not None

    @property
    def speed_scale(self) -> float:
        """Current start-up ramp factor in (0, 1] (1 without a ramp)."""
        return 1.0 if self.ramp is None else self.ramp.scale(self._stable_s)

    @property
    def counts(self) -> Mapping[str, int]:
        """Read-only count of events per :data:`~telerig.safety.filters.SafetyCode` since creation."""
        return self._counts_view

    @property
    def estop_event(self) -> SafetyEvent | None:
        """The latched e-stop (its code says why: ``estop``, ``driver_fault``, ...), or ``None``."""
        return self._estop

    def estop(self, reason: str, *, code: SafetyCode = "estop", suggested_action: str | None = None) -> bool:
        """Latch an emergency stop: every step returns ``"estopped"`` and no command until :meth:`reset`.

        Safe to call from any thread. A second call while latched keeps the first reason.

        Args:
            reason: One line saying why.
            code: ``estop`` (requested), ``driver_fault`` or ``joint_limit_fault``.
            suggested_action: One line for the operator; a default when ``None``.

        Returns:
            Whether this call latched it (False when it was already latched).
        """
        with self._estop_lock:
            if self._estop is not None:
                return False
            self._estop_reported = False
            self._estop = SafetyEvent(
                code, reason, suggested_action or "make the robot and workspace safe, then reset"
            )
            return True

    def reset(self) -> None:
        """Release a latched e-stop. The chain restarts stopped: it re-seeds from the measured state
        and needs fresh valid input, then ramps up again."""
        with self._estop_lock:
            self._estop = None
            self._estop_reported = True
        self._seeded = False
        self._running = False
        self._stale = False
        self._stable_s = 0.0
        self.goal.forget()  # a goal stamped ahead of the clock must not outlive the reset

    def restart(self) -> None:
        """Restart stopped as after :meth:`reset`, but keep a latched e-stop: re-seed from the measured
        state, then track fresh valid input through the start-up ramp (an input device that was
        paused on its own resumes gently, wherever the operator's hand went meanwhile)."""
        self._seeded = False
        self._running = False
        self._stale = False
        self._stable_s = 0.0
        self.goal.forget()

    def hand_over(self) -> None:
        """A new source takes over a running chain: keep tracking from the last command, restart the
        start-up ramp. Unlike :meth:`restart` nothing re-seeds from the measured state, so the output
        never steps to where the arm *is* when that differs from where it was commanded (a position-
        controlled arm sags under gravity: re-seeded there, it would drop by that sag). A chain that is
        not running restarts as after :meth:`restart`."""
        if not (self._running and self._seeded):
            self.restart()
            return
        self._stable_s = 0.0

    def note(self, event: SafetyEvent) -> None:
        """Count an event of this robot's safety layer raised outside the chain (gripper, base).

        Counted in :attr:`counts` like the chain's own; call from the control loop.
        """
        self._counts[event.code] += 1

    def step(
        self, requested: JointCommand | None, *, now_ns: int, measured: JointState | None
    ) -> SafetyOutput:
        """Run one control tick.

        Args:
            requested: New command from retargeting, or ``None`` if there is none this tick.
                Joint names must equal ``limits.names`` in order; positions [rad].
            now_ns: Current time in the rig's common clock [ns] (the clock of ``capture_ns``).
            measured: Latest measured joint state of the robot, same joints; ``None`` when the
                driver could not deliver one (latches a ``driver_fault`` e-stop).

        Returns:
            The command to send (or ``None`` when e-stopped), the status and this tick's events.
        """
        self._seq += 1
        self._events.clear()
        if self._estop is None:
            self._check_measured(measured)
        if self._estop is not None or measured is None:
            return self._estopped()
        tick = self._tick
        self._advance(tick, now_ns, measured)
        for gate in self.gates:
            verdict = gate.admit(now_ns, tick)
            if verdict is not True:
                requested = None  # dropped: the chain holds, then stops as on input loss
                if verdict is not False:
                    self._report(verdict)
        new = False
        if requested is not None:
            rejection = self.goal.offer(requested, tick)
            if rejection is None:
                new = True
            else:
                self._report(rejection)
        goal = self.goal
        age_ns = now_ns - goal.capture_ns
        freshness = self.watchdog.freshness(age_ns) if goal.valid else "expired"
        if not self._running:
            if not (new and freshness == "fresh"):
                return self._stopped(now_ns)
            self._resume(tick, measured)
        elif freshness == "expired":
            self._report(_watchdog_stop(age_ns, self.watchdog.stop_timeout_ns))
            self._running = False
            self._stable_s = 0.0
            self._stop_position[:] = measured.positions
            return self._stopped(now_ns)
        status: SafetyStatus
        if freshness == "stale":
            status = "holding"
            if not self._stale:
                self._stale = True
                tick.goal_velocity.fill(0.0)  # the held goal no longer moves
                self._report(_input_stale(age_ns))
        else:
            self._stale = False
            status = "ok" if new else "holding"
        tick.speed_scale = 1.0 if self.ramp is None else self.ramp.scale(self._stable_s)
        if new and freshness == "fresh":
            self._stable_s += tick.dt_s
        if self._limit(tick) and status == "ok":
            status = "limited"
        self._status = status
        stamp = requested.stamp if (new and requested is not None) else self._own_stamp(now_ns)
        events = self._events
        return SafetyOutput(
            JointCommand(stamp, self._names, tick.target), status, tuple(events) if events else _NO_EVENTS
        )

    def _check_measured(self, measured: JointState | None) -> None:
        limits = self.limits
        for check in self.measured:
            fault = check.check(measured, limits)
            if fault is not None:
                self.estop(fault.reason, code=fault.code, suggested_action=fault.suggested_action)
                return

    def _estopped(self) -> SafetyOutput:
        self._status = "estopped"
        self._running = False
        estop = self._estop
        if estop is not None and not self._estop_reported:
            self._estop_reported = True
            self._count(estop)
            return SafetyOutput(None, "estopped", (estop,))
        return SafetyOutput(None, "estopped", _NO_EVENTS)

    def _advance(self, tick: Tick, now_ns: int, measured: JointState) -> None:
        """Seed the tick from the measured state after a start or reset, else bound its dt."""
        if not self._seeded:
            self._seeded = True
            tick.previous[:] = measured.positions
            tick.previous_velocity.fill(0.0)
            self._stop_position[:] = measured.positions
            tick.dt_s = self.period_s
        else:
            gap_ns = now_ns - self._last_now_ns
            if self._running and gap_ns > self.watchdog.hold_timeout_ns:
                # The chain itself did not tick for longer than the input watchdog's hold (a loop
                # starved by a loaded host): the robot held its last command all that while. Resume
                # from where it is, at the start of the ramp, as after a watchdog stop; catching up
                # at full speed with a goal that moves along with the output overshoots the goal.
                self._report(_control_gap(gap_ns, self.watchdog.hold_timeout_ns))
                self._resume(tick, measured)
                tick.dt_s = self.period_s
            else:
                dt = gap_ns * 1e-9
                tick.dt_s = 0.0 if dt < 0.0 else min(dt, self._max_dt_s)
        self._last_now_ns = now_ns

    def _resume(self, tick: Tick, measured: JointState) -> None:
        """Start tracking from where the arm is, at the start of the ramp."""
        self._running = True
        self._stale = False
        self._stable_s = 0.0
        tick.previous[:] = measured.positions
        tick.previous_velocity.fill(0.0)
        tick.goal_velocity.fill(0.0)

    def _limit(self, tick: Tick) -> bool:
        """Shape the goal through the limits into ``tick.target``; whether any limit changed it."""
        tick.target[:] = self.goal.positions
        limited = False
        for limit in self.filters:
            event = limit.apply(tick)
            if event is not None:
                limited = True
                self._report(event)
        dt = tick.dt_s
        if dt > 0.0:
            np.subtract(tick.target, tick.previous, out=tick.previous_velocity)
            tick.previous_velocity *= 1.0 / dt
        tick.previous[:] = tick.target
        return limited

    def _stopped(self, now_ns: int) -> SafetyOutput:
        self._status = "stopped"
        events = self._events
        return SafetyOutput(
            JointCommand(self._own_stamp(now_ns), self._names, self._stop_position),
            "stopped",
            tuple(events) if events else _NO_EVENTS,
        )

    def _own_stamp(self, now_ns: int) -> Stamp:
        return Stamp(self.source_id, self._seq, now_ns, now_ns)

    def _count(self, event: SafetyEvent) -> None:
        self._counts[event.code] += 1

    def _report(self, event: SafetyEvent) -> None:
        self._counts[event.code] += 1
        self._events.append(event)


def _watchdog_stop(age_ns: int, limit_ns: int) -> SafetyEvent:
    return SafetyEvent(
        "watchdog_stop",
        f"no valid input for {age_ns * 1e-6:.0f} ms (limit {limit_ns * 1e-6:.0f} ms); "
        "holding the measured position",
        "check the input device and its connection; control resumes with fresh input",
    )


def _control_gap(gap_ns: int, limit_ns: int) -> SafetyEvent:
    return SafetyEvent(
        "input_stale",
        f"no control tick for {gap_ns * 1e-6:.0f} ms (limit {limit_ns * 1e-6:.0f} ms); the robot held "
        "its last command; resuming from the measured position at the start of the speed ramp",
        "the control loop was starved: a loaded host, or the robot process without real-time priority",
    )


def _input_stale(age_ns: int) -> SafetyEvent:
    return SafetyEvent(
        "input_stale",
        f"last valid input is {age_ns * 1e-6:.0f} ms old; holding the last valid command",
        "check the input device and its connection",
    )
