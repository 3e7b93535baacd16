"""Config of the ``policy`` device: a trained checkpoint rolled out as an input device."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import Field, model_validator

from telerig.config.schema import DeviceConfig
from telerig.registry import DEVICES

if TYPE_CHECKING:
    from telerig.devices.base import Device

__all__ = ["PolicyConfig"]

_LOADER = r"^[A-Za-z_][\w.]*:[A-Za-z_]\w*$"
_Id = Annotated[str, Field(pattern=r"^[A-Za-z0-9_.\-]+$", min_length=1, max_length=64)]


@DEVICES.register
class PolicyConfig(DeviceConfig):
    """A policy checkpoint that drives a robot through the rig's bindings (issue 16).

    Bind its ``joints`` part to the robot's ``arm`` with the ``joint_passthrough`` retargeter; an
    operator bound to the same arm with a higher ``priority`` takes over (see
    :mod:`telerig.runtime.handover`). The cameras it reads need ``observation:`` set in the rig.

    Attributes:
        checkpoint: The checkpoint file (``telerig train --out``).
        robot: The robot whose measured ``joint_state`` / ``gripper_state`` the policy observes.
        cameras: Checkpoint camera key → rig camera id; a key not listed names the camera by its
            last dotted part (``observation.images.scene`` → ``scene``).
        rate_hz: Actions per second [Hz]; the checkpoint's fps when unset.
        deadline_ms: How long a tick waits for its action [ms]; 80 % of a period when unset. A later
            action is a missed sample: the safety chain holds, then stops.
        execute_actions: Actions of each predicted chunk sent before the next inference.
        temporal_ensemble: ACT's temporal ensembling, with this weight decay per tick (ACT: 0.01):
            infer every tick and send the weighted mean of the overlapping chunks' actions (smooth
            motion, a robot that can stand still). Needs ``execute_actions`` 1. Unset: off.
        max_frame_age_ms: Frames older than this do not count as the camera's view [ms].
        threads: torch threads of the inference process.
        loader: ``module:function`` that loads the checkpoint in the inference process (a plug-in
            point for other policy code; telerig's own runner by default).
        start_timeout_s: How long loading may take [s].
    """

    type: Literal["policy"] = "policy"
    checkpoint: Path
    robot: _Id
    cameras: dict[str, _Id] = Field(default_factory=dict)
    rate_hz: Annotated[float, Field(gt=0, le=1000)] | None = None
    deadline_ms: Annotated[float, Field(gt=0, le=10_000)] | None = None
    execute_actions: Annotated[int, Field(ge=1, le=1000)] = 1
    temporal_ensemble: Annotated[float, Field(gt=0, le=10)] | None = None
    max_frame_age_ms: Annotated[float, Field(gt=0, le=60_000)] = 500.0
    threads: Annotated[int, Field(ge=1, le=64)] = 1
    loader: Annotated[str, Field(pattern=_LOADER)] = "telerig.policy.runner:load_policy"
    start_timeout_s: Annotated[float, Field(gt=0, le=600)] = 120.0

    @model_validator(mode="after")
    def _one_way_to_act(self) -> PolicyConfig:
        if self.temporal_ensemble is not None and self.execute_actions != 1:
            raise ValueError(
                f"temporal_ensemble infers every tick: set execute_actions to 1 (got {self.execute_actions}) "
                "or drop the ensemble"
            )
        return self

    def build(self) -> Device:
        from telerig.devices.policy.device import PolicyDevice

        return PolicyDevice(
            self.id,
            str(self.checkpoint),
            robot=self.robot,
            cameras=self.cameras,
            rate_hz=self.rate_hz,
            deadline_ms=self.deadline_ms,
            execute_actions=self.execute_actions,
            temporal_ensemble=self.temporal_ensemble,
            max_frame_age_ms=self.max_frame_age_ms,
            loader=self.loader,
            threads=self.threads,
            start_timeout_s=self.start_timeout_s,
        )
