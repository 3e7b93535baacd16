"""Rotations and frame transforms on (w, x, y, z) unit quaternions, the one place for frame math.

Conventions: Hamilton quaternions, scalar first; right-handed frames; a
quaternion ``q_ab`` rotates vectors from frame b into frame a.
"""

from __future__ import annotations

import math

import numpy as np

from telerig.ir.types import FloatArray

__all__ = [
    "quat_angle",
    "quat_conjugate",
    "quat_from_axis_angle",
    "quat_multiply",
    "quat_normalize",
    "quat_rotate",
]


def quat_normalize(q: FloatArray) -> FloatArray:
    """Unit quaternion with a non-negative scalar part. Shape (4,)."""
    n = float(np.linalg.norm(q))
    if n < 1e-12 or not math.isfinite(n):
        raise ValueError(f"cannot normalize quaternion {q!r}")
    out = np.asarray(q, dtype=np.float64) / n
    return -out if out[0] < 0 else out


def quat_multiply(a: FloatArray, b: FloatArray) -> FloatArray:
    """Hamilton product ``a * b`` (apply b, then a). Shapes (4,)."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ]
    )


def quat_conjugate(q: FloatArray) -> FloatArray:
    """Inverse of a unit quaternion. Shape (4,)."""
    return np.array([q[0], -q[1], -q[2], -q[3]])


def quat_rotate(q: FloatArray, v: FloatArray) -> FloatArray:
    """Rotate vector ``v`` (3,) by unit quaternion ``q`` (4,)."""
    w = q[0]
    u = np.asarray(q[1:])
    t = 2.0 * np.cross(u, v)
    return np.asarray(v + w * t + np.cross(u, t), dtype=np.float64)


def quat_from_axis_angle(axis: FloatArray, angle: float) -> FloatArray:
    """Quaternion rotating by ``angle`` [rad] about ``axis`` (3,, any non-zero length)."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    s = math.sin(angle / 2.0)
    return np.array([math.cos(angle / 2.0), a[0] * s, a[1] * s, a[2] * s])


def quat_angle(a: FloatArray, b: FloatArray) -> float:
    """Angle [rad] of the rotation between two unit quaternions, in [0, pi]."""
    d = abs(float(np.dot(a, b)))
    return 2.0 * math.acos(min(1.0, d))
