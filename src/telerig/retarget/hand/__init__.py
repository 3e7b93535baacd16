"""Dexterous hand retargeting: human keypoint vectors matched by a fast bounded least-squares solver."""

from telerig.retarget.hand.optimizer import (
    HandRetargeter,
    HandRetargetResult,
    OptimizerResult,
    VectorOptimizer,
)
from telerig.retarget.hand.vectors import KeypointVectors, default_vectors, hand_rotation, human_vectors

__all__ = [
    "HandRetargetResult",
    "HandRetargeter",
    "KeypointVectors",
    "OptimizerResult",
    "VectorOptimizer",
    "default_vectors",
    "hand_rotation",
    "human_vectors",
]
