"""Arm retargeting in absolute alignment: operator hand pose → robot base frame → IK → joint targets."""

from __future__ import annotations

from telerig.ir.types import ControllerState, FloatArray, JointCommand, Pose
from telerig.retarget.alignment import Alignment
from telerig.retarget.arm_ik import ArmIK, IKResult

__all__ = ["AbsolutePoseRetargeter"]


class AbsolutePoseRetargeter:
    """ "Where your hand is, the end effector is": align the pose, then solve IK from ``q_current``."""

    __slots__ = ("_alignment", "_ik", "joint_names")

    def __init__(self, alignment: Alignment, ik: ArmIK, joint_names: tuple[str, ...]) -> None:
        self._alignment = alignment
        self._ik = ik
        self.joint_names = joint_names

    def __call__(
        self, sample: ControllerState | Pose, q_current: FloatArray, dt: float
    ) -> tuple[JointCommand, IKResult]:
        """Joint targets for ``sample`` (stamped with the sample's stamp) and the IK residual."""
        position, orientation = self._alignment.apply(sample.position, sample.orientation)
        result = self._ik.solve(position, orientation, q_current, dt)
        return JointCommand(sample.stamp, self.joint_names, result.q), result
