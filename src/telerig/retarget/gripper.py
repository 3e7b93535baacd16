"""Parallel gripper retargeting: controller trigger or grip → gripper opening."""

from __future__ import annotations

import math
from typing import Literal

from telerig.ir.types import ControllerState, GripperCommand

__all__ = ["TriggerGripper"]


class TriggerGripper:
    """Pressed closes: ``opening = 1 - value`` for the trigger or grip axis in [0, 1]."""

    __slots__ = ("source",)

    def __init__(self, source: Literal["trigger", "grip"] = "trigger") -> None:
        self.source = source

    def __call__(self, sample: ControllerState) -> GripperCommand | None:
        """Opening for ``sample``; ``None`` for a non-finite value (the gripper keeps its last command,
        so a glitch can neither drop a held object nor squeeze)."""
        value = sample.trigger if self.source == "trigger" else sample.grip
        if not math.isfinite(value):
            return None
        return GripperCommand(sample.stamp, opening=1.0 - min(1.0, max(0.0, value)))
