"""Stream names: which bus stream a sample of a device or robot travels on."""

from __future__ import annotations

import re

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
    "BASE_REQUESTED",
    "BASE_SENT",
    "CAMERA_FRAMES",
    "GRIPPER_REQUESTED",
    "GRIPPER_SENT",
    "JOINT_REQUESTED",
    "JOINT_SENT",
    "JOINT_STATE",
    "PREVIEW",
    "RESIDUAL",
    "SESSION",
    "STATUS",
    "device_stream",
]

_UNSAFE = re.compile(r"[^A-Za-z0-9_.\-]")

JOINT_REQUESTED = "joint_command_requested"
JOINT_SENT = "joint_command_sent"
GRIPPER_REQUESTED = "gripper_command_requested"
GRIPPER_SENT = "gripper_command_sent"
JOINT_STATE = "joint_state"
BASE_REQUESTED = "base_command_requested"
BASE_SENT = "base_command_sent"
#: Per-tick retargeting residual of a robot (JSON): ``capture_ns``, ``flagged`` and per-task errors.
RESIDUAL = "residual"
CAMERA_FRAMES = "frames"
PREVIEW = "preview"
STATUS = "status"
SESSION = "session"


def device_stream(sample: Sample) -> str:
    """The device part a sample belongs to, used as its stream name and bound by rig ``part``.

    Controllers and hands are named by side (``right_controller``, ``left_hand``); poses,
    skeletons and twists by the part of their source id after the device id (``quest/head`` →
    ``head``, ``mocap/wand`` → ``wand``), so one device can stream several rigid bodies.
    """
    match sample:
        case ControllerState():
            return f"{sample.hand}_controller"
        case HandPose():
            return f"{sample.handedness}_hand"
        case BodySkeleton():
            return _suffix(sample.stamp.source_id, "body")
        case Pose():
            return _suffix(sample.stamp.source_id, "pose")
        case Twist():
            return _suffix(sample.stamp.source_id, "twist")
        case BaseVelocity():
            return "base"
        case _:
            raise ValueError(f"{type(sample).__name__} is not a device sample")


def _suffix(source_id: str, default: str) -> str:
    _, sep, part = source_id.partition("/")
    # Topic levels allow letters, digits, '_', '-', '.': a rigid body named "Rigid Body 1" → Rigid_Body_1.
    return _UNSAFE.sub("_", part) if sep and part else default
