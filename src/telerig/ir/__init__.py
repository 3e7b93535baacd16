"""Intermediate representation: typed samples with capture timestamps, and their wire encoding."""

from telerig.ir.types import (
    HAND_KEYPOINTS,
    BaseVelocity,
    BodySkeleton,
    CameraFrame,
    ControllerState,
    ControlSource,
    GripperCommand,
    HandPose,
    JointCommand,
    JointState,
    Pose,
    Sample,
    Stamp,
    Twist,
    Wrench,
    now_ns,
)

__all__ = [
    "HAND_KEYPOINTS",
    "BaseVelocity",
    "BodySkeleton",
    "CameraFrame",
    "ControlSource",
    "ControllerState",
    "GripperCommand",
    "HandPose",
    "JointCommand",
    "JointState",
    "Pose",
    "Sample",
    "Stamp",
    "Twist",
    "Wrench",
    "now_ns",
]
