"""Safety filters: input checks, target limits, the start-up ramp and the input watchdog."""

from __future__ import annotations

import math
import typing
from dataclasses import dataclass
from typing import Literal, Protocol, runtime_checkable

import numpy as np

from telerig.errors import ConfigError
from telerig.ir.types import FloatArray, JointCommand
from telerig.robots.base import JointLimits

__all__ = [
    "SAFETY_CODES",
    "AccelerationLimit",
    "Freshness",
    "InputCheck",
    "InputWatchdog",
    "Limit",
    "PositionClamp",
    "PositionRangeCheck",
    "SafetyCode",
    "SafetyEvent",
    "StartupRamp",
    "Tick",
    "VelocityLimit",
]

#: What a safety event is about. ``workspace`` / ``self_collision``: a configuration check refused a
#: request or braked the output; ``deadman``: the enable switch was released; ``joint_limit_fault``:
#: the *measured* state is beyond the joint limits; ``driver_fault``: the driver raised, lost its
#: connection or reported an invalid state. The last three latch an e-stop.
SafetyCode = Literal[
    "invalid_input",
    "out_of_range",
    "position_limit",
    "velocity_limit",
    "acceleration_limit",
    "workspace",
    "self_collision",
    "deadman",
    "input_stale",
    "watchdog_stop",
    "joint_limit_fault",
    "driver_fault",
    "estop",
]

#: Every :data:`SafetyCode`, in severity order (the chain keeps a counter for each).
SAFETY_CODES: tuple[SafetyCode, ...] = typing.get_args(SafetyCode)

# Reductions called as ufuncs: ndarray.any() / .all() go through a Python wrapper (numpy's
# _methods.py) that costs ~0.4 us a call, and a chain tick makes about ten of them.
_any = np.logical_or.reduce
_all = np.logical_and.reduce

#: How old the last valid input is, as judged by :class:`InputWatchdog`.
Freshness = Literal["fresh", "stale", "expired"]


@dataclass(frozen=True, slots=True)
class SafetyEvent:
    """Something the safety chain did or refused, for logs, counters and operator alerts.

    Attributes:
        code: What happened (one of :data:`SAFETY_CODES`).
        reason: One line for a human: what was wrong, with numbers and joint names where known.
        suggested_action: One line saying what the operator or integrator should do about it.
    """

    code: SafetyCode
    reason: str
    suggested_action: str


class Tick:
    """Per-tick working state the chain hands to every :class:`Limit`; reused, never reallocated.

    Attributes:
        limits: The robot's joint limits (n joints).
        target: Command being shaped, edited in place by each limit [rad]. Shape (n,).
        previous: Output of the previous tick [rad]. Shape (n,). Read-only for limits.
        previous_velocity: Velocity of the previous output step [rad/s]. Shape (n,). Read-only.
        goal_velocity: Estimated velocity of the requested goal [rad/s], from consecutive valid
            requests; zero when holding a stale goal or just resumed. Shape (n,). Read-only.
        dt_s: Time since the previous tick [s], already bounded by the chain (>= 0).
        speed_scale: Start-up ramp factor in (0, 1] applied to the velocity limits.
        work: Scratch buffer a limit may overwrite freely. Shape (n,).
        bound: Second scratch buffer. Shape (n,).
    """

    __slots__ = (
        "bound",
        "dt_s",
        "goal_velocity",
        "limits",
        "previous",
        "previous_velocity",
        "speed_scale",
        "target",
        "work",
    )

    def __init__(self, limits: JointLimits) -> None:
        n = len(limits.names)
        self.limits = limits
        self.target: FloatArray = np.zeros(n)
        self.previous: FloatArray = np.zeros(n)
        self.previous_velocity: FloatArray = np.zeros(n)
        self.goal_velocity: FloatArray = np.zeros(n)
        self.dt_s = 0.0
        self.speed_scale = 1.0
        self.work: FloatArray = np.zeros(n)
        self.bound: FloatArray = np.zeros(n)


@runtime_checkable
class InputCheck(Protocol):
    """Decides whether a requested command may be used at all; a failed check rejects it."""

    def check(self, command: JointCommand, limits: JointLimits) -> SafetyEvent | None:
        """Return ``None`` if ``command`` is acceptable, else the event that rejects it.

        The chain has already checked that the joint names match ``limits.names`` (same order)
        and that every value is finite.
        """
        ...


@runtime_checkable
class Limit(Protocol):
    """Shapes ``tick.target`` in place so the output respects one limit."""

    def apply(self, tick: Tick) -> SafetyEvent | None:
        """Edit ``tick.target`` in place; return an event if it had to change it, else ``None``."""
        ...


