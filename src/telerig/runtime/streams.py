"""Stream names: which bus stream a sample of a device or robot travels on."""

from __future__ import annotations

from telerig.ir.types import (
    BaseVelocity,
    BodySkeleton,
    ControllerState,
    HandPose,
    Pose,
    Sample,
    Twist,
)

__all__ = [
    "CAMERA_FRAMES",
    "GRIPPER_REQUESTED",
    "GRIPPER_SENT",
    "JOINT_REQUESTED",
    "JOINT_SENT",
    "JOINT_STATE",
    "SESSION",
    "STATUS",
    "device_stream",
]

JOINT_REQUESTED = "joint_command_requested"
JOINT_SENT = "joint_command_sent"
GRIPPER_REQUESTED = "gripper_command_requested"
GRIPPER_SENT = "gripper_command_sent"
JOINT_STATE = "joint_state"
CAMERA_FRAMES = "frames"
STATUS = "status"
SESSION = "session"


def device_stream(sample: Sample) -> str:
    """The device part a sample belongs to, used as its stream name (e.g. ``right_controller``)."""
    match sample:
        case ControllerState():
            return f"{sample.hand}_controller"
        case HandPose():
            return f"{sample.handedness}_hand"
        case BodySkeleton():
            return "body"
        case Pose():
            return "pose"
        case Twist():
            return "twist"
        case BaseVelocity():
            return "base"
        case _:
            raise ValueError(f"{type(sample).__name__} is not a device sample")
