"""The 24 orthogonal rotations (the cube's rotation group) and the quaternion conversions they need."""

from __future__ import annotations

import itertools
import math
from functools import cache

import numpy as np

from telerig.ir.types import FloatArray

__all__ = ["cube_rotations", "matrix_from_quat", "mean_quaternion", "quat_from_matrix"]


def matrix_from_quat(q: FloatArray) -> FloatArray:
    """Rotation matrix of a unit quaternion (w, x, y, z). Shape (4,) → (3, 3)."""
    w, x, y, z = (float(c) for c in q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def quat_from_matrix(m: FloatArray) -> FloatArray:
    """Unit quaternion (w, x, y, z), w >= 0, of a rotation matrix. Shape (3, 3) → (4,).

    Shepperd's method: divides by the largest of the four candidate terms, so it is exact for
    half turns too.
    """
    m = np.asarray(m, dtype=np.float64)
    trace = float(m[0, 0] + m[1, 1] + m[2, 2])
    terms = (trace, float(m[0, 0]), float(m[1, 1]), float(m[2, 2]))
    i = int(np.argmax(terms))
    if i == 0:
        s = 2.0 * math.sqrt(1.0 + trace)
        q = (0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s)
    elif i == 1:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = ((m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s)
    elif i == 2:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = ((m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s)
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = ((m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s)
    out = np.array(q, dtype=np.float64)
    out /= np.linalg.norm(out)
    return -out if out[0] < 0 else out


@cache
def _cube() -> tuple[tuple[FloatArray, FloatArray], ...]:
    rotations = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            m = np.zeros((3, 3))
            for row, (col, sign) in enumerate(zip(perm, signs, strict=True)):
                m[row, col] = sign
            if np.linalg.det(m) > 0:
                m.flags.writeable = False
                q = quat_from_matrix(m)
                q.flags.writeable = False
                rotations.append((m, q))
    return tuple(rotations)


def cube_rotations() -> tuple[tuple[FloatArray, FloatArray], ...]:
    """The 24 proper rotations that map coordinate axes onto coordinate axes (signed permutation
    matrices with determinant +1), as ``(matrix (3, 3), quaternion (w, x, y, z) (4,))`` pairs,
    identity first. Read-only arrays."""
    return _cube()


def mean_quaternion(quats: FloatArray) -> FloatArray:
    """Average orientation of unit quaternions (Markley et al. 2007: the eigenvector of the largest
    eigenvalue of sum q q^T), insensitive to the q / -q sign ambiguity. Shape (n, 4) → (4,), w >= 0."""
    q = np.asarray(quats, dtype=np.float64)
    _, vectors = np.linalg.eigh(q.T @ q)
    mean: FloatArray = vectors[:, -1] / np.linalg.norm(vectors[:, -1])
    return -mean if mean[0] < 0 else mean