class PositionRangeCheck:
    """Rejects targets beyond the position limits by more than a tolerance (likely a retargeting fault).

    Targets within the tolerance pass and are clamped later by :class:`PositionClamp`.
    """

    __slots__ = ("tolerance",)

    def __init__(self, tolerance: float = 0.05) -> None:
        """Args:
        tolerance: Allowed excess beyond the limits before rejecting [rad] (>= 0).
        """
        if not (math.isfinite(tolerance) and tolerance >= 0.0):
            raise ConfigError(f"position tolerance must be a finite value >= 0 rad, got {tolerance}")
        self.tolerance = float(tolerance)

    def check(self, command: JointCommand, limits: JointLimits) -> SafetyEvent | None:
        """Reject ``command`` if a joint exceeds ``[lower - tolerance, upper + tolerance]``."""
        q = command.positions
        # Fast path: nearly every command is inside the limits.
        if not (_any(q < limits.lower) or _any(q > limits.upper)):
            return None
        excess = np.maximum(limits.lower - q, q - limits.upper)
        worst = int(np.argmax(excess))
        if excess[worst] <= self.tolerance:
            return None
        side = "lower" if q[worst] < limits.lower[worst] else "upper"
        bound = limits.lower[worst] if side == "lower" else limits.upper[worst]
        return SafetyEvent(
            "out_of_range",
            f"joint '{limits.names[worst]}' target {q[worst]:.3f} rad is beyond its {side} limit "
            f"{bound:.3f} rad by {excess[worst]:.3f} rad (tolerance {self.tolerance:.3f} rad); rejected",
            "check the retargeting (IK branch, calibration, scaling) for this joint",
        )


class PositionClamp:
    """Clamps the target to the joint position limits, without ever making the output jump.

    If the previous output is already outside a limit (e.g. the chain was seeded from a measured
    state just past it), the bound is widened to the previous output for that joint, so the output
    never moves further out and never jumps back in.
    """

    __slots__ = ("_event",)

    def __init__(self) -> None:
        self._event = SafetyEvent(
            "position_limit",
            "target clamped to the joint position limits",
            "move the operator's hand back into the robot's reachable range",
        )

    def apply(self, tick: Tick) -> SafetyEvent | None:
        """Clamp ``tick.target`` to ``[min(lower, previous), max(upper, previous)]`` [rad]."""
        x, lo, hi = tick.target, tick.limits.lower, tick.limits.upper
        if not (_any(x < lo) or _any(x > hi)):
            return None
        np.minimum(lo, tick.previous, out=tick.work)
        np.maximum(x, tick.work, out=x)
        np.maximum(hi, tick.previous, out=tick.work)
        np.minimum(x, tick.work, out=x)
        return self._event


class VelocityLimit:
    """Bounds each joint's step to ``fraction * speed_scale * velocity * dt`` per tick.

    With ``speed_scale`` from the start-up ramp, this is what makes the robot start slowly.
    """

    __slots__ = ("_event", "fraction")

    def __init__(self, fraction: float = 1.0) -> None:
        """Args:
        fraction: Share of the rated joint speeds (``JointLimits.velocity``) to allow, in (0, 1].
        """
        if not (math.isfinite(fraction) and 0.0 < fraction <= 1.0):
            raise ConfigError(f"velocity fraction must be in (0, 1], got {fraction}")
        self.fraction = float(fraction)
        self._event = SafetyEvent(
            "velocity_limit",
            "joint speed limited",
            "none needed; move more slowly to track the operator exactly",
        )

    def apply(self, tick: Tick) -> SafetyEvent | None:
        """Limit ``tick.target - tick.previous`` per joint to the scaled speed times ``dt_s`` [rad]."""
        step, bound = tick.work, tick.bound
        np.multiply(tick.limits.velocity, self.fraction * tick.speed_scale * tick.dt_s, out=bound)
        np.subtract(tick.target, tick.previous, out=step)
        if _all(np.abs(step) <= bound):
            return None
        np.minimum(step, bound, out=step)
        np.negative(bound, out=bound)
        np.maximum(step, bound, out=step)
        np.add(tick.previous, step, out=tick.target)
        return self._event


