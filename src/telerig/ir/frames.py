"""Rotations and frame transforms on (w, x, y, z) unit quaternions, the one place for frame math.

Conventions: Hamilton quaternions, scalar first; right-handed frames; a
quaternion ``q_ab`` rotates vectors from frame b into frame a.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from telerig.ir.types import FloatArray

__all__ = [
    "Q_OPERATOR_FROM_OPENXR",
    "cross3",
    "openxr_to_operator_body_quat",
    "openxr_to_operator_points",
    "openxr_to_operator_quat",
    "quat_angle",
    "quat_conjugate",
    "quat_exp",
    "quat_from_axis_angle",
    "quat_log",
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


def quat_log(q: FloatArray) -> FloatArray:
    """Rotation vector (axis * angle [rad], angle in [0, pi]) of a unit quaternion (w, x, y, z)."""
    w, x, y, z = float(q[0]), float(q[1]), float(q[2]), float(q[3])
    if w < 0.0:  # the shorter of the two rotations q and -q represent
        w, x, y, z = -w, -x, -y, -z
    s = math.sqrt(x * x + y * y + z * z)
    # angle/sin(angle/2) -> 2 as angle -> 0; atan2 keeps precision near 0 and pi alike.
    k = 2.0 * math.atan2(s, w) / s if s > 1e-12 else 2.0
    return np.array([k * x, k * y, k * z])


def quat_exp(v: FloatArray) -> FloatArray:
    """Unit quaternion (w, x, y, z) of a rotation vector ``v`` (axis * angle [rad]). Shape (3,) → (4,)."""
    x, y, z = float(v[0]), float(v[1]), float(v[2])
    angle = math.sqrt(x * x + y * y + z * z)
    half = 0.5 * angle
    k = math.sin(half) / angle if angle > 1e-12 else 0.5
    return np.array([math.cos(half), k * x, k * y, k * z])


def cross3(a: FloatArray, b: FloatArray) -> FloatArray:
    """Cross product of two 3-vectors. Shapes (3,).

    ``np.cross`` validates and broadcasts its arguments, which costs ~30 µs per call on 3-vectors;
    this is the hot-path version (device parsers, alignment).
    """
    ax, ay, az = float(a[0]), float(a[1]), float(a[2])
    bx, by, bz = float(b[0]), float(b[1]), float(b[2])
    return np.array([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx])


def quat_rotate(q: FloatArray, v: FloatArray) -> FloatArray:
    """Rotate vector ``v`` (3,) by unit quaternion ``q`` (4,)."""
    w = q[0]
    u = np.asarray(q[1:])
    t = 2.0 * cross3(u, v)
    return np.asarray(v + w * t + cross3(u, t), dtype=np.float64)


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


# --- OpenXR ---------------------------------------------------------------------------------------
# OpenXR stage/local space: right-handed, +x right, +y up, -z forward (metres). telerig's operator
# frame: right-handed, x forward, y left, z up. Both are right-handed, so the change is a proper
# rotation (no mirroring): x_op = -z_xr, y_op = -x_xr, z_op = y_xr.

#: Quaternion (w, x, y, z) rotating OpenXR stage-space vectors into the operator frame
#: (x_op = -z_xr, y_op = -x_xr, z_op = y_xr).
Q_OPERATOR_FROM_OPENXR: tuple[float, float, float, float] = (0.5, 0.5, -0.5, -0.5)


def openxr_to_operator_points(points: FloatArray | Sequence[float]) -> FloatArray:
    """Points [m] in OpenXR stage space -> operator frame (x forward, y left, z up). Shape (..., 3).

    Returns a new float64 array of the same shape: ``(-z, -x, y)`` per point.
    """
    p = np.asarray(points, dtype=np.float64)
    return np.stack((-p[..., 2], -p[..., 0], p[..., 1]), axis=-1)


def openxr_to_operator_quat(q_xyzw: FloatArray | Sequence[float]) -> FloatArray:
    """Change the reference frame of an OpenXR orientation from stage space to the operator frame.

    Args:
        q_xyzw: Orientation in OpenXR component order (x, y, z, w) mapping body vectors into stage
            space. Shape (4,).

    Returns:
        ``Q_OPERATOR_FROM_OPENXR * q`` as (w, x, y, z): the same body axes, now mapped into the
        operator frame. Shape (4,).
    """
    x, y, z, w = (float(c) for c in q_xyzw)
    a, b, c, d = Q_OPERATOR_FROM_OPENXR
    return np.array(
        [
            a * w - b * x - c * y - d * z,
            a * x + b * w + c * z - d * y,
            a * y - b * z + c * w + d * x,
            a * z + b * y - c * x + d * w,
        ]
    )


def openxr_to_operator_body_quat(q_xyzw: FloatArray | Sequence[float]) -> FloatArray:
    """Convert an OpenXR orientation's reference frame and body axes to telerig's conventions.

    OpenXR bodies (the view, hand joints) use -z forward, +y up, +x right; telerig bodies use
    x forward, y left, z up, like the operator frame. The result maps telerig body axes into the
    operator frame, so a body at rest (OpenXR identity) stays the identity.

    Args:
        q_xyzw: Orientation in OpenXR component order (x, y, z, w), stage space. Shape (4,).

    Returns:
        ``Q * q * conj(Q)`` with ``Q = Q_OPERATOR_FROM_OPENXR``, as (w, x, y, z). Shape (4,).
    """
    x, y, z, w = (float(c) for c in q_xyzw)
    # Conjugation by Q rotates the vector part like a point: (w, -z, -x, y).
    return np.array([w, -z, -x, y])
