"""Controller mode for a wheeled base: buttons drive forward/backward, the thumbstick turns."""

from __future__ import annotations

import math

from telerig.ir.types import BaseVelocity, ControllerState, Sample, Stamp
from telerig.retarget.clutch import button_held

__all__ = ["BaseDrive"]


class BaseDrive:
    """Controller sample → planar base velocity, limited to the configured speeds.

    ``vx = max_linear_m_s`` while ``forward_button`` is held, ``-max_linear_m_s`` while
    ``backward_button`` is (both: 0); ``wz = -turn * max_angular_rad_s`` with ``turn`` the thumbstick
    x (right positive) after the dead zone, rescaled to [-1, 1]: pushing right turns clockwise.
    ``vy`` is always 0 (differential drive semantics; holonomic bases simply do not strafe).

    Args:
        forward_button: Button that drives forward (see :func:`~telerig.retarget.clutch.button_held`).
        backward_button: Button that drives backward.
        max_linear_m_s: Forward/backward speed [m/s], > 0.
        max_angular_rad_s: Yaw rate at full stick [rad/s], > 0.
        deadzone: Thumbstick magnitude below which it reads 0, in [0, 1).
        input_timeout_s: Input older than this [s] zeroes the command (see :meth:`expired`).
    """

    __slots__ = (
        "_seq",
        "backward_button",
        "deadzone",
        "forward_button",
        "input_timeout_s",
        "max_angular_rad_s",
        "max_linear_m_s",
        "source_id",
    )

    def __init__(
        self,
        *,
        forward_button: str,
        backward_button: str,
        max_linear_m_s: float = 0.3,
        max_angular_rad_s: float = 0.8,
        deadzone: float = 0.15,
        input_timeout_s: float = 0.25,
        source_id: str = "base_drive",
    ) -> None:
        if forward_button == backward_button:
            raise ValueError(f"forward_button and backward_button must differ, both are {forward_button!r}")
        for name, value in (
            ("max_linear_m_s", max_linear_m_s),
            ("max_angular_rad_s", max_angular_rad_s),
            ("input_timeout_s", input_timeout_s),
        ):
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be > 0, got {value}")
        if not 0.0 <= deadzone < 1.0:
            raise ValueError(f"deadzone must be in [0, 1), got {deadzone}")
        self.forward_button = forward_button
        self.backward_button = backward_button
        self.max_linear_m_s = float(max_linear_m_s)
        self.max_angular_rad_s = float(max_angular_rad_s)
        self.deadzone = float(deadzone)
        self.input_timeout_s = float(input_timeout_s)
        self.source_id = source_id
        self._seq = 0

    def __call__(self, sample: Sample) -> BaseVelocity | None:
        """The base command for a controller sample (its stamp); ``None`` for other samples."""
        if not isinstance(sample, ControllerState):
            return None
        stick = float(sample.joystick[0])
        forward = button_held(sample, self.forward_button)
        backward = button_held(sample, self.backward_button)
        vx = self.max_linear_m_s * (int(forward) - int(backward))
        turn = 0.0
        if math.isfinite(stick) and abs(stick) > self.deadzone:
            turn = math.copysign(min(1.0, (abs(stick) - self.deadzone) / (1.0 - self.deadzone)), stick)
        return BaseVelocity(sample.stamp, vx=float(vx), vy=0.0, wz=-turn * self.max_angular_rad_s)

    def stop(self, now_ns: int) -> BaseVelocity:
        """A zero command stamped now (input lost, e-stop, homing, shutdown)."""
        self._seq += 1
        return BaseVelocity(Stamp(self.source_id, self._seq, now_ns, now_ns), 0.0, 0.0, 0.0)

    def expired(self, last_input_ns: int, now_ns: int) -> bool:
        """Whether input last seen at ``last_input_ns`` [ns] is too old to keep driving at ``now_ns``."""
        return now_ns - last_input_ns > self.input_timeout_s * 1e9
