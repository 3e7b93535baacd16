"""One-Euro low-pass of tracked 3-D keypoints (skeleton joints), each point with its own adaptive cutoff."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from telerig.ir.types import FloatArray

__all__ = ["OneEuroPointFilter"]

_TWO_PI = 2.0 * math.pi


class OneEuroPointFilter:
    """Speed-adaptive low-pass of K points in R^3 (Casiez et al., CHI 2012), one cutoff per point.

    Per point ``k``: ``x_k += a(fc_k) (x_in_k - x_k)`` with ``fc_k = min_cutoff_hz + beta * |v_k|`` and
    ``v_k`` its speed [m/s], estimated from the raw input and low-passed at ``derivative_cutoff_hz``.
    A point held still (a shoulder) is smoothed hard while a moving one (a wrist in a reach) follows
    with little lag; points are independent, so one fast hand does not unfilter the other.

    Latency: a point moving at ``v`` [m/s] trails the input by ``1 / (2 pi (min_cutoff_hz + beta v))``
    seconds (:func:`telerig.retarget.se3_filter.steady_state_lag_s`); with the defaults (2 Hz, 10 /m)
    that is 80 ms at rest, 23 ms at 0.5 m/s and 13 ms at 1 m/s. ``benchmarks/humanoid_rig.py``
    measures the wrist-target lag on the shipped BVH clip.

    A point given as NaN (an optional keypoint not tracked) comes out NaN and restarts at its next
    finite input; a gap longer than ``max_gap_s`` restarts every point.

    Args:
        min_cutoff_hz: Cutoff at rest [Hz], > 0.
        beta: Cutoff increase per unit speed [Hz per m/s = 1/m], >= 0.
        derivative_cutoff_hz: Cutoff of the speed estimate [Hz], > 0.
        max_gap_s: Longest gap between samples the state survives [s], > 0.
    """

    __slots__ = ("_beta", "_d_cutoff", "_live", "_max_gap", "_min_cutoff", "_raw", "_t", "_v", "_x")

    def __init__(
        self,
        min_cutoff_hz: float = 2.0,
        beta: float = 10.0,
        derivative_cutoff_hz: float = 1.0,
        max_gap_s: float = 0.5,
    ) -> None:
        for name, value in (
            ("min_cutoff_hz", min_cutoff_hz),
            ("derivative_cutoff_hz", derivative_cutoff_hz),
            ("max_gap_s", max_gap_s),
        ):
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"{name} must be > 0, got {value}")
        if not (math.isfinite(beta) and beta >= 0.0):
            raise ValueError(f"beta must be >= 0 [1/m], got {beta}")
        self._min_cutoff = float(min_cutoff_hz)
        self._beta = float(beta)
        self._d_cutoff = float(derivative_cutoff_hz)
        self._max_gap = float(max_gap_s)
        self._t: float | None = None
        self._x = np.zeros((0, 3))
        self._raw = np.zeros((0, 3))
        self._v = np.zeros((0, 3))
        self._live = np.zeros(0, dtype=bool)

    def reset(self) -> None:
        """Forget the state; the next sample passes through unchanged."""
        self._t = None

    def __call__(self, points: npt.ArrayLike, t_s: float) -> FloatArray:
        """Filter one sample of the points.

        Args:
            points: Input positions [m], any frame. Shape (K, 3); NaN rows for untracked points.
            t_s: Sample time [s] (capture time); a sample not newer than the last one returns the
                current estimate unchanged.

        Returns:
            Filtered positions [m], same frame. Shape (K, 3), NaN where the input row is not finite.
        """
        x_in = np.array(points, dtype=np.float64)
        if x_in.ndim != 2 or x_in.shape[1] != 3:
            raise ValueError(f"points must have shape (K, 3), got {x_in.shape}")
        finite = np.all(np.isfinite(x_in), axis=1)
        t_last = self._t
        if t_last is None or x_in.shape != self._x.shape or t_s - t_last > self._max_gap:
            self._t = t_s
            self._x = x_in.copy()
            self._raw = x_in.copy()
            self._v = np.zeros_like(x_in)
            self._live = finite
            return x_in
        dt = t_s - t_last
        if dt <= 0.0:
            return self._x.copy()
        self._t = t_s
        a_d = 1.0 / (1.0 + 1.0 / (_TWO_PI * self._d_cutoff * dt))
        v = self._v + a_d * ((x_in - self._raw) / dt - self._v)
        speed = np.sqrt(np.einsum("ij,ij->i", v, v))
        a = 1.0 / (1.0 + 1.0 / (_TWO_PI * (self._min_cutoff + self._beta * speed) * dt))
        x: FloatArray = self._x + a[:, None] * (x_in - self._x)
        restart = finite & ~self._live  # (re)appearing points start at their input
        x[restart] = x_in[restart]
        v[restart] = 0.0
        x[~finite] = np.nan
        v[~finite] = 0.0
        self._x, self._v, self._raw, self._live = x, v, x_in, finite
        return x.copy()
