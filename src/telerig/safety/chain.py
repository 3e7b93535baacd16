"""The safety chain: the one gate between retargeting and every robot driver, stepped once per tick."""

from __future__ import annotations

import math
import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType
from typing import Literal

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

__all__ = ["FAULT_CODES", "SafetyChain", "SafetyOutput", "SafetyStatus"]

#: What the chain did this tick, most severe first: ``estopped`` (latched, no command: call
#: ``driver.estop()``), ``stopped`` (input lost or never started: hold the measured position),
#: ``holding`` (no fresh input: keep going to the last valid command), ``limited`` (tracking, but a
#: limit changed the command), ``ok`` (tracking the request unchanged).
SafetyStatus = Literal["ok", "limited", "holding", "stopped", "estopped"]

_NO_EVENTS: tuple[SafetyEvent, ...] = ()
#: Refusals of valid requests because of where they lead; they keep the watchdog fed.
_LIVE_REJECTIONS: frozenset[SafetyCode] = frozenset({"workspace", "self_collision"})
#: Codes that mean the robot itself is at fault (the fleet policy reacts to them).
FAULT_CODES: frozenset[SafetyCode] = frozenset({"joint_limit_fault", "driver_fault"})


@dataclass(frozen=True, slots=True)
class SafetyOutput:
    """Result of one :meth:`SafetyChain.step`.

    Attributes:
        command: What to send to the driver, or ``None`` when e-stopped (call ``driver.estop()``).
            Stamped with the request's stamp when it tracks this tick's request, else with a new
            stamp from the chain (source id ``SafetyChain.source_id``, capture time = ``now_ns``).
        status: What the chain did (see :data:`SafetyStatus`).
        events: What happened this tick, in filter order; empty on a normal tick.
    """

    command: JointCommand | None
    status: SafetyStatus
    events: tuple[SafetyEvent, ...]


