"""One-Euro keypoint filter: lag as designed, per-point cutoffs, untracked points, restarts."""

from __future__ import annotations

import math

import numpy as np
import pytest

from telerig.retarget.keypoint_filter import OneEuroPointFilter
from telerig.retarget.se3_filter import steady_state_lag_s

RATE = 100.0


def test_a_ramp_is_trailed_by_the_designed_lag() -> None:
    f = OneEuroPointFilter(min_cutoff_hz=2.0, beta=10.0, derivative_cutoff_hz=1.0)
    speed = 0.5  # [m/s] along x
    out = np.zeros(3)
    for k in range(400):
        t = k / RATE
        out = f(np.array([[speed * t, 0.0, 1.0]]), t)[0]
    lag = (speed * 399 / RATE - out[0]) / speed
    assert lag == pytest.approx(steady_state_lag_s(2.0, 10.0, speed), abs=1.0 / RATE)


def test_points_are_filtered_independently() -> None:
    f = OneEuroPointFilter(min_cutoff_hz=1.0, beta=20.0)
    rng = np.random.default_rng(0)
    still, moving = [], []
    for k in range(300):
        t = k / RATE
        x = np.array([[0.0, 0.0, 0.0], [0.8 * t, 0.0, 0.0]]) + rng.normal(0.0, 0.005, (2, 3))
        out = f(x, t)
        if k >= 100:
            still.append(out[0])
            moving.append(out[1, 0] - 0.8 * t)
    assert np.std(np.array(still)[:, 0]) < 0.005 / 3  # jitter of the still point cut > 3x
    assert abs(np.mean(moving)) < 0.8 * 0.03  # the fast point trails by less than 30 ms


def test_untracked_points_come_out_nan_and_restart_at_their_input() -> None:
    f = OneEuroPointFilter()
    f(np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]), 0.0)
    out = f(np.array([[0.1, 0.0, 0.0], [np.nan, np.nan, np.nan]]), 0.01)
    assert np.all(np.isnan(out[1]))
    assert np.all(np.isfinite(out[0]))
    out = f(np.array([[0.1, 0.0, 0.0], [5.0, 5.0, 5.0]]), 0.02)
    np.testing.assert_array_equal(out[1], [5.0, 5.0, 5.0])


def test_a_long_gap_restarts_at_the_input() -> None:
    f = OneEuroPointFilter(max_gap_s=0.5)
    f(np.zeros((1, 3)), 0.0)
    assert f(np.ones((1, 3)), 0.01)[0, 0] < 1.0  # filtered
    np.testing.assert_array_equal(f(np.full((1, 3), 2.0), 1.0), [[2.0, 2.0, 2.0]])


def test_reset_passes_the_next_sample_through() -> None:
    f = OneEuroPointFilter()
    f(np.zeros((1, 3)), 0.0)
    f.reset()
    np.testing.assert_array_equal(f(np.ones((1, 3)), 0.01), [[1.0, 1.0, 1.0]])


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"min_cutoff_hz": 0.0}, "min_cutoff_hz must be > 0"),
        ({"beta": -1.0}, "beta must be >= 0"),
        ({"derivative_cutoff_hz": math.nan}, "derivative_cutoff_hz must be > 0"),
    ],
)
def test_bad_parameters_are_refused(kwargs: dict[str, float], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        OneEuroPointFilter(**kwargs)
