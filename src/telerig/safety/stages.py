"""Safety chain stages around the target limits: measured-state checks, request gates, the held goal.

Together with :mod:`telerig.safety.filters` (input checks, limits, ramp, watchdog) these are the
small objects a :class:`~telerig.safety.SafetyChain` is composed of, each with one method:

==========================  ==================================  =====================================
stage                       method                              what it decides
==========================  ==================================  =====================================
:class:`MeasuredCheck`      ``check(measured, limits)``         is the robot itself at fault? (e-stop)
:class:`Gate`               ``admit(now_ns, tick)``             may requests pass this tick?
:class:`InputCheck`         ``check(command, limits)``          may this request be used at all?
:class:`GoalHold`           ``offer(command, tick)``            the last valid request, held as goal
:class:`Limit`              ``apply(tick)``                     shape the output to one limit
==========================  ==================================  =====================================

Every stage reuses its buffers and returns preallocated events on the normal path, so a chain
step allocates only its output (the chain runs at 100-500 Hz).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Protocol, runtime_checkable

import numpy as np

from telerig.errors import ConfigError
from telerig.ir.types import FloatArray, JointCommand, JointState
from telerig.robots.base import JointLimits
from telerig.safety.deadman import Deadman
from telerig.safety.filters import InputCheck, SafetyCode, SafetyEvent, Tick

__all__ = [
    "LIVE_REJECTIONS",
    "DeadmanGate",
    "DriverStateCheck",
    "FiniteCheck",
    "Gate",
    "GoalHold",
    "JointNamesCheck",
    "MeasuredCheck",
    "MeasuredLimitCheck",
]

#: Refusals of valid requests because of where they lead; they keep the watchdog fed.
LIVE_REJECTIONS: frozenset[SafetyCode] = frozenset({"workspace", "self_collision"})

# A ufunc reduction: skips ndarray.any()'s Python wrapper (~0.4 us) on the per-tick path.
_any = np.logical_or.reduce

_DRIVER_ACTION = "check the driver's connection and the robot controller, then reset"


@runtime_checkable
class MeasuredCheck(Protocol):
    """Judges the robot's measured state each tick; a failed check latches the chain's e-stop."""

    def check(self, measured: JointState | None, limits: JointLimits) -> SafetyEvent | None:
        """``None`` if ``measured`` (``None``: the driver delivered none) is sound, else the fault."""
        ...


@runtime_checkable
class Gate(Protocol):
    """Decides whether this tick's request may pass at all (e.g. the deadman switch)."""

    def admit(self, now_ns: int, tick: Tick) -> bool | SafetyEvent:
        """``True``: pass the request; ``False``: drop it; an event: drop it and report the event.

        A gate that closes zeroes ``tick.goal_velocity`` so the held goal no longer moves.
        """
        ...


class DriverStateCheck:
    """Faults on a missing or malformed measured state: none, other joints, non-finite positions.

    Always first in a chain: every later stage relies on the measured state being sound.
    """

    __slots__ = ()

    def check(self, measured: JointState | None, limits: JointLimits) -> SafetyEvent | None:
        """A ``driver_fault`` unless ``measured`` has ``limits.names`` (in order) and finite positions."""
        if measured is None:
            return SafetyEvent("driver_fault", "no measured state from the driver", _DRIVER_ACTION)
        if measured.names != limits.names:
            return SafetyEvent(
                "driver_fault",
                f"measured joints {measured.names} do not match the commanded joints {limits.names}",
                _DRIVER_ACTION,
            )
        q = measured.positions
        if not math.isfinite(float(q.sum())):
            return SafetyEvent(
                "driver_fault", f"measured joint positions are not finite: {q.tolist()}", _DRIVER_ACTION
            )
        return None


