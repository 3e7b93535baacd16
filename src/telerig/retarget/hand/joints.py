"""The hand retargeter as a control-loop part: tracked hand → robot hand joint command plus residual."""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from telerig.errors import ConfigError
from telerig.ir.types import FloatArray, HandPose, JointCommand, Sample
from telerig.retarget.hand.optimizer import HandRetargeter

__all__ = ["HandJointsRetargeter", "HandResidual"]


@dataclass(frozen=True, slots=True)
class HandResidual:
    """How well one hand sample was matched.

    Attributes:
        error_m: Mean vector error over the valid vectors [m].
        max_error_m: Largest valid vector error [m].
        valid: Vectors used (keypoints confident enough).
        total: Vectors configured.
        threshold_m: Mean error above which the sample is flagged [m].
        solve_s: Time spent retargeting this sample [s].
    """

    error_m: float
    max_error_m: float
    valid: int
    total: int
    threshold_m: float
    solve_s: float

    @property
    def flagged(self) -> bool:
        """True when the mean vector error exceeds the threshold."""
        return self.error_m > self.threshold_m

    def metrics(self) -> Mapping[str, float]:
        """``vector_error_m``, ``vector_error_max_m``, ``vectors_valid`` (count) and ``solve_s``."""
        return {
            "vector_error_m": self.error_m,
            "vector_error_max_m": self.max_error_m,
            "vectors_valid": float(self.valid),
            "solve_s": self.solve_s,
        }


class HandJointsRetargeter:
    """Drives a robot hand's commanded joints from :class:`~telerig.ir.types.HandPose` samples.

    Implements :class:`~telerig.retarget.binding.Retargeter`. The command carries the sample's
    stamp and the robot's joint order. A sample of the other hand, or one with no confident
    vector, yields ``(None, None)``: nothing is sent and the safety chain holds the last command
    (then stops on its watchdog if such samples continue).

    Args:
        retargeter: The vector optimizer for the robot's hand model.
        joint_names: The robot's commanded joints, in driver order; the same set as
            ``retargeter.joint_names``.
        threshold_m: Mean vector error above which a residual is flagged [m], > 0.

    Raises:
        ConfigError: the joint sets differ (names the missing and unexpected joints).
    """

    accepts: tuple[type, ...] = (HandPose,)

    def __init__(
        self, retargeter: HandRetargeter, joint_names: tuple[str, ...], *, threshold_m: float = 0.03
    ) -> None:
        if not (math.isfinite(threshold_m) and threshold_m > 0.0):
            raise ValueError(f"threshold_m must be > 0, got {threshold_m}")
        model = tuple(retargeter.joint_names)
        missing = [n for n in model if n not in joint_names]
        unexpected = [n for n in joint_names if n not in model]
        if missing or unexpected or len(joint_names) != len(model):
            raise ConfigError(
                f"the robot's joints do not match the {retargeter.hand.name} hand model: "
                f"missing {', '.join(missing) or 'none'}; unexpected {', '.join(unexpected) or 'none'}"
            )
        self.retargeter = retargeter
        self.joint_names = tuple(joint_names)
        self.threshold_m = float(threshold_m)
        index = {n: i for i, n in enumerate(model)}
        self._order = np.array([index[n] for n in joint_names], dtype=np.intp)
        self._total = len(retargeter.vectors)

    def __call__(
        self, sample: Sample, q_current: FloatArray, dt: float
    ) -> tuple[JointCommand | None, HandResidual | None]:
        """Joint targets [rad] for ``sample`` in driver order, or ``(None, None)`` (see the class)."""
        del q_current, dt  # the optimizer warm-starts from its own last solution
        start = time.perf_counter_ns()
        result = self.retargeter(sample)
        if result is None:
            return None, None
        positions = result.command.positions[self._order]
        solve_s = (time.perf_counter_ns() - start) * 1e-9
        valid_errors = result.vector_errors[result.valid]
        residual = HandResidual(
            error_m=result.error_m,
            max_error_m=float(np.max(valid_errors)),
            valid=int(np.count_nonzero(result.valid)),
            total=self._total,
            threshold_m=self.threshold_m,
            solve_s=solve_s,
        )
        return JointCommand(sample.stamp, self.joint_names, positions), residual

    def reset(self) -> None:
        """Restart the optimizer's warm start from the open hand (called while the robot homes)."""
        self.retargeter.reset()
