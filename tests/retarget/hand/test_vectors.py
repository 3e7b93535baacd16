"""Human keypoint vectors in the hand frame."""

from __future__ import annotations

import math

import numpy as np
import pytest

from telerig.devices.glove.kinematics import HandModel
from telerig.ir.frames import quat_from_axis_angle, quat_rotate
from telerig.ir.types import HandPose, Stamp
from telerig.retarget.hand.vectors import KeypointVectors, default_vectors, hand_rotation, human_vectors

TIPS = KeypointVectors.of([(0, 4), (0, 8), (0, 12), (0, 16), (0, 20)])


def _pose(
    kp: np.ndarray, conf: np.ndarray | None = None, quat: np.ndarray | None = None, hand: str = "right"
) -> HandPose:
    return HandPose(
        Stamp("glove", 1, 5, 5),
        hand,  # type: ignore[arg-type]
        kp[0],
        np.array([1.0, 0.0, 0.0, 0.0]) if quat is None else quat,
        kp,
        np.ones(21) if conf is None else conf,
        "operator",
    )


def _open_hand(hand: str = "right") -> np.ndarray:
    return HandModel.default().keypoints(np.zeros((5, 4)), hand)  # type: ignore[arg-type]


def test_vectors_of_a_flat_hand_point_forward_with_the_thumb_to_the_left() -> None:
    found = human_vectors(_pose(_open_hand()), TIPS)
    assert found is not None
    v, valid = found
    assert valid.all()
    assert np.all(v[:, 0] > 0.09)  # every tip ahead of the wrist
    assert v[0, 1] > 0.05
    assert v[4, 1] < -0.03
    np.testing.assert_allclose(
        np.linalg.norm(v, axis=1), np.linalg.norm(TIPS.of_points(_open_hand()), axis=1)
    )


def test_vectors_do_not_depend_on_where_the_hand_is_or_how_it_is_turned() -> None:
    kp = _open_hand()
    q = quat_from_axis_angle(np.array([0.3, -0.5, 0.8]) / math.sqrt(0.98), 1.1)
    moved = np.array([quat_rotate(q, p) for p in kp]) + np.array([0.4, -0.2, 1.3])
    a, b = human_vectors(_pose(kp), TIPS), human_vectors(_pose(moved), TIPS)
    assert a is not None
    assert b is not None
    np.testing.assert_allclose(a[0], b[0], atol=1e-12)


def test_left_hand_mirrors_the_right_one() -> None:
    right = human_vectors(_pose(_open_hand("right")), TIPS)
    left = human_vectors(_pose(_open_hand("left"), hand="left"), TIPS)
    assert right is not None
    assert left is not None
    np.testing.assert_allclose(left[0], right[0] * np.array([1.0, -1.0, 1.0]), atol=1e-12)


def test_low_confidence_keypoints_invalidate_their_vectors_only() -> None:
    conf = np.ones(21)
    conf[8] = 0.1
    found = human_vectors(_pose(_open_hand(), conf), TIPS, min_confidence=0.5)
    assert found is not None
    np.testing.assert_array_equal(found[1], [True, False, True, True, True])
    np.testing.assert_array_equal(found[0][1], 0.0)


def test_frame_falls_back_to_the_wrist_orientation_when_a_knuckle_is_lost() -> None:
    kp = _open_hand()
    conf = np.ones(21)
    conf[9] = 0.0
    yaw = quat_from_axis_angle(np.array([0.0, 0.0, 1.0]), 0.5)
    rot = hand_rotation(_pose(kp, conf, quat=yaw))
    assert rot is not None
    np.testing.assert_allclose(rot[:, 0], [math.cos(0.5), math.sin(0.5), 0.0], atol=1e-12)


def test_wrist_frame_source_uses_the_device_orientation() -> None:
    yaw = quat_from_axis_angle(np.array([0.0, 0.0, 1.0]), math.pi / 2)
    rot = hand_rotation(_pose(_open_hand(), quat=yaw), source="wrist")
    assert rot is not None
    np.testing.assert_allclose(rot, [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], atol=1e-12)


def test_default_vectors_add_the_thumb_mcp_and_skip_missing_fingers() -> None:
    assert default_vectors(range(21)).pairs == ((0, 4), (0, 8), (0, 12), (0, 16), (0, 20), (0, 2))
    assert default_vectors([0, 2, 4, 8, 12, 16]).pairs == ((0, 4), (0, 8), (0, 12), (0, 16), (0, 2))


@pytest.mark.parametrize("pairs", [[], [(0, 21)], [(3, 3)], [(-1, 4)]])
def test_bad_pairs_are_rejected(pairs: list[tuple[int, int]]) -> None:
    with pytest.raises(ValueError, match="keypoint"):
        KeypointVectors.of(pairs)
