"""Human hand keypoint vectors (e.g. wrist to fingertip) from a HandPose, in the hand's own wrist frame."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt

from telerig.ir.types import HAND_KEYPOINTS, FloatArray, HandPose
from telerig.robots.models.hands import hand_frame_axes

__all__ = [
    "FINGER_OF_KEYPOINT",
    "FRAME_KEYPOINTS",
    "HandFrameSource",
    "KeypointVectors",
    "default_vectors",
    "hand_rotation",
    "human_vectors",
]

#: How the hand frame is found: from the wrist and knuckle keypoints, or the device's wrist orientation.
HandFrameSource = Literal["keypoints", "wrist"]
#: Keypoints the hand frame is built from: wrist, index MCP, middle MCP, little MCP.
FRAME_KEYPOINTS = (0, 5, 9, 17)
#: Finger of each MediaPipe keypoint (0 thumb .. 4 little); the wrist counts as -1.
FINGER_OF_KEYPOINT: tuple[int, ...] = (-1, *(f for f in range(5) for _ in range(4)))
_FRAME_INDEX = np.array(FRAME_KEYPOINTS, dtype=np.intp)


@dataclass(frozen=True, slots=True)
class KeypointVectors:
    """Vectors between keypoint pairs: ``v_i = p[tasks[i]] - p[origins[i]]``.

    Attributes:
        origins: MediaPipe index of each vector's start. Shape (m,).
        tasks: MediaPipe index of each vector's end. Shape (m,).
    """

    origins: npt.NDArray[np.intp]
    tasks: npt.NDArray[np.intp]

    @classmethod
    def of(cls, pairs: Sequence[tuple[int, int]]) -> KeypointVectors:
        """Vectors from ``(origin, task)`` MediaPipe index pairs.

        Raises:
            ValueError: no pairs, an index outside [0, 20], or a pair with equal ends.
        """
        if not pairs:
            raise ValueError("need at least one (origin, task) keypoint pair")
        arr = np.array(pairs, dtype=np.intp).reshape(-1, 2)
        if np.any((arr < 0) | (arr >= HAND_KEYPOINTS)):
            raise ValueError(
                f"keypoint indices must be in [0, {HAND_KEYPOINTS - 1}], got {list(map(tuple, arr))}"
            )
        if np.any(arr[:, 0] == arr[:, 1]):
            raise ValueError(f"a vector needs two different keypoints, got {list(map(tuple, arr))}")
        origins, tasks = arr[:, 0].copy(), arr[:, 1].copy()
        origins.flags.writeable = False
        tasks.flags.writeable = False
        return cls(origins, tasks)

    def __len__(self) -> int:
        return int(self.origins.size)

    @property
    def pairs(self) -> tuple[tuple[int, int], ...]:
        """``(origin, task)`` pairs."""
        return tuple((int(o), int(t)) for o, t in zip(self.origins, self.tasks, strict=True))

    @property
    def fingers(self) -> npt.NDArray[np.intp]:
        """Finger (0 thumb .. 4 little) each vector's task keypoint is on. Shape (m,)."""
        return np.array([FINGER_OF_KEYPOINT[int(t)] for t in self.tasks], dtype=np.intp)

    def of_points(self, points: FloatArray) -> FloatArray:
        """Vectors [m] of 21 keypoints ``points`` (21, 3), in their frame. Shape (m, 3)."""
        out: FloatArray = points[self.tasks] - points[self.origins]
        return out


def default_vectors(available: Sequence[int]) -> KeypointVectors:
    """Wrist to every fingertip in ``available``, plus wrist to the thumb MCP when available.

    The thumb MCP vector pins the thumb's base, which fingertip vectors alone leave free to swing.
    """
    pairs = [(0, tip) for tip in (4, 8, 12, 16, 20) if tip in available]
    if 2 in available:
        pairs.append((0, 2))
    return KeypointVectors.of(pairs)


def hand_rotation(
    pose: HandPose, source: HandFrameSource = "keypoints", min_confidence: float = 0.5
) -> FloatArray | None:
    """Rotation from the hand frame to ``pose.frame_id`` (columns: hand x, y, z). Shape (3, 3).

    The hand frame is :func:`~telerig.robots.models.hands.hand_frame_axes`: x wrist to middle MCP,
    z out of the back of the hand, y = z x x. With ``source="keypoints"`` it is built from the
    wrist and knuckles (falling back to the wrist orientation when one of them is below
    ``min_confidence``); with ``"wrist"`` from ``pose.wrist_orientation``, which telerig devices
    report in the same convention. ``None`` when no frame can be found (degenerate or non-finite).
    """
    if source == "keypoints":
        conf = pose.keypoint_confidence[_FRAME_INDEX]
        pts = pose.keypoints[_FRAME_INDEX]
        if (conf >= min_confidence).all() and np.isfinite(pts).all():
            try:
                return hand_frame_axes(pts[0], pts[1], pts[2], pts[3], pose.handedness)
            except ValueError:
                pass
    return _quat_matrix(pose.wrist_orientation)


def human_vectors(
    pose: HandPose,
    vectors: KeypointVectors,
    *,
    source: HandFrameSource = "keypoints",
    min_confidence: float = 0.5,
) -> tuple[FloatArray, npt.NDArray[np.bool_]] | None:
    """The vectors [m] of a tracked hand in its hand frame, and which of them are trustworthy.

    Args:
        pose: A tracked hand; keypoints in any frame.
        vectors: Keypoint pairs.
        source: How the hand frame is found (see :func:`hand_rotation`).
        min_confidence: Keypoint confidence below which a vector using it is invalid.

    Returns:
        ``(v, valid)``: vectors in the hand frame, shape (m, 3), and a mask of those whose ends are
        both at least ``min_confidence`` and finite, shape (m,); invalid rows are zero. ``None`` when
        the hand frame cannot be found.
    """
    rot = hand_rotation(pose, source, min_confidence)
    if rot is None:
        return None
    kp = pose.keypoints
    ok = (pose.keypoint_confidence >= min_confidence) & np.isfinite(kp).all(axis=1)
    valid = ok[vectors.origins] & ok[vectors.tasks]
    v = vectors.of_points(np.where(ok[:, None], kp, 0.0)) @ rot
    v[~valid] = 0.0
    return v, valid


def _quat_matrix(q: FloatArray) -> FloatArray | None:
    w, x, y, z = (float(c) for c in q)
    n = w * w + x * x + y * y + z * z
    if not (np.isfinite(n) and n > 1e-12):
        return None
    s = 2.0 / n
    return np.array(
        [
            [1 - s * (y * y + z * z), s * (x * y - w * z), s * (x * z + w * y)],
            [s * (x * y + w * z), 1 - s * (x * x + z * z), s * (y * z - w * x)],
            [s * (x * z - w * y), s * (y * z + w * x), 1 - s * (x * x + y * y)],
        ]
    )
