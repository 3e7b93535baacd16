"""OpenXR stage space -> operator frame conversions in telerig.ir.frames."""

from __future__ import annotations

import numpy as np
import pytest

from telerig.ir.frames import (
    Q_OPERATOR_FROM_OPENXR,
    openxr_to_operator_body_quat,
    openxr_to_operator_points,
    openxr_to_operator_quat,
    quat_conjugate,
    quat_from_axis_angle,
    quat_multiply,
    quat_rotate,
)

Q = np.array(Q_OPERATOR_FROM_OPENXR)
RNG = np.random.default_rng(11)


def xyzw(q: np.ndarray) -> np.ndarray:
    return np.array([q[1], q[2], q[3], q[0]])


@pytest.mark.parametrize(
    ("openxr", "operator"),
    [((0, 0, -1), (1, 0, 0)), ((1, 0, 0), (0, -1, 0)), ((0, 1, 0), (0, 0, 1))],
    ids=["forward", "right", "up"],
)
def test_openxr_axes_map_to_operator_axes(openxr: tuple[int, ...], operator: tuple[int, ...]) -> None:
    np.testing.assert_allclose(openxr_to_operator_points(openxr), operator)
    np.testing.assert_allclose(quat_rotate(Q, np.array(openxr, dtype=float)), operator, atol=1e-12)


def test_axis_change_is_a_proper_rotation() -> None:
    m = openxr_to_operator_points(np.eye(3)).T  # columns: images of the OpenXR axes
    assert np.linalg.det(m) == pytest.approx(1.0)


def test_points_keep_their_batch_shape() -> None:
    pts = RNG.normal(size=(4, 26, 3))
    out = openxr_to_operator_points(pts)
    assert out.shape == (4, 26, 3)
    np.testing.assert_allclose(out[2, 5], openxr_to_operator_points(pts[2, 5]))


def test_quat_changes_only_the_reference_frame() -> None:
    q = quat_from_axis_angle(RNG.normal(size=3), 1.1)
    v_body = RNG.normal(size=3)
    converted = openxr_to_operator_quat(xyzw(q))
    np.testing.assert_allclose(
        quat_rotate(converted, v_body), openxr_to_operator_points(quat_rotate(q, v_body)), atol=1e-12
    )


def test_body_quat_is_conjugation_by_the_axis_change() -> None:
    q = quat_from_axis_angle(RNG.normal(size=3), -2.3)
    expected = quat_multiply(quat_multiply(Q, q), quat_conjugate(Q))
    np.testing.assert_allclose(openxr_to_operator_body_quat(xyzw(q)), expected, atol=1e-12)


def test_body_at_rest_stays_identity() -> None:
    np.testing.assert_allclose(openxr_to_operator_body_quat((0.0, 0.0, 0.0, 1.0)), [1, 0, 0, 0])