class MeasuredLimitCheck:
    """Faults on a measured position beyond the joint limits by more than a tolerance.

    Place it after :class:`DriverStateCheck` (it assumes the joints match and are finite).
    """

    __slots__ = ("_for", "_lower", "_upper", "tolerance")

    def __init__(self, tolerance: float = 0.05) -> None:
        """Args:
        tolerance: Excess of a *measured* position beyond the joint limits that is a fault [rad] (>= 0).
        """
        if not (math.isfinite(tolerance) and tolerance >= 0):
            raise ConfigError(f"measured_tolerance must be a finite value >= 0 rad, got {tolerance}")
        self.tolerance = float(tolerance)
        self._for: JointLimits | None = None
        self._lower: FloatArray = np.zeros(0)
        self._upper: FloatArray = np.zeros(0)

    def check(self, measured: JointState | None, limits: JointLimits) -> SafetyEvent | None:
        """A ``joint_limit_fault`` naming the worst joint beyond its limits by more than the tolerance."""
        if measured is None:
            return None
        if self._for is not limits:  # derived bounds, computed once per limits object
            self._for = limits
            self._lower = limits.lower - self.tolerance
            self._upper = limits.upper + self.tolerance
        q = measured.positions
        if not (_any(q < self._lower) or _any(q > self._upper)):
            return None
        excess = np.maximum(limits.lower - q, q - limits.upper)
        j = int(np.argmax(excess))
        return SafetyEvent(
            "joint_limit_fault",
            f"measured joint '{limits.names[j]}' at {q[j]:.3f} rad is beyond its limits "
            f"[{limits.lower[j]:.3f}, {limits.upper[j]:.3f}] rad by {excess[j]:.3f} rad",
            "jog the joint back inside its range, check the configured limits, then reset",
        )


class DeadmanGate:
    """Passes requests only while a :class:`~telerig.safety.Deadman` switch is enabled.

    Released, every request is dropped, so the chain holds and then stops as on input loss; the
    release is reported once (``deadman``), and pressing again resumes from where the arm is.
    """

    __slots__ = ("_open", "_released", "deadman")

    def __init__(self, deadman: Deadman) -> None:
        """Args:
        deadman: The switch the control node feeds.
        """
        self.deadman = deadman
        self._open = False  # released, and the release already reported
        self._released = SafetyEvent(
            "deadman",
            "deadman switch released; holding the last command, stopping after the watchdog time",
            "hold the enable button to move the robot",
        )

    def admit(self, now_ns: int, tick: Tick) -> bool | SafetyEvent:
        """``True`` while enabled; the release event on the first released tick; ``False`` after."""
        if self.deadman.enabled(now_ns):
            self._open = False
            return True
        if self._open:
            return False
        self._open = True
        tick.goal_velocity.fill(0.0)  # the held goal no longer moves
        return self._released


class JointNamesCheck:
    """Rejects a request whose joints are not the robot's, in the robot's order."""

    __slots__ = ()

    def check(self, command: JointCommand, limits: JointLimits) -> SafetyEvent | None:
        """``invalid_input`` naming the missing and unknown joints (or the wrong order)."""
        names = limits.names
        if command.names == names:
            return None
        missing = [n for n in names if n not in command.names]
        extra = [n for n in command.names if n not in names]
        detail = f"missing {missing}, unknown {extra}" if missing or extra else "wrong order"
        return SafetyEvent(
            "invalid_input",
            f"joint names {list(command.names)} do not match the robot's {list(names)} ({detail})",
            "make the retargeter emit the driver's joints, in the driver's order",
        )


class FiniteCheck:
    """Rejects a request with a NaN or infinite position or velocity (an IK failure, a bad sample)."""

    __slots__ = ()

    def check(self, command: JointCommand, limits: JointLimits) -> SafetyEvent | None:
        """``invalid_input`` unless every position and velocity is finite."""
        # A sum is finite only if every term is (finite values this large are rejected by range).
        if math.isfinite(float(command.positions.sum())) and (
            not command.velocities.size or math.isfinite(float(command.velocities.sum()))
        ):
            return None
        return SafetyEvent(
            "invalid_input",
            f"non-finite joint command {command.positions.tolist()}",
            "check the retargeting (IK failure) and the input device's samples",
        )


