"""The Unitree G1 joints telerig drives through ``arm_sdk``: names, motor slots and position limits."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["G1_UPPER_BODY", "G1_UPPER_BODY_NAMES", "G1Joint"]


@dataclass(frozen=True, slots=True)
class G1Joint:
    """A joint's URDF name, its motor slot in ``unitree_hg`` messages and its limits [rad]."""

    name: str
    motor: int
    lower: float
    upper: float


#: The G1 (29 DoF) joints arm_sdk drives: motor index and position limits [rad], from Unitree's
#: g1_29dof_rev_1_0 URDF (example-robot-data ships it; a test checks this table against it).
G1_UPPER_BODY: tuple[G1Joint, ...] = (
    G1Joint("waist_yaw_joint", 12, -2.618, 2.618),
    G1Joint("waist_roll_joint", 13, -0.52, 0.52),
    G1Joint("waist_pitch_joint", 14, -0.52, 0.52),
    G1Joint("left_shoulder_pitch_joint", 15, -3.0892, 2.6704),
    G1Joint("left_shoulder_roll_joint", 16, -1.5882, 2.2515),
    G1Joint("left_shoulder_yaw_joint", 17, -2.618, 2.618),
    G1Joint("left_elbow_joint", 18, -1.0472, 2.0944),
    G1Joint("left_wrist_roll_joint", 19, -1.972222054, 1.972222054),
    G1Joint("left_wrist_pitch_joint", 20, -1.614429558, 1.614429558),
    G1Joint("left_wrist_yaw_joint", 21, -1.614429558, 1.614429558),
    G1Joint("right_shoulder_pitch_joint", 22, -3.0892, 2.6704),
    G1Joint("right_shoulder_roll_joint", 23, -2.2515, 1.5882),
    G1Joint("right_shoulder_yaw_joint", 24, -2.618, 2.618),
    G1Joint("right_elbow_joint", 25, -1.0472, 2.0944),
    G1Joint("right_wrist_roll_joint", 26, -1.972222054, 1.972222054),
    G1Joint("right_wrist_pitch_joint", 27, -1.614429558, 1.614429558),
    G1Joint("right_wrist_yaw_joint", 28, -1.614429558, 1.614429558),
)
#: The arm_sdk joint names in motor order (waist, left arm, right arm): a config's default.
G1_UPPER_BODY_NAMES: tuple[str, ...] = tuple(j.name for j in G1_UPPER_BODY)