class AccelerationLimit:
    """Bounds each joint's change of velocity to ``fraction * acceleration * dt`` per tick.

    It also caps the speed towards the target to what can still be braked at that acceleration
    relative to the goal's own velocity (``tick.goal_velocity``), so the output approaches a far
    target with a trapezoidal profile instead of overshooting, yet tracks a moving one without lag.
    Place it before :class:`VelocityLimit`, which keeps the result within the speed limit.
    """

    __slots__ = ("_a", "_event", "_for", "_two_over_a", "fraction")

    def __init__(self, fraction: float = 1.0) -> None:
        """Args:
        fraction: Share of the rated joint accelerations (``JointLimits.acceleration``), in (0, 1].
        """
        if not (math.isfinite(fraction) and 0.0 < fraction <= 1.0):
            raise ConfigError(f"acceleration fraction must be in (0, 1], got {fraction}")
        self.fraction = float(fraction)
        self._event = SafetyEvent(
            "acceleration_limit",
            "joint acceleration limited",
            "none needed; move more smoothly to track the operator exactly",
        )
        self._for: JointLimits | None = None
        self._a: FloatArray = np.zeros(0)
        self._two_over_a: FloatArray = np.zeros(0)

    def apply(self, tick: Tick) -> SafetyEvent | None:
        """Limit the velocity implied by ``tick.target`` to the accelerations and braking distance."""
        dt = tick.dt_s
        if dt <= 0.0:
            return None
        if self._for is not tick.limits:  # derived arrays, computed once per limits object
            self._for = tick.limits
            self._a = tick.limits.acceleration * self.fraction
            self._two_over_a = 2.0 / self._a
        a, v, bound = self._a, tick.work, tick.bound
        np.subtract(tick.target, tick.previous, out=v)
        dist = np.abs(v)
        direction = np.sign(v)
        # Largest relative speed from which a discrete-time stop at acceleration a covers at most
        # dist: v^2 / (2a) + v dt / 2 = dist; plus the goal's own speed along the error.
        np.multiply(dist, self._two_over_a, out=bound)
        bound += 0.25 * dt * dt
        np.sqrt(bound, out=bound)
        bound -= 0.5 * dt
        bound *= a
        bound += direction * tick.goal_velocity
        dist *= 1.0 / dt  # now the speed that reaches the target this tick
        braking = bool(_any(bound < dist))
        np.minimum(dist, bound, out=dist)
        np.multiply(dist, direction, out=v)
        # Velocity change per tick at most a * dt around the previous velocity.
        np.multiply(a, dt, out=bound)
        np.subtract(tick.previous_velocity, bound, out=dist)
        np.add(tick.previous_velocity, bound, out=bound)
        if not braking and _all(v >= dist) and _all(v <= bound):
            return None
        np.maximum(v, dist, out=v)
        np.minimum(v, bound, out=v)
        v *= dt
        np.add(tick.previous, v, out=tick.target)
        return self._event


class StartupRamp:
    """Start-up speed ramp: the velocity limits start at a fraction and relax linearly to 100 %.

    Time counts only while control is stable (a fresh, valid command every tick); the chain
    restarts the ramp after every stop, watchdog stop and e-stop reset.
    """

    __slots__ = ("duration_s", "initial_fraction")

    def __init__(self, initial_fraction: float = 0.1, duration_s: float = 3.0) -> None:
        """Args:
        initial_fraction: Speed scale at the start, in (0, 1].
        duration_s: Stable control time to reach full speed [s] (>= 0; 0 disables the ramp).
        """
        if not (math.isfinite(initial_fraction) and 0.0 < initial_fraction <= 1.0):
            raise ConfigError(f"ramp initial_fraction must be in (0, 1], got {initial_fraction}")
        if not (math.isfinite(duration_s) and duration_s >= 0.0):
            raise ConfigError(f"ramp duration_s must be a finite value >= 0 s, got {duration_s}")
        self.initial_fraction = float(initial_fraction)
        self.duration_s = float(duration_s)

    def scale(self, stable_s: float) -> float:
        """Speed scale in [initial_fraction, 1] after ``stable_s`` seconds of stable control."""
        if stable_s >= self.duration_s:
            return 1.0
        f0 = self.initial_fraction
        return f0 + (1.0 - f0) * (stable_s / self.duration_s)


class InputWatchdog:
    """Judges the age of the last valid input: fresh, stale (still holding) or expired (stop).

    Age is ``now - capture time`` of the last valid command, so a pipeline that keeps delivering
    old samples trips it just like a silent one.
    """

    __slots__ = ("hold_timeout_ns", "stop_timeout_ns")

    def __init__(self, hold_timeout_s: float = 0.1, stop_timeout_s: float = 0.25) -> None:
        """Args:
        hold_timeout_s: Age up to which input counts as fresh [s]; beyond it the chain holds
            and reports ``input_stale``.
        stop_timeout_s: Age beyond which the chain stops the robot [s] (> hold_timeout_s).
        """
        if not (math.isfinite(hold_timeout_s) and hold_timeout_s > 0.0):
            raise ConfigError(f"hold_timeout_s must be > 0 s, got {hold_timeout_s}")
        if not (math.isfinite(stop_timeout_s) and stop_timeout_s > hold_timeout_s):
            raise ConfigError(
                f"stop_timeout_s must be greater than hold_timeout_s ({hold_timeout_s} s), "
                f"got {stop_timeout_s}"
            )
        self.hold_timeout_ns = round(hold_timeout_s * 1e9)
        self.stop_timeout_ns = round(stop_timeout_s * 1e9)

    def freshness(self, age_ns: int) -> Freshness:
        """``"fresh"`` below the hold timeout, ``"expired"`` past the stop timeout, else ``"stale"``."""
        if age_ns < self.hold_timeout_ns:
            return "fresh"
        if age_ns > self.stop_timeout_ns:
            return "expired"
        return "stale"
