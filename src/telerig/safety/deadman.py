"""Deadman (enable) switch: requests reach the robot only while the operator holds a button."""

from __future__ import annotations

import math
import threading

from telerig.errors import ConfigError

__all__ = ["Deadman"]


class Deadman:
    """An enable switch fed by the control node; the :class:`~telerig.safety.SafetyChain` reads it.

    The control node calls :meth:`update` with the button's state from every sample of the
    device stream that carries it (e.g. ``"grip" in ControllerState.buttons``). The switch is
    *enabled* only while the last update said "held" and is younger than ``signal_timeout_s``,
    so a device that goes silent with the button held counts as released.

    While released, the chain drops every request: it holds the last valid command, reports
    ``input_stale`` after its hold timeout and stops the robot (commands the measured position)
    after its stop timeout. Pressing again resumes tracking from where the arm is.

    Thread-safe: :meth:`update` may run on a bus thread while the control loop reads.
    """

    __slots__ = ("_held", "_lock", "_updated_ns", "signal_timeout_ns")

    def __init__(self, signal_timeout_s: float = 0.2) -> None:
        """Args:
        signal_timeout_s: Age of the last button report beyond which the switch counts as
            released [s] (> 0).
        """
        if not (math.isfinite(signal_timeout_s) and signal_timeout_s > 0.0):
            raise ConfigError(f"deadman signal_timeout_s must be > 0 s, got {signal_timeout_s}")
        self.signal_timeout_ns = round(signal_timeout_s * 1e9)
        self._lock = threading.Lock()
        self._held = False
        self._updated_ns = 0

    def update(self, held: bool, now_ns: int) -> None:
        """Report the button's state, observed at ``now_ns`` (common clock [ns])."""
        with self._lock:
            self._held = bool(held)
            self._updated_ns = now_ns

    def release(self) -> None:
        """Force the switch released (e.g. the device disconnected)."""
        with self._lock:
            self._held = False

    def enabled(self, now_ns: int) -> bool:
        """Whether requests may pass at ``now_ns`` [ns]: held and reported within the signal timeout."""
        with self._lock:
            return self._held and now_ns - self._updated_ns <= self.signal_timeout_ns
