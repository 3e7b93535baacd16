"""Clutch for relative teleoperation: the arm follows the hand only while a button is held."""

from __future__ import annotations

from typing import Literal

from telerig.ir.types import ControllerState, Sample

__all__ = ["ANALOG_BUTTONS", "Clutch", "ClutchEvent", "button_held"]

#: What one sample did to the clutch.
ClutchEvent = Literal["press", "hold", "release", "idle"]

#: Button names that also read the controller's analog axis (pressed at >= 0.5), because some
#: device families (udp_vr) report trigger and grip only as axes while others (webxr) also as buttons.
ANALOG_BUTTONS = frozenset({"trigger", "grip"})


def button_held(sample: Sample, button: str) -> bool:
    """Whether ``button`` is held in ``sample``; ``trigger``/``grip`` also count when their axis >= 0.5.

    Button names are the device family's (``ControllerState.buttons``): udp_vr ``a b x y thumbstick
    menu``; webxr ``trigger grip touchpad thumbstick a b`` (left: ``x y``); gamepad ``a b x y rb rt
    r3 start mode`` (left: ``lb lt l3 select dpad_*``); keyboard ``mode<N>`` and its ``button:`` keys;
    spacemouse its configured ``button_names``. Samples other than controllers hold no button.
    """
    if not isinstance(sample, ControllerState):
        return False
    if button in sample.buttons:
        return True
    if button == "trigger":
        return sample.trigger >= 0.5
    if button == "grip":
        return sample.grip >= 0.5
    return False


class Clutch:
    """Edge detector on one button: ``press`` on the sample where it goes down, ``release`` where it goes up.

    Args:
        button: Button name (see :func:`button_held`).
    """

    __slots__ = ("_held", "button")

    def __init__(self, button: str) -> None:
        if not button:
            raise ValueError("clutch button must be a non-empty button name, e.g. 'grip' or 'a'")
        self.button = button
        self._held = False

    @property
    def engaged(self) -> bool:
        """Whether the clutch was held in the last sample."""
        return self._held

    def update(self, sample: Sample) -> ClutchEvent:
        """Advance with one sample and say what changed."""
        held = button_held(sample, self.button)
        was = self._held
        self._held = held
        if held:
            return "hold" if was else "press"
        return "release" if was else "idle"

    def reset(self) -> None:
        """Disengage; the next held sample is a ``press`` again (re-anchors)."""
        self._held = False
