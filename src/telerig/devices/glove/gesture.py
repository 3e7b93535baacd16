"""Hand gesture classification (open, fist, pinch, point) from keypoints, with hysteresis.

Works on any :class:`~telerig.ir.types.HandPose` (glove, Leap, camera): the features are frame- and
scale-invariant. Per finger (index..little), *curl* [rad] is the sum of the bend angles along
wrist -> MCP -> PIP -> DIP -> tip (about 0.2 rad straight, 3+ rad in a fist); *pinch ratio* is the
thumb-tip to index-tip distance divided by the palm length (wrist to middle MCP).

Rules, first match wins: all four fingers curled -> FIST; pinch -> PINCH; index extended and the
other three curled -> POINT; all four extended -> OPEN; otherwise NONE.

Hysteresis: a finger becomes *extended* below ``extend_enter_rad`` and stays so until above
``extend_exit_rad``; it becomes *curled* above ``curl_enter_rad`` and stays so until below
``curl_exit_rad``; pinch starts below ``pinch_enter`` and ends above ``pinch_exit``. The stateless
:func:`classify` uses the enter thresholds only (a gesture is reported only when clearly made);
:class:`GestureTracker` keeps the states between samples and also debounces: a new gesture is
reported after it has held for ``hold_samples`` consecutive samples. Use one tracker per hand.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from telerig.errors import ConfigError
from telerig.ir.types import FloatArray, HandPose

__all__ = ["Gesture", "GestureThresholds", "GestureTracker", "HandFeatures", "classify", "hand_features"]


class Gesture(StrEnum):
    """A discrete hand gesture."""

    NONE = "none"
    OPEN = "open"
    FIST = "fist"
    PINCH = "pinch"
    POINT = "point"


@dataclass(frozen=True, slots=True)
class GestureThresholds:
    """Hysteresis thresholds; curls in [rad], pinch as a fraction of the palm length."""

    extend_enter_rad: float = 0.9
    extend_exit_rad: float = 1.3
    curl_enter_rad: float = 2.3
    curl_exit_rad: float = 1.9
    pinch_enter: float = 0.30
    pinch_exit: float = 0.45

    def __post_init__(self) -> None:
        if (
            not 0.0
            < self.extend_enter_rad
            <= self.extend_exit_rad
            < self.curl_exit_rad
            <= self.curl_enter_rad
        ):
            raise ConfigError(
                "gesture thresholds must satisfy 0 < extend_enter_rad <= extend_exit_rad < "
                f"curl_exit_rad <= curl_enter_rad, got {self}"
            )
        if not 0.0 < self.pinch_enter <= self.pinch_exit:
            raise ConfigError(f"gesture thresholds must satisfy 0 < pinch_enter <= pinch_exit, got {self}")


@dataclass(frozen=True, slots=True)
class HandFeatures:
    """Gesture features of one hand.

    Attributes:
        curl: Curl [rad] of index, middle, ring, little. Shape (4,).
        pinch: Thumb-tip to index-tip distance over palm length (dimensionless, >= 0).
    """

    curl: FloatArray
    pinch: float


def _angles_between(a: FloatArray, b: FloatArray) -> FloatArray:
    """Row-wise angle [rad] between vectors a and b. Shapes (n, 3) -> (n,)."""
    dot = np.einsum("ij,ij->i", a, b)
    cross = np.linalg.norm(np.cross(a, b), axis=1)
    out: FloatArray = np.arctan2(cross, dot)
    return out


_MCP = np.array([5, 9, 13, 17])


def hand_features(hand: HandPose) -> HandFeatures | None:
    """Curls and pinch ratio of ``hand``; None if the keypoints are degenerate (zero palm)."""
    kp = hand.keypoints
    palm = float(np.linalg.norm(kp[9] - kp[0]))
    if not (palm > 1e-6 and math.isfinite(palm)):
        return None
    chains = kp[5:21].reshape(4, 4, 3)  # fingers x (mcp, pip, dip, tip)
    bones = np.empty((4, 4, 3))
    bones[:, 0] = kp[_MCP] - kp[0]
    bones[:, 1:] = np.diff(chains, axis=1)
    curl = _angles_between(bones[:, :3].reshape(-1, 3), bones[:, 1:].reshape(-1, 3)).reshape(4, 3).sum(1)
    pinch = float(np.linalg.norm(kp[4] - kp[8])) / palm
    return HandFeatures(curl=curl, pinch=pinch)


def _decide(extended: list[bool], curled: list[bool], pinching: bool) -> Gesture:
    if all(curled):
        return Gesture.FIST
    if pinching:
        return Gesture.PINCH
    if extended[0] and all(curled[1:]):
        return Gesture.POINT
    if all(extended):
        return Gesture.OPEN
    return Gesture.NONE


_DEFAULT_THRESHOLDS = GestureThresholds()


def classify(hand: HandPose, thresholds: GestureThresholds = _DEFAULT_THRESHOLDS) -> Gesture:
    """Gesture of a single sample (no history; enter thresholds only)."""
    f = hand_features(hand)
    if f is None:
        return Gesture.NONE
    t = thresholds
    extended = [bool(c < t.extend_enter_rad) for c in f.curl]
    curled = [bool(c > t.curl_enter_rad) for c in f.curl]
    return _decide(extended, curled, f.pinch < t.pinch_enter)


class GestureTracker:
    """Stateful classifier for one hand: hysteresis on every feature plus a debounce.

    Args:
        thresholds: Hysteresis thresholds.
        hold_samples: Samples a new gesture must persist before it is reported (>= 1).
    """

    def __init__(self, thresholds: GestureThresholds = _DEFAULT_THRESHOLDS, *, hold_samples: int = 3) -> None:
        if hold_samples < 1:
            raise ConfigError(f"hold_samples must be >= 1, got {hold_samples}")
        self.thresholds = thresholds
        self.hold_samples = hold_samples
        self.reset()

    def reset(self) -> None:
        """Forget the history; the gesture becomes NONE."""
        self._extended = [False] * 4
        self._curled = [False] * 4
        self._pinching = False
        self._gesture = Gesture.NONE
        self._candidate = Gesture.NONE
        self._count = 0
        self.changed = False

    @property
    def gesture(self) -> Gesture:
        """The current (debounced) gesture."""
        return self._gesture

    def update(self, hand: HandPose) -> Gesture:
        """Feed one sample; returns the current gesture. ``changed`` tells whether it just changed."""
        f = hand_features(hand)
        self.changed = False
        if f is None:
            return self._gesture
        t = self.thresholds
        for i, c in enumerate(f.curl.tolist()):
            self._extended[i] = c < (t.extend_exit_rad if self._extended[i] else t.extend_enter_rad)
            self._curled[i] = c > (t.curl_exit_rad if self._curled[i] else t.curl_enter_rad)
        self._pinching = f.pinch < (t.pinch_exit if self._pinching else t.pinch_enter)
        raw = _decide(self._extended, self._curled, self._pinching)
        if raw == self._gesture:
            self._candidate, self._count = raw, 0
            return self._gesture
        if raw != self._candidate:
            self._candidate, self._count = raw, 0
        self._count += 1
        if self._count >= self.hold_samples:
            self._gesture, self._count = raw, 0
            self.changed = True
        return self._gesture
