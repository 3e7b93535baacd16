"""Configs of the built-in retargeters (registered by ``type``)."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field

from telerig.config.schema import AlignmentConfig, RetargeterConfig
from telerig.registry import RETARGETERS

__all__ = ["AbsolutePoseConfig", "TriggerGripperConfig"]


@RETARGETERS.register
class AbsolutePoseConfig(RetargeterConfig):
    """Absolute alignment: the operator's hand pose, mapped into the robot base frame, is the EE target."""

    type: Literal["absolute_pose"] = "absolute_pose"
    alignment: AlignmentConfig = Field(default_factory=AlignmentConfig)
    residual_threshold_m: Annotated[float, Field(gt=0, le=1)] = 0.05
    #: QP sub-steps per control tick; 1 tracks smooth 100 Hz input to 0.01 mm (benchmarks/arm_ik.py).
    ik_substeps: Annotated[int, Field(ge=1, le=20)] = 1


@RETARGETERS.register
class TriggerGripperConfig(RetargeterConfig):
    """Controller trigger (or grip) → gripper opening: pressed closes."""

    type: Literal["trigger_gripper"] = "trigger_gripper"
    source: Literal["trigger", "grip"] = "trigger"
