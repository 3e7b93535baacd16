"""Stream names of devices, robots and cameras; they live in the catalogue, :mod:`telerig.bus.catalogue`."""

from telerig.bus.catalogue import (
    BASE_REQUESTED,
    BASE_SENT,
    CAMERA_FRAMES,
    GRIPPER_REQUESTED,
    GRIPPER_SENT,
    JOINT_REQUESTED,
    JOINT_SENT,
    JOINT_STATE,
    PREVIEW,
    RESIDUAL,
    SESSION,
    STATUS,
    device_stream,
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
