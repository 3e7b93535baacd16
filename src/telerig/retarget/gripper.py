"""Parallel gripper retargeting: controller trigger or grip, or a hand's pinch distance → gripper opening."""

from __future__ import annotations

import math
from typing import Literal

import numpy as np

from telerig.ir.types import ControllerState, GripperCommand, HandPose, Sample

__all__ = ["PinchGripper", "TriggerGripper"]


class TriggerGripper:
    """Pressed closes: ``opening = 1 - value`` for the trigger or grip axis in [0, 1]."""

    __slots__ = ("source",)

    def __init__(self, source: Literal["trigger", "grip"] = "trigger") -> None:
        self.source = source

    def __call__(self, sample: Sample) -> GripperCommand | None:
        """Opening for ``sample``; ``None`` for a non-finite value (the gripper keeps its last command,
        so a glitch can neither drop a held object nor squeeze) or a sample that is not a controller."""
        if not isinstance(sample, ControllerState):
            return None
        value = sample.trigger if self.source == "trigger" else sample.grip
        if not math.isfinite(value):
            return None
        return GripperCommand(sample.stamp, opening=1.0 - min(1.0, max(0.0, value)))


class PinchGripper:
    """Thumb tip to index tip distance → opening: pinched closes, spread opens.

    Args:
        closed_at_m: Pinch distance [m] at and below which the gripper is fully closed.
        open_at_m: Pinch distance [m] at and above which it is fully open.
    """

    __slots__ = ("closed_at_m", "open_at_m")

    #: MediaPipe keypoint indices of the thumb tip and the index fingertip.
    THUMB_TIP = 4
    INDEX_TIP = 8

    def __init__(self, closed_at_m: float = 0.02, open_at_m: float = 0.08) -> None:
        if not 0 <= closed_at_m < open_at_m:
            raise ValueError(f"need 0 <= closed_at_m < open_at_m, got {closed_at_m} and {open_at_m}")
        self.closed_at_m = closed_at_m
        self.open_at_m = open_at_m

    def __call__(self, sample: Sample) -> GripperCommand | None:
        """Opening for a :class:`HandPose`; ``None`` for other samples or non-finite keypoints."""
        if not isinstance(sample, HandPose):
            return None
        d = float(np.linalg.norm(sample.keypoints[self.THUMB_TIP] - sample.keypoints[self.INDEX_TIP]))
        if not math.isfinite(d):
            return None
        u = (d - self.closed_at_m) / (self.open_at_m - self.closed_at_m)
        return GripperCommand(sample.stamp, opening=min(1.0, max(0.0, u)))
