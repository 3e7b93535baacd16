"""Safety stages of a robot's other parts: the gripper and the wheeled base.

The joint chain (:class:`~telerig.safety.SafetyChain`) guards the arm; these guard the commands
that go to the gripper and the base, one method each, and :class:`~telerig.safety.RobotSafety`
runs them (and refuses both while the robot is e-stopped) before any driver call.
"""

from __future__ import annotations

import math

from telerig.config.safety import BaseSafetyConfig, GripperSafetyConfig
from telerig.errors import ConfigError
from telerig.ir.types import BaseVelocity, GripperCommand
from telerig.safety.filters import SafetyEvent

__all__ = ["BaseLimit", "GripperLimit"]


def _positive(name: str, value: float) -> float:
    if not (math.isfinite(value) and value > 0.0):
        raise ConfigError(f"{name} must be a finite value > 0, got {value}")
    return float(value)


class GripperLimit:
    """Keeps gripper commands valid: rejects non-finite values, clamps the opening and the force.

    The opening is clamped to [0, 1] (closed to open, every gripper's normalized range) and the
    force to [0, ``max_force_n``]. A rejected command is never sent: the gripper keeps its last
    opening, so a glitch can neither drop a held object nor squeeze.
    """

    __slots__ = ("max_force_n",)

    def __init__(self, max_force_n: float | None = None) -> None:
        """Args:
        max_force_n: Grip force cap [N] (> 0); ``None`` leaves the force to the gripper's rating.
        """
        self.max_force_n = None if max_force_n is None else _positive("gripper max_force_n", max_force_n)

    @classmethod
    def from_config(cls, config: GripperSafetyConfig) -> GripperLimit:
        """The limit a rig's ``safety.robots.<id>.gripper`` settings describe."""
        return cls(config.max_force_n)

    def apply(self, command: GripperCommand) -> GripperCommand | SafetyEvent:
        """The command to send (``command`` itself when within the limits), or the event rejecting it."""
        opening, force = command.opening, command.max_force
        if not (math.isfinite(opening) and math.isfinite(force)):
            return SafetyEvent(
                "invalid_input",
                f"non-finite gripper command (opening {opening}, max_force {force} N); not sent",
                "check the gripper retargeting and the input device's samples",
            )
        cap = self.max_force_n
        if 0.0 <= opening <= 1.0 and force >= 0.0 and (cap is None or force <= cap):
            return command
        opening = min(1.0, max(0.0, opening))
        force = max(0.0, force) if cap is None else min(cap, max(0.0, force))
        return GripperCommand(command.stamp, opening, force)