class SafetyChain:
    """Validates, limits and watches joint commands; stepped once per control tick (e.g. 100 Hz).

    Per tick: reject invalid requests (treated like no input), keep the last valid one as goal,
    shape the goal with ``filters`` (in order) starting from the previous output, and watch the
    input's age. Structural checks (joint names and order match ``limits.names``, all values finite,
    capture time not older than the last accepted request) are always on because the chain's own
    state depends on them; ``checks`` adds policy on top.

    States: the chain starts *stopped*, commanding the measured position. Fresh valid input starts
    tracking from where the arm is, through the start-up ramp. Input older than the hold timeout
    makes it hold (going on to the last valid command); older than the stop timeout makes it stop
    (command the measured position) until fresh valid input arrives. :meth:`estop` latches until
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
        deadman: Enable switch; ``None`` means always enabled.
        measured_tolerance: Excess of a *measured* position beyond the joint limits that latches a
            ``joint_limit_fault`` e-stop [rad] (>= 0); ``None`` disables the check.
        """
        if not (math.isfinite(period_s) and period_s > 0.0):
            raise ConfigError(f"period_s must be > 0 s, got {period_s}")
        if measured_tolerance is not None and not (
            math.isfinite(measured_tolerance) and measured_tolerance >= 0
        ):
            raise ConfigError(f"measured_tolerance must be a finite value >= 0 rad, got {measured_tolerance}")
        self.limits = limits
        self.checks: tuple[InputCheck, ...] = tuple(checks)
        self.filters: tuple[Limit, ...] = tuple(filters)
        self.ramp = ramp
        self.watchdog = watchdog if watchdog is not None else InputWatchdog()
        self.period_s = float(period_s)
        self.source_id = source_id
        self.deadman = deadman
        self.measured_tolerance = measured_tolerance
        self._lower_tol = limits.lower - (measured_tolerance or 0.0)
        self._upper_tol = limits.upper + (measured_tolerance or 0.0)
        self._estop_lock = threading.Lock()
        self._deadman_open = False
        self._names = limits.names
        self._max_dt_s = 2.0 * self.period_s
        self._tick = Tick(limits)
        self._goal = np.zeros(len(limits.names))
        self._stop_position = np.zeros(len(limits.names))
        self._neg_velocity = -limits.velocity
        self._counts: dict[str, int] = dict.fromkeys(SAFETY_CODES, 0)
        self._counts_view: Mapping[str, int] = MappingProxyType(self._counts)
        self._events: list[SafetyEvent] = []
        self._seq = 0
        self._seeded = False
        self._last_now_ns = 0
        self._has_goal = False
        self._last_capture_ns = 0
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
        events = self._events
        events.clear()

        if self._estop is None:
            fault = self._check_measured(measured)
            if fault is not None:
                self.estop(fault[1], code=fault[0], suggested_action=fault[2])
        estop = self._estop
        if estop is not None or measured is None:
            self._status = "estopped"
            self._running = False
            if estop is not None and not self._estop_reported:
                self._estop_reported = True
                self._count(estop)
                return SafetyOutput(None, "estopped", (estop,))
            return SafetyOutput(None, "estopped", _NO_EVENTS)

        tick = self._tick
        if not self._seeded:
            self._seeded = True
            tick.previous[:] = measured.positions
            tick.previous_velocity.fill(0.0)
            self._stop_position[:] = measured.positions
            tick.dt_s = self.period_s
        else:
            dt = (now_ns - self._last_now_ns) * 1e-9
            tick.dt_s = 0.0 if dt < 0.0 else min(dt, self._max_dt_s)
        self._last_now_ns = now_ns

        if self.deadman is not None:
            if self.deadman.enabled(now_ns):
                self._deadman_open = False
            else:
                requested = None  # dropped: the chain holds, then stops as on input loss
                if not self._deadman_open:
                    self._deadman_open = True
                    tick.goal_velocity.fill(0.0)  # the held goal no longer moves
                    released = SafetyEvent(
                        "deadman",
                        "deadman switch released; holding the last command, stopping after the watchdog time",
                        "hold the enable button to move the robot",
                    )
                    self._count(released)
                    events.append(released)

        new = False
        if requested is not None:
            rejection = self._validate(requested)
            if rejection is None:
                self._estimate_goal_velocity(requested)
                self._goal[:] = requested.positions
                self._last_capture_ns = requested.stamp.capture_ns
                self._has_goal = True
                new = True
            else:
                tick.goal_velocity.fill(0.0)  # the held goal no longer moves: brake, never coast past it
                if (
                    rejection.code in _LIVE_REJECTIONS
                    and self._has_goal
                    and requested.stamp.capture_ns >= self._last_capture_ns
                ):
                    # A well-formed request refused for where it leads proves the input is alive:
                    # hold at the last safe command without a watchdog stop (and ramp restart).
                    self._last_capture_ns = requested.stamp.capture_ns
                self._count(rejection)
                events.append(rejection)

        freshness = self.watchdog.freshness(now_ns - self._last_capture_ns) if self._has_goal else "expired"

        if not self._running:
            if not (new and freshness == "fresh"):
                return self._stopped(now_ns)
            # Resume from where the arm is, at the start of the ramp.
            self._running = True
            self._stale = False
            self._stable_s = 0.0
            tick.previous[:] = measured.positions
            tick.previous_velocity.fill(0.0)
            tick.goal_velocity.fill(0.0)
        elif freshness == "expired":
            self._running = False
            self._stable_s = 0.0
            self._stop_position[:] = measured.positions
            event = SafetyEvent(
                "watchdog_stop",
                f"no valid input for {(now_ns - self._last_capture_ns) * 1e-6:.0f} ms "
                f"(limit {self.watchdog.stop_timeout_ns * 1e-6:.0f} ms); holding the measured position",
                "check the input device and its connection; control resumes with fresh input",
            )
            self._count(event)
            events.append(event)
            return self._stopped(now_ns)

        status: SafetyStatus
        if freshness == "stale":
            status = "holding"
            if not self._stale:
                self._stale = True
                tick.goal_velocity.fill(0.0)  # the held goal no longer moves
                event = SafetyEvent(
                    "input_stale",
                    f"last valid input is {(now_ns - self._last_capture_ns) * 1e-6:.0f} ms old; "
                    "holding the last valid command",
                    "check the input device and its connection",
                )
                self._count(event)
                events.append(event)
        else:
            self._stale = False
            status = "ok" if new else "holding"

        tick.speed_scale = 1.0 if self.ramp is None else self.ramp.scale(self._stable_s)
        if new and freshness == "fresh":
            self._stable_s += tick.dt_s
        tick.target[:] = self._goal
        limited = False
        for limit in self.filters:
            limit_event = limit.apply(tick)
            if limit_event is not None:
                limited = True
                self._count(limit_event)
                events.append(limit_event)
        if limited and status == "ok":
            status = "limited"

        dt = tick.dt_s
        if dt > 0.0:
            np.subtract(tick.target, tick.previous, out=tick.previous_velocity)
            tick.previous_velocity *= 1.0 / dt
        tick.previous[:] = tick.target
        stamp = requested.stamp if (new and requested is not None) else self._own_stamp(now_ns)
        self._status = status
        return SafetyOutput(
            JointCommand(stamp, self._names, tick.target),
            status,
            tuple(events) if events else _NO_EVENTS,
        )

    def _stopped(self, now_ns: int) -> SafetyOutput:
        self._status = "stopped"
        events = self._events
        return SafetyOutput(
            JointCommand(self._own_stamp(now_ns), self._names, self._stop_position),
            "stopped",
            tuple(events) if events else _NO_EVENTS,
        )

    def _estimate_goal_velocity(self, command: JointCommand) -> None:
        # Finite difference of consecutive valid requests, bounded by the speed limits; only the
        # acceleration limit's braking uses it, so noise here can only loosen braking a little.
        gv = self._tick.goal_velocity
        dt = (command.stamp.capture_ns - self._last_capture_ns) * 1e-9
        if not self._has_goal or dt <= 0.0 or dt > self._max_dt_s * 5:
            gv.fill(0.0)
            return
        np.subtract(command.positions, self._goal, out=gv)
        gv *= 1.0 / dt
        np.minimum(gv, self.limits.velocity, out=gv)
        np.maximum(gv, self._neg_velocity, out=gv)

    def _own_stamp(self, now_ns: int) -> Stamp:
        return Stamp(self.source_id, self._seq, now_ns, now_ns)

    def _count(self, event: SafetyEvent) -> None:
        self._counts[event.code] += 1

    def _check_measured(self, measured: JointState | None) -> tuple[SafetyCode, str, str] | None:
        driver = "check the driver's connection and the robot controller, then reset"
        if measured is None:
            return "driver_fault", "no measured state from the driver", driver
        if measured.names != self._names:
            return (
                "driver_fault",
                f"measured joints {measured.names} do not match the commanded joints {self._names}",
                driver,
            )
        q = measured.positions
        if not math.isfinite(float(q.sum())):
            return "driver_fault", f"measured joint positions are not finite: {q.tolist()}", driver
        if self.measured_tolerance is not None and (
            bool((q < self._lower_tol).any()) or bool((q > self._upper_tol).any())
        ):
            lim = self.limits
            excess = np.maximum(lim.lower - q, q - lim.upper)
            j = int(np.argmax(excess))
            return (
                "joint_limit_fault",
                f"measured joint '{self._names[j]}' at {q[j]:.3f} rad is beyond its limits "
                f"[{lim.lower[j]:.3f}, {lim.upper[j]:.3f}] rad by {excess[j]:.3f} rad",
                "jog the joint back inside its range, check the configured limits, then reset",
            )
        return None

    def _validate(self, command: JointCommand) -> SafetyEvent | None:
        if command.names != self._names:
            missing = [n for n in self._names if n not in command.names]
            extra = [n for n in command.names if n not in self._names]
            detail = f"missing {missing}, unknown {extra}" if missing or extra else "wrong order"
            return _invalid(
                f"joint names {list(command.names)} do not match the robot's {list(self._names)} ({detail})",
                "make the retargeter emit the driver's joints, in the driver's order",
            )
        # A sum is finite only if every term is (finite values this large are rejected by range).
        if not math.isfinite(float(command.positions.sum())) or (
            command.velocities.size and not math.isfinite(float(command.velocities.sum()))
        ):
            return _invalid(
                f"non-finite joint command {command.positions.tolist()}",
                "check the retargeting (IK failure) and the input device's samples",
            )
        if self._has_goal and command.stamp.capture_ns < self._last_capture_ns:
            return _invalid(
                f"command captured at {command.stamp.capture_ns} ns is older than the last accepted one "
                f"({self._last_capture_ns} ns); out of order",
                "check the transport's ordering between retargeting and the control loop",
            )
        for check in self.checks:
            event = check.check(command, self.limits)
            if event is not None:
                return event
        return None


def _invalid(reason: str, action: str) -> SafetyEvent:
    code: SafetyCode = "invalid_input"
    return SafetyEvent(code, reason, action)
