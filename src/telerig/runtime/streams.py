"""Stream names of devices, robots and cameras (from :mod:`telerig.bus.catalogue`), and a rig's nodes."""

from __future__ import annotations

from telerig.bus.catalogue import (
    BASE_POSE,
    BASE_REQUESTED,
    BASE_SENT,
    CAMERA_FRAMES,
    GRIPPER_REQUESTED,
    GRIPPER_SENT,
    GRIPPER_STATE,
    JOINT_REQUESTED,
    JOINT_SENT,
    JOINT_STATE,
    OBJECT_POSE,
    PREVIEW,
    RESIDUAL,
    SESSION,
    STATUS,
    TICK,
    WRENCH,
    RigNodes,
    device_stream,
)
from telerig.config.schema import RigConfig

__all__ = [
    "BASE_POSE",
    "BASE_REQUESTED",
    "BASE_SENT",
    "CAMERA_FRAMES",
    "GRIPPER_REQUESTED",
    "GRIPPER_SENT",
    "GRIPPER_STATE",
    "JOINT_REQUESTED",
    "JOINT_SENT",
    "JOINT_STATE",
    "OBJECT_POSE",
    "PREVIEW",
    "RESIDUAL",
    "SESSION",
    "STATUS",
    "TICK",
    "WRENCH",
    "device_stream",
    "rig_nodes",
]


def rig_nodes(config: RigConfig) -> RigNodes:
    """The rig's bus nodes by role (devices, robots, cameras, stations): who may publish which stream."""
    return RigNodes.of(
        devices=(d.id for d in config.devices),
        robots=(r.id for r in config.robots),
        cameras=(c.id for c in config.cameras),
        stations=(s.id for s in config.stations),
    )
