"""Quaternion identities of telerig.ir.frames, checked numerically."""

from __future__ import annotations

import math

import numpy as np
import pytest

from telerig.ir.frames import (
    cross3,
    quat_angle,
    quat_conjugate,
    quat_from_axis_angle,
    quat_multiply,
    quat_normalize,
    quat_rotate,
)

RNG = np.random.default_rng(7)


def _random_quat() -> np.ndarray:
    return quat_normalize(RNG.normal(size=4))


def test_rotation_about_z_by_90_degrees_maps_x_to_y() -> None:
    q = quat_from_axis_angle(np.array([0.0, 0.0, 1.0]), math.pi / 2)
    np.testing.assert_allclose(quat_rotate(q, np.array([1.0, 0.0, 0.0])), [0.0, 1.0, 0.0], atol=1e-12)


@pytest.mark.parametrize("_", range(20))
def test_product_composes_rotations(_: int) -> None:
    a, b, v = _random_quat(), _random_quat(), RNG.normal(size=3)
    np.testing.assert_allclose(
        quat_rotate(quat_multiply(a, b), v), quat_rotate(a, quat_rotate(b, v)), atol=1e-12
    )


@pytest.mark.parametrize("_", range(20))
def test_conjugate_is_inverse(_: int) -> None:
    q = _random_quat()
    np.testing.assert_allclose(quat_multiply(q, quat_conjugate(q)), [1.0, 0.0, 0.0, 0.0], atol=1e-12)


def test_angle_between_quaternions() -> None:
    q = quat_from_axis_angle(np.array([1.0, 1.0, 0.0]), 0.3)
    assert quat_angle(np.array([1.0, 0.0, 0.0, 0.0]), q) == pytest.approx(0.3)
    assert quat_angle(q, -q) == pytest.approx(0.0, abs=1e-7)


def test_normalize_rejects_zero() -> None:
    with pytest.raises(ValueError, match="cannot normalize"):
        quat_normalize(np.zeros(4))


@pytest.mark.parametrize("_", range(10))
def test_cross3_matches_numpy(_: int) -> None:
    a, b = RNG.normal(size=3), RNG.normal(size=3)
    np.testing.assert_allclose(cross3(a, b), np.cross(a, b), atol=1e-12)
