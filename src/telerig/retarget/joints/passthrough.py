"""Joint targets by name → the robot's commanded joints and gripper, blended in after a re-anchor.

A policy (or any joint-space source) already speaks the robot's joints, so retargeting is a lookup
by joint name (a ``<robot>.`` prefix, as multi-robot exports write it, is accepted). After
:meth:`JointPassthrough.reset` (the robot was driven home, a device resumed, the source took over
from another one) the first ``blend_s`` seconds move linearly from where the robot was commanded
to the source's targets, on top of the safety chain's start-up ramp: a source whose first target
is far away never makes the robot jump.
"""

from __future__ import annotations

import numpy as np

from telerig.ir.types import FloatArray, GripperCommand, JointCommand, Sample

__all__ = ["GRIPPER", "JointGripper", "JointPassthrough"]

#: The entry of a joint-space sample that is the gripper's opening (0 closed, 1 open).
GRIPPER = "gripper"


def _index(names: tuple[str, ...], robot: str) -> dict[str, int]:
    prefix = f"{robot}."
    return {(n[len(prefix) :] if n.startswith(prefix) else n): i for i, n in enumerate(names)}


class JointPassthrough:
    """A :class:`~telerig.retarget.binding.Retargeter` of :class:`JointCommand` samples.

    Args:
        robot: Robot id (the accepted name prefix).
        joint_names: The robot's commanded joints, in driver order.
        blend_s: Time to blend from the commanded pose to the source's targets after a reset [s].

    A sample that lacks one of the robot's joints sends nothing (counted in ``mismatched``).
    """

    accepts: tuple[type, ...] = (JointCommand,)

    def __init__(self, robot: str, joint_names: tuple[str, ...], *, blend_s: float = 0.5) -> None:
        if not blend_s >= 0.0:
            raise ValueError(f"blend_s must be >= 0 s, got {blend_s}")
        self.robot = robot
        self.joint_names = joint_names
        self.blend_s = blend_s
        self.mismatched = 0
        self._order: tuple[tuple[str, ...], np.ndarray] | None = None
        self._anchor: FloatArray | None = None
        self._since_s = 0.0

    def __call__(self, sample: Sample, q_current: FloatArray, dt: float) -> tuple[JointCommand | None, None]:
        if not isinstance(sample, JointCommand):
            raise TypeError(f"joint passthrough takes JointCommand samples, got {type(sample).__name__}")
        order = self._order
        if order is None or order[0] != sample.names:
            index = _index(sample.names, self.robot)
            missing = [n for n in self.joint_names if n not in index]
            if missing:
                self.mismatched += 1
                return None, None
            order = self._order = (sample.names, np.array([index[n] for n in self.joint_names]))
        target = np.asarray(sample.positions, dtype=np.float64)[order[1]]
        if self.blend_s > 0.0:
            if self._anchor is None:
                self._anchor, self._since_s = np.array(q_current, dtype=np.float64), 0.0
            self._since_s += dt
            alpha = min(1.0, self._since_s / self.blend_s)
            if alpha < 1.0:
                target = self._anchor + alpha * (target - self._anchor)
        return JointCommand(sample.stamp, self.joint_names, target), None

    def reset(self) -> None:
        """Blend in again from the pose commanded at the next sample."""
        self._anchor = None
        self._since_s = 0.0


class JointGripper:
    """A :class:`~telerig.retarget.binding.GripperRetargeter`: the ``gripper`` entry of a
    :class:`JointCommand` (or a :class:`GripperCommand` as is), clipped to [0, 1]."""

    def __call__(self, sample: Sample) -> GripperCommand | None:
        if isinstance(sample, GripperCommand):
            opening = sample.opening
        elif isinstance(sample, JointCommand) and GRIPPER in sample.names:
            opening = float(sample.positions[sample.names.index(GRIPPER)])
        else:
            return None
        if not np.isfinite(opening):
            return None
        return GripperCommand(sample.stamp, float(np.clip(opening, 0.0, 1.0)))