class GoalHold:
    """Holds the last valid request as the chain's goal ("hold the last valid command on short loss").

    :meth:`offer` runs the input checks in order: the joint names, finite values, capture order
    (never older than the goal), then ``checks`` (policy: range, workspace...). An accepted request
    becomes the goal, with its velocity estimated from the previous goal for the acceleration
    limit's braking. A rejected one leaves the goal and stops it moving; if it was refused only for
    where it leads (:data:`LIVE_REJECTIONS`), it still proves the input alive for the watchdog.

    Attributes:
        positions: The goal [rad]. Shape (n,). Meaningful once ``valid``.
        capture_ns: Capture time of the last request that proved the input alive [ns].
        valid: Whether a request was ever accepted.
    """

    __slots__ = (
        "_limits",
        "_max_gap_s",
        "_neg_velocity",
        "_policy",
        "_structural",
        "capture_ns",
        "checks",
        "positions",
        "valid",
    )

    def __init__(
        self, limits: JointLimits, checks: Sequence[InputCheck] = (), *, max_gap_s: float = 0.1
    ) -> None:
        """Args:
        limits: Joint limits of the robot part (n joints).
        checks: Policy checks, run in order after the structural ones.
        max_gap_s: Requests further apart than this [s] do not estimate a goal velocity (> 0).
        """
        if not (math.isfinite(max_gap_s) and max_gap_s > 0.0):
            raise ConfigError(f"max_gap_s must be > 0 s, got {max_gap_s}")
        self._limits = limits
        self._max_gap_s = float(max_gap_s)
        self._neg_velocity = -limits.velocity
        self._structural: tuple[InputCheck, ...] = (JointNamesCheck(), FiniteCheck())
        self._policy: tuple[InputCheck, ...] = tuple(checks)
        #: Every input check, in the order :meth:`offer` runs them (the capture order check sits
        #: between the structural ones and the policy ones).
        self.checks: tuple[InputCheck, ...] = self._structural + self._policy
        self.positions: FloatArray = np.zeros(len(limits.names))
        self.capture_ns = 0
        self.valid = False

    def forget(self) -> None:
        """Drop the goal and its capture time: the next valid request becomes the goal whatever its
        stamp (after a reset, a request stamped ahead of the clock no longer holds the order check)."""
        self.capture_ns = 0
        self.valid = False

    def offer(self, command: JointCommand, tick: Tick) -> SafetyEvent | None:
        """Make ``command`` the goal and estimate ``tick.goal_velocity``; else the rejection.

        A rejection zeroes ``tick.goal_velocity``: the held goal no longer moves, so the output
        brakes instead of coasting past it.
        """
        rejection = self._rejection(command)
        if rejection is None:
            self._estimate_velocity(command, tick.goal_velocity)
            self.positions[:] = command.positions
            self.capture_ns = command.stamp.capture_ns
            self.valid = True
            return None
        tick.goal_velocity.fill(0.0)
        if rejection.code in LIVE_REJECTIONS and self.valid and command.stamp.capture_ns >= self.capture_ns:
            # A well-formed request refused for where it leads proves the input is alive:
            # hold at the last safe command without a watchdog stop (and ramp restart).
            self.capture_ns = command.stamp.capture_ns
        return rejection

    def _rejection(self, command: JointCommand) -> SafetyEvent | None:
        limits = self._limits
        for check in self._structural:  # names and finite values: the order check relies on them
            event = check.check(command, limits)
            if event is not None:
                return event
        if self.valid and command.stamp.capture_ns < self.capture_ns:
            return SafetyEvent(
                "invalid_input",
                f"command captured at {command.stamp.capture_ns} ns is older than the last accepted one "
                f"({self.capture_ns} ns); out of order",
                "check the transport's ordering between retargeting and the control loop",
            )
        for check in self._policy:
            event = check.check(command, limits)
            if event is not None:
                return event
        return None

    def _estimate_velocity(self, command: JointCommand, gv: FloatArray) -> None:
        # Finite difference of consecutive valid requests, bounded by the speed limits; only the
        # acceleration limit's braking uses it, so noise here can only loosen braking a little.
        dt = (command.stamp.capture_ns - self.capture_ns) * 1e-9
        if not self.valid or dt <= 0.0 or dt > self._max_gap_s:
            gv.fill(0.0)
            return
        np.subtract(command.positions, self.positions, out=gv)
        gv *= 1.0 / dt
        np.minimum(gv, self._limits.velocity, out=gv)
        np.maximum(gv, self._neg_velocity, out=gv)
