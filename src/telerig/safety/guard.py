"""Configuration guard: refuses forbidden joint configurations (workspace, self-collision), brakes in time."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from telerig.errors import ConfigError
from telerig.ir.types import FloatArray, JointCommand
from telerig.robots.base import JointLimits
from telerig.safety.filters import SafetyCode, SafetyEvent, Tick

__all__ = ["ConfigurationCheck", "ConfigurationGuard", "Violation"]


@dataclass(frozen=True, slots=True)
class Violation:
    """Why a joint configuration is forbidden.

    Attributes:
        code: ``workspace`` or ``self_collision`` (any :data:`~telerig.safety.SafetyCode`).
        depth_m: How far into the forbidden set [m] (> 0): distance outside the workspace box or
            inside a keep-out zone, or penetration (plus margin) of the worst contact.
        reason: One line naming the body/site, zone or body pair, with numbers.
        suggested_action: One line for the operator.
    """

    code: SafetyCode
    depth_m: float
    reason: str
    suggested_action: str


@runtime_checkable
class ConfigurationCheck(Protocol):
    """Judges one joint configuration of the robot (model-specific; the chain stays model-agnostic)."""

    def violation(self, q: FloatArray) -> Violation | None:
        """``None`` if the joint positions ``q`` [rad] (driver order, shape (n,)) are allowed."""
        ...


class ConfigurationGuard:
    """Keeps every command inside the allowed configurations; an input check and a limit in one object.

    As an :class:`~telerig.safety.InputCheck` it refuses a request whose configuration a check
    forbids: the chain then holds the last safe request (the request's goal velocity is dropped,
    so the output does not coast past it).

    As a :class:`~telerig.safety.Limit` (place it after the velocity limit) it looks ahead: the
    shaped output is accepted only if both it and the configuration where the robot would come to
    rest when braking from it at the acceleration limit are allowed. Otherwise the output brakes at
    that acceleration from the previous tick, towards the rest point verified on the previous tick.
    So the output never enters a forbidden configuration at any tick, and never jumps. The
    braking path between the verified end points is not checked (joints brake independently).

    A robot that starts inside a forbidden configuration may only move so that it does not go
    deeper (and only to requests that are themselves allowed).
    """

    __slots__ = (
        "_a",
        "_brake_events",
        "_for",
        "_has_last",
        "_last_out",
        "_prev_depth",
        "_stop",
        "acceleration_fraction",
        "checks",
    )

    def __init__(self, checks: Sequence[ConfigurationCheck], *, acceleration_fraction: float = 1.0) -> None:
        """Args:
        checks: Configuration checks, evaluated in order (all of them, for the deepest violation).
        acceleration_fraction: Share of the rated accelerations used for braking, in (0, 1]; use
            the same as the chain's :class:`~telerig.safety.AccelerationLimit`.
        """
        if not checks:
            raise ConfigError("a configuration guard needs at least one check")
        if not (math.isfinite(acceleration_fraction) and 0.0 < acceleration_fraction <= 1.0):
            raise ConfigError(f"acceleration fraction must be in (0, 1], got {acceleration_fraction}")
        self.checks: tuple[ConfigurationCheck, ...] = tuple(checks)
        self.acceleration_fraction = float(acceleration_fraction)
        self._for: JointLimits | None = None
        self._a: FloatArray = np.zeros(0)
        self._stop: FloatArray = np.zeros(0)
        self._last_out: FloatArray = np.zeros(0)
        self._has_last = False
        self._prev_depth = 0.0

    def worst(self, q: FloatArray) -> Violation | None:
        """The deepest violation of any check at joint positions ``q`` [rad], or ``None``."""
        worst: Violation | None = None
        for check in self.checks:
            v = check.violation(q)
            if v is not None and (worst is None or v.depth_m > worst.depth_m):
                worst = v
        return worst

    def check(self, command: JointCommand, limits: JointLimits) -> SafetyEvent | None:
        """Refuse ``command`` if its configuration is forbidden."""
        v = self.worst(command.positions)
        if v is None:
            return None
        return SafetyEvent(
            v.code, f"{v.reason}; request refused, holding the last safe command", v.suggested_action
        )

    def stop_point(self, tick: Tick, out: FloatArray) -> FloatArray:
        """Where the robot comes to rest braking at the acceleration limit from ``tick.target`` [rad].

        Discrete braking from velocity ``v = (target - previous) / dt``: the speed drops by
        ``a * dt`` per tick, so the rest point is ``target + sign(v) dt (n s - a dt n (n + 1) / 2)``
        with ``s = |v|`` and ``n = floor(s / (a dt))``. Writes into ``out`` (shape (n,)).
        """
        dt = tick.dt_s
        adt = self._a * dt
        v = np.subtract(tick.target, tick.previous, out=tick.work)
        v *= 1.0 / dt
        s = np.abs(v, out=tick.bound)
        n = np.floor(s / adt)
        dist = dt * (n * s - adt * n * (n + 1.0) * 0.5)
        np.multiply(np.sign(v), dist, out=out)
        out += tick.target
        return out

    def apply(self, tick: Tick) -> SafetyEvent | None:
        """Accept ``tick.target`` if it and its rest point are allowed, else brake to the last safe one."""
        dt = tick.dt_s
        if dt <= 0.0:
            return None
        if self._for is not tick.limits:
            self._for = tick.limits
            self._a = tick.limits.acceleration * self.acceleration_fraction
            n = len(tick.limits.names)
            self._stop = np.zeros(n)
            self._last_out = np.zeros(n)
            self._has_last = False
        if not (self._has_last and np.array_equal(tick.previous, self._last_out)):
            # The chain (re)started from the measured state: judge where the robot is now.
            here = self.worst(tick.previous)
            self._prev_depth = 0.0 if here is None else here.depth_m
            self._has_last = True
        stop = self.stop_point(tick, self._stop)
        v_stop = self.worst(stop)
        v_target = v_stop if np.array_equal(stop, tick.target) else self.worst(tick.target)
        depth = max(0.0 if v is None else v.depth_m for v in (v_stop, v_target))
        if depth == 0.0 or depth <= self._prev_depth:
            self._prev_depth = depth
            self._last_out[:] = tick.target
            return None
        # Brake: the speed drops by a * dt per joint, towards the rest point verified last tick.
        violation = v_target if v_target is not None else v_stop
        assert violation is not None
        pv = tick.previous_velocity
        s = np.abs(pv, out=tick.work)
        s -= self._a * dt
        np.maximum(s, 0.0, out=s)
        s *= np.sign(pv)
        s *= dt
        np.add(tick.previous, s, out=tick.target)
        self._last_out[:] = tick.target
        return SafetyEvent(
            violation.code,
            f"{violation.reason}; braking to a safe stop",
            violation.suggested_action,
        )