class BaseLimit:
    """Limits a wheeled base's velocity and its change; a non-finite command stops the base.

    Speed: the planar speed ``|(vx, vy)|`` is scaled down to ``max_linear_m_s`` (direction kept),
    ``|wz|`` clamped to ``max_angular_rad_s``. Acceleration: the planar velocity changes by at most
    ``max_linear_accel_m_s2 * dt`` from the last command this limit passed, ``wz`` by at most
    ``max_angular_accel_rad_s2 * dt``, with ``dt`` the time since that command bounded to
    ``max_dt_s`` (a command after a pause is no bigger step). A stop (all zero) passes at once:
    stopping never waits on a ramp. A NaN or infinite command is replaced by a stop, because a base
    that keeps its last velocity is not holding still.

    Call from one thread (the robot's control loop).
    """

    __slots__ = (
        "_invalid_action",
        "_last_ns",
        "_sent",
        "_too_fast",
        "_too_sudden",
        "max_angular_accel_rad_s2",
        "max_angular_rad_s",
        "max_dt_s",
        "max_linear_accel_m_s2",
        "max_linear_m_s",
    )

    def __init__(
        self,
        max_linear_m_s: float = 1.0,
        max_angular_rad_s: float = 2.0,
        max_linear_accel_m_s2: float = 2.0,
        max_angular_accel_rad_s2: float = 4.0,
        *,
        max_dt_s: float = 0.1,
    ) -> None:
        """Args:
        max_linear_m_s: Planar speed limit [m/s] (> 0).
        max_angular_rad_s: Yaw rate limit [rad/s] (> 0).
        max_linear_accel_m_s2: Planar acceleration limit [m/s^2] (> 0).
        max_angular_accel_rad_s2: Yaw acceleration limit [rad/s^2] (> 0).
        max_dt_s: Longest time between commands the acceleration limit credits [s] (> 0).
        """
        self.max_linear_m_s = _positive("base max_linear_m_s", max_linear_m_s)
        self.max_angular_rad_s = _positive("base max_angular_rad_s", max_angular_rad_s)
        self.max_linear_accel_m_s2 = _positive("base max_linear_accel_m_s2", max_linear_accel_m_s2)
        self.max_angular_accel_rad_s2 = _positive("base max_angular_accel_rad_s2", max_angular_accel_rad_s2)
        self.max_dt_s = _positive("base max_dt_s", max_dt_s)
        self._sent = (0.0, 0.0, 0.0)
        self._last_ns: int | None = None
        self._too_fast = SafetyEvent(
            "velocity_limit", "base speed limited", "none needed; drive more slowly to track exactly"
        )
        self._too_sudden = SafetyEvent(
            "acceleration_limit",
            "base acceleration limited",
            "none needed; accelerate more gently to track exactly",
        )
        self._invalid_action = "check the base retargeting and the input device's samples"

    @classmethod
    def from_config(cls, config: BaseSafetyConfig) -> BaseLimit:
        """The limit a rig's ``safety.robots.<id>.base`` settings describe."""
        return cls(
            config.max_linear_m_s,
            config.max_angular_rad_s,
            config.max_linear_accel_m_s2,
            config.max_angular_accel_rad_s2,
        )

    def apply(self, command: BaseVelocity, now_ns: int) -> tuple[BaseVelocity, SafetyEvent | None]:
        """The command to send at ``now_ns`` [ns] (``command`` itself when within the limits) and the
        event saying what was limited or rejected, if anything."""
        vx, vy, wz = command.vx, command.vy, command.wz
        last_ns, self._last_ns = self._last_ns, now_ns
        if not (math.isfinite(vx) and math.isfinite(vy) and math.isfinite(wz)):
            self._sent = (0.0, 0.0, 0.0)
            invalid = SafetyEvent(
                "invalid_input",
                f"non-finite base command (vx {vx}, vy {vy}, wz {wz}); stopping the base",
                self._invalid_action,
            )
            return BaseVelocity(command.stamp, 0.0, 0.0, 0.0), invalid
        if vx == 0.0 and vy == 0.0 and wz == 0.0:
            self._sent = (0.0, 0.0, 0.0)
            return command, None
        event: SafetyEvent | None = None
        speed = math.hypot(vx, vy)
        if speed > self.max_linear_m_s or abs(wz) > self.max_angular_rad_s:
            event = self._too_fast
            if speed > self.max_linear_m_s:
                scale = self.max_linear_m_s / speed
                vx, vy = vx * scale, vy * scale
            wz = min(self.max_angular_rad_s, max(-self.max_angular_rad_s, wz))
        dt = self.max_dt_s if last_ns is None else min(self.max_dt_s, max(0.0, (now_ns - last_ns) * 1e-9))
        px, py, pw = self._sent
        dvx, dvy, dwz = vx - px, vy - py, wz - pw
        step = math.hypot(dvx, dvy)
        dv_max, dw_max = self.max_linear_accel_m_s2 * dt, self.max_angular_accel_rad_s2 * dt
        if step > dv_max or abs(dwz) > dw_max:
            event = self._too_sudden
            if step > dv_max:
                scale = dv_max / step
                vx, vy = px + dvx * scale, py + dvy * scale
            wz = pw + min(dw_max, max(-dw_max, dwz))
        self._sent = (vx, vy, wz)
        if event is None:
            return command, None
        return BaseVelocity(command.stamp, vx, vy, wz), event
