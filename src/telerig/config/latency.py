"""Latency budgets of a rig file (``latency:``): per stage of the operator loop, what the view shows green.

Data only. The control node measures the robot stages per applied command, the control center the
browser and video stages (:mod:`telerig.runtime.control_health`, :mod:`telerig.server.view_latency`);
each stage's p99 over the rolling window is compared with its budget here, and a stage over budget
raises its alert (``latency_budget``). The stages follow one input sample, each ending where its
name says:

==================  ==========================================================================
stage               from → to (each stamp in the rig's common clock)
==================  ==========================================================================
``receive``         the device's capture → telerig has it (the device node stamps ``arrival_ns``)
``bus``             → the control node's MQTT client received it (through the broker)
``queue``           → the control tick that uses it started
``retarget``        → the retargeter returned the joint targets
``apply``           → the driver applied the command (safety chain + driver; its stamp)
``state``           → the first measured joint state at or after it (the driver's stamp)
``rendered``        → the operator's browser drew that state (the page reports it)
``end_to_end``      capture → state (the sum of the robot stages)
``video_encode``    a camera frame's capture → its preview JPEG encoded
``video_deliver``   → the control center received it (over the bus)
``video_display``   → the operator's browser drew it (the page reports it)
==================  ==========================================================================
"""

from __future__ import annotations

import typing
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field

__all__ = [
    "DEFAULT_BUDGETS_MS",
    "ROBOT_STAGES",
    "STAGES",
    "VIDEO_STAGES",
    "LatencyConfig",
    "StageName",
]

StageName = Literal[
    "receive",
    "bus",
    "queue",
    "retarget",
    "apply",
    "state",
    "rendered",
    "end_to_end",
    "video_encode",
    "video_deliver",
    "video_display",
]
STAGES: tuple[StageName, ...] = typing.get_args(StageName)
#: The stages the control node measures, in order: consecutive stamps of one applied command.
ROBOT_STAGES: tuple[StageName, ...] = ("receive", "bus", "queue", "retarget", "apply", "state")
#: A camera's live-view stages, in order.
VIDEO_STAGES: tuple[StageName, ...] = ("video_encode", "video_deliver", "video_display")

#: p99 budgets [ms] when the rig file gives none. The robot stages add up to ``end_to_end``'s 50 ms:
#: the demo rig measures p99 ~2 ms capture-to-command and ~12 ms to the next state on this 2-core
#: host (README, latency.py), so 50 ms leaves room for a real tracker and a loaded station while
#: staying well under the 100 ms the safety chain holds at. A display at 60 Hz draws every 16.7 ms,
#: so ``rendered`` allows three frames; video previews come at ~2 Hz and are judged looser.
DEFAULT_BUDGETS_MS: dict[StageName, float] = {
    "receive": 10.0,
    "bus": 5.0,
    "queue": 5.0,
    "retarget": 5.0,
    "apply": 5.0,
    "state": 20.0,
    "rendered": 50.0,
    "end_to_end": 50.0,
    "video_encode": 50.0,
    "video_deliver": 20.0,
    "video_display": 100.0,
}

_Budget = Annotated[float, Field(gt=0, le=60_000, allow_inf_nan=False)]


class LatencyConfig(BaseModel):
    """``latency:`` of a rig file.

    Attributes:
        budgets_ms: p99 budget [ms] per stage (see the module docs); stages not named keep
            :data:`DEFAULT_BUDGETS_MS`. A finite number in (0, 60000].
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    budgets_ms: dict[StageName, _Budget] = Field(default_factory=dict)

    def budget_ms(self, stage: StageName) -> float:
        """The p99 budget of ``stage`` [ms]: the rig's, else the default."""
        return self.budgets_ms.get(stage, DEFAULT_BUDGETS_MS[stage])

    def budgets(self) -> dict[StageName, float]:
        """Every stage's budget [ms]."""
        return {stage: self.budget_ms(stage) for stage in STAGES}
