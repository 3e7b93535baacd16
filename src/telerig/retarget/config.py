"""Configs of the built-in retargeters (registered by ``type``)."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, model_validator

from telerig.config.schema import AlignmentConfig, RetargeterConfig
from telerig.registry import RETARGETERS

__all__ = ["AbsolutePoseConfig", "PinchGripperConfig", "TriggerGripperConfig"]


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


@RETARGETERS.register
class PinchGripperConfig(RetargeterConfig):
    """A tracked hand's thumb-index pinch distance → gripper opening (glove, camera, XR hands)."""

    type: Literal["pinch_gripper"] = "pinch_gripper"
    closed_at_m: Annotated[float, Field(ge=0, le=0.2)] = 0.02
    open_at_m: Annotated[float, Field(gt=0, le=0.3)] = 0.08

    @model_validator(mode="after")
    def _ordered(self) -> PinchGripperConfig:
        if self.closed_at_m >= self.open_at_m:
            raise ValueError(f"closed_at_m ({self.closed_at_m}) must be below open_at_m ({self.open_at_m})")
        return self
