"""Batched axis changes from a capture frame into the operator convention, and rotation helpers."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Literal

import numpy as np

from telerig.errors import ConfigError
from telerig.ir.types import FloatArray

__all__ = ["AXES", "AxisName", "MountTransform", "matrix_to_quat", "quat_matrix"]

AxisName = Literal["+x", "-x", "+y", "-y", "+z", "-z"]
#: Valid axis names, in the order error messages list them.
AXES: tuple[AxisName, ...] = ("+x", "-x", "+y", "-y", "+z", "-z")


def _axis(name: str, field: str) -> FloatArray:
    if name not in AXES:
        raise ConfigError(f"{field} must be one of {', '.join(AXES)}; got {name!r}")
    v = np.zeros(3)
    v["xyz".index(name[1])] = 1.0 if name[0] == "+" else -1.0
    return v


def matrix_to_quat(m: FloatArray) -> FloatArray:
    """Unit quaternions (w, x, y, z), w >= 0, of rotation matrices. Shape (..., 3, 3) -> (..., 4)."""
    m = np.asarray(m, dtype=np.float64)
    shape = m.shape[:-2]
    r = m.reshape(-1, 3, 3)
    # Build from the largest of the four candidate squares (Shepperd), which never divides by ~0.
    t = np.stack(
        [
            1.0 + r[:, 0, 0] + r[:, 1, 1] + r[:, 2, 2],
            1.0 + r[:, 0, 0] - r[:, 1, 1] - r[:, 2, 2],
            1.0 - r[:, 0, 0] + r[:, 1, 1] - r[:, 2, 2],
            1.0 - r[:, 0, 0] - r[:, 1, 1] + r[:, 2, 2],
        ],
        axis=1,
    )
    k = np.argmax(t, axis=1)
    cand = np.empty((r.shape[0], 4, 4))
    cand[:, 0] = np.stack(
        [t[:, 0], r[:, 2, 1] - r[:, 1, 2], r[:, 0, 2] - r[:, 2, 0], r[:, 1, 0] - r[:, 0, 1]], axis=1
    )
    cand[:, 1] = np.stack(
        [r[:, 2, 1] - r[:, 1, 2], t[:, 1], r[:, 1, 0] + r[:, 0, 1], r[:, 0, 2] + r[:, 2, 0]], axis=1
    )
    cand[:, 2] = np.stack(
        [r[:, 0, 2] - r[:, 2, 0], r[:, 1, 0] + r[:, 0, 1], t[:, 2], r[:, 2, 1] + r[:, 1, 2]], axis=1
    )
    cand[:, 3] = np.stack(
        [r[:, 1, 0] - r[:, 0, 1], r[:, 0, 2] + r[:, 2, 0], r[:, 2, 1] + r[:, 1, 2], t[:, 3]], axis=1
    )
    q = cand[np.arange(r.shape[0]), k]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q *= np.where(q[:, :1] < 0.0, -1.0, 1.0)
    out: FloatArray = q.reshape(*shape, 4)
    return out


def quat_matrix(q: FloatArray) -> FloatArray:
    """Rotation matrices of unit quaternions (w, x, y, z). Shape (..., 4) -> (..., 3, 3)."""
    q = np.asarray(q, dtype=np.float64)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=-1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=-1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1),
        ],
        axis=-2,
    )


def _left(q: FloatArray) -> FloatArray:
    """Matrix L(q) with L(q) @ p == q * p (Hamilton, w first)."""
    w, x, y, z = q
    return np.array([[w, -x, -y, -z], [x, w, -z, y], [y, z, w, -x], [z, -y, x, w]])


def _right(q: FloatArray) -> FloatArray:
    """Matrix R(q) with R(q) @ p == p * q (Hamilton, w first)."""
    w, x, y, z = q
    return np.array([[w, -x, -y, -z], [x, w, z, -y], [y, -z, w, x], [z, y, -x, w]])


class MountTransform:
    """Maps poses from a capture system's world frame into the operator axis convention.

    The capture frame is any right-handed frame named by its ``up`` and ``forward`` axes (Motive
    and most BVH files: Y up, +Z forward, so X is left). The output frame has x forward, y left,
    z up (see :mod:`telerig.devices.scripted`), metres: ``p_out = Rz(yaw) @ A @ (scale * p) + offset``
    where A is the axis change. Body orientations are re-expressed with the same axis change on
    both sides, ``q_out = q_yaw * q_A * q * q_A^-1``, so a body whose axes match the capture
    world's reports the identity (before yaw) and its local axes read x forward, y left, z up too.
    """

    def __init__(
        self,
        *,
        up: str = "+y",
        forward: str = "+z",
        yaw_deg: float = 0.0,
        offset: Sequence[float] = (0.0, 0.0, 0.0),
        scale: float = 1.0,
    ) -> None:
        """Args:
        up: Capture-frame axis pointing up, e.g. ``"+y"`` for Motive's default.
        forward: Capture-frame axis pointing forward (orthogonal to ``up``), e.g. ``"+z"``.
        yaw_deg: Extra rotation about the output z axis [deg], applied after the axis change.
        offset: Translation added after rotation [m], output frame. Shape (3,).
        scale: Capture units to metres (0.01 for centimetres); finite and > 0.
        """
        u, f = _axis(up, "up_axis"), _axis(forward, "forward_axis")
        if abs(float(u @ f)) > 0.5:
            raise ConfigError(f"forward_axis {forward!r} must be orthogonal to up_axis {up!r}")
        if not (math.isfinite(scale) and scale > 0.0):
            raise ConfigError(f"scale must be a finite factor > 0 (capture units to metres), got {scale}")
        off = np.asarray(offset, dtype=np.float64)
        if off.shape != (3,) or not np.all(np.isfinite(off)):
            raise ConfigError(f"offset must be three finite coordinates [m], got {offset!r}")
        if not math.isfinite(yaw_deg):
            raise ConfigError(f"yaw_deg must be finite, got {yaw_deg}")
        axes = np.array([f, np.cross(u, f), u])  # rows: output x, y, z in capture coordinates
        c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
        yaw = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        self.up, self.forward, self.yaw_deg, self.scale = up, forward, float(yaw_deg), float(scale)
        self.offset = off
        #: Rotation taking capture coordinates to output coordinates. Shape (3, 3).
        self.rotation = yaw @ axes
        self._axes = axes
        self._yaw = yaw
        q_axes = matrix_to_quat(axes)
        q_left = matrix_to_quat(self.rotation)
        q_axes_inv = q_axes * np.array([1.0, -1.0, -1.0, -1.0])
        self._qmat = _left(q_left) @ _right(q_axes_inv)

    def positions(self, p: FloatArray) -> FloatArray:
        """Capture-frame points (capture units) -> output frame [m]. Shape (N, 3) -> (N, 3)."""
        out: FloatArray = (np.asarray(p, dtype=np.float64) * self.scale) @ self.rotation.T + self.offset
        return out

    def orientations(self, q: FloatArray) -> FloatArray:
        """Capture-frame body orientations (w, x, y, z), unit norm -> output frame. Shape (N, 4)."""
        out = np.asarray(q, dtype=np.float64) @ self._qmat.T
        return out * np.where(out[:, :1] < 0.0, -1.0, 1.0)

    def matrices(self, r: FloatArray) -> FloatArray:
        """Capture-frame body rotation matrices -> output frame. Shape (..., 3, 3)."""
        out: FloatArray = self.rotation @ np.asarray(r, dtype=np.float64) @ self._axes.T
        return out
