"""Configs of the joint-space retargeters (registered by ``type``)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, ClassVar, Literal

from pydantic import Field

from telerig.config.schema import RetargeterConfig
from telerig.registry import RETARGETERS

if TYPE_CHECKING:
    from telerig.retarget.binding import BindContext, Bound

__all__ = ["JointGripperConfig", "JointPassthroughConfig"]


@RETARGETERS.register
class JointPassthroughConfig(RetargeterConfig):
    """Joint targets by name (a ``policy`` device's ``joints``) → the robot's arm joints.

    ``blend_s``: after a reset (homing, resume, a handover to this source) the targets are blended
    in from the commanded pose over this time [s], on top of the safety chain's start-up ramp.
    """

    type: Literal["joint_passthrough"] = "joint_passthrough"
    targets: ClassVar[tuple[str, ...]] = ("arm",)
    blend_s: Annotated[float, Field(ge=0, le=10)] = 0.5

    def bind(self, context: BindContext) -> Bound:
        from telerig.retarget.binding import Bound
        from telerig.retarget.joints.passthrough import JointPassthrough

        context.require_target(self.type, *self.targets)
        robot = context.robot
        return Bound(joints=JointPassthrough(context.robot_id, robot.joint_names, blend_s=self.blend_s))


@RETARGETERS.register
class JointGripperConfig(RetargeterConfig):
    """The ``gripper`` entry of a joint-space sample (a policy's action) → the gripper opening."""

    type: Literal["joint_gripper"] = "joint_gripper"
    targets: ClassVar[tuple[str, ...]] = ("gripper",)

    def bind(self, context: BindContext) -> Bound:
        from telerig.retarget.binding import Bound
        from telerig.retarget.joints.passthrough import JointGripper

        context.require_target(self.type, *self.targets)
        return Bound(gripper=JointGripper())
