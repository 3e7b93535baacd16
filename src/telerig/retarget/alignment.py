"""Operator-to-robot frame alignment: absolute poses, and relative displacements for clutched motion."""

from __future__ import annotations

import numpy as np

from telerig.config.schema import AlignmentConfig
from telerig.ir.frames import quat_conjugate, quat_multiply, quat_normalize, quat_rotate
from telerig.ir.types import FloatArray

__all__ = ["Alignment"]


class Alignment:
    """``p_robot = R (s (p_op - o_op)) + o_robot``, ``q_robot = R q_op``.

    Args:
        rotation: Rotation from the operator frame to the robot base frame (w, x, y, z). Shape (4,).
        operator_origin: Operator-frame point that maps onto ``robot_origin`` [m]. Shape (3,).
        robot_origin: Robot-base-frame point [m]. Shape (3,).
        scale: Human-to-robot motion scale (dimensionless, > 0).
    """

    __slots__ = ("_o_op", "_o_robot", "_q", "_scale")

    def __init__(
        self,
        rotation: FloatArray,
        operator_origin: FloatArray,
        robot_origin: FloatArray,
        scale: float = 1.0,
    ) -> None:
        if scale <= 0:
            raise ValueError(f"scale must be > 0, got {scale}")
        self._q = quat_normalize(np.asarray(rotation, dtype=np.float64))
        self._o_op = np.asarray(operator_origin, dtype=np.float64).reshape(3)
        self._o_robot = np.asarray(robot_origin, dtype=np.float64).reshape(3)
        self._scale = float(scale)

    @classmethod
    def from_config(cls, config: AlignmentConfig) -> Alignment:
        return cls(
            np.array(config.rotation),
            np.array(config.operator_origin),
            np.array(config.robot_origin),
            config.scale,
        )

    @property
    def rotation(self) -> FloatArray:
        """Rotation from the operator frame to the robot base frame (w, x, y, z). Shape (4,)."""
        return self._q.copy()

    @property
    def scale(self) -> float:
        """Human-to-robot motion scale (calibration ratio, dimensionless)."""
        return self._scale

    def displacement(self, delta: FloatArray) -> FloatArray:
        """An operator-frame displacement [m] as a robot-base-frame one, scaled: ``s R delta``. Shape (3,)."""
        return quat_rotate(self._q, self._scale * delta)

    def rotation_delta(self, delta: FloatArray) -> FloatArray:
        """An operator-frame rotation ``q1 q0^-1`` (w, x, y, z) expressed in the robot base frame. Shape (4,).

        ``R delta R^-1``: the same rotation about the corresponding robot-frame axis.
        """
        return quat_multiply(quat_multiply(self._q, delta), quat_conjugate(self._q))

    def apply(self, position: FloatArray, orientation: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Map an operator-frame pose to the robot base frame. Shapes (3,), (4,) → (3,), (4,)."""
        p = quat_rotate(self._q, self._scale * (position - self._o_op)) + self._o_robot
        q = quat_multiply(self._q, orientation)
        return p, q
