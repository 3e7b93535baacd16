"""One-Euro SE(3) filter: convergence, ramp lag against theory, rotation filtered on the manifold."""

from __future__ import annotations

import math

import numpy as np
import pytest

from telerig.ir.frames import quat_angle, quat_exp, quat_from_axis_angle, quat_log, quat_multiply
from telerig.retarget.se3_filter import OneEuroPoseFilter, steady_state_lag_s

IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])
Z = np.array([0.0, 0.0, 1.0])
DT = 0.01


def _yaw(angle: float) -> np.ndarray:
    return quat_from_axis_angle(Z, angle)


def test_log_exp_round_trip_up_to_pi() -> None:
    rng = np.random.default_rng(0)
    for _ in range(200):
        v = rng.normal(size=3)
        v *= rng.uniform(0.0, math.pi - 1e-6) / np.linalg.norm(v)
        np.testing.assert_allclose(quat_log(quat_exp(v)), v, atol=1e-9)
    np.testing.assert_allclose(quat_log(IDENTITY), np.zeros(3))
    np.testing.assert_allclose(quat_log(-_yaw(0.3)), [0.0, 0.0, 0.3], atol=1e-12)


def test_first_sample_passes_through_and_constant_input_converges() -> None:
    f = OneEuroPoseFilter()
    p, q = f(np.array([0.1, 0.2, 0.3]), _yaw(0.2), 0.0)
    np.testing.assert_allclose(p, [0.1, 0.2, 0.3])
    target_p, target_q = np.array([0.4, -0.1, 0.5]), _yaw(1.2)
    for k in range(1, 400):
        p, q = f(target_p, target_q, k * DT)
    np.testing.assert_allclose(p, target_p, atol=1e-6)
    assert quat_angle(q, target_q) < 1e-6


@pytest.mark.parametrize("speed", [0.05, 0.2, 0.5])
def test_ramp_lag_matches_the_documented_formula(speed: float) -> None:
    f = OneEuroPoseFilter(min_cutoff_hz=2.0, beta=40.0)
    direction = np.array([0.6, 0.8, 0.0])
    lag = 0.0
    for k in range(600):
        t = k * DT
        p_in = speed * t * direction
        p, _ = f(p_in, IDENTITY, t)
        lag = float(np.linalg.norm(p_in - p)) / speed
    expected = steady_state_lag_s(2.0, 40.0, speed)
    assert lag == pytest.approx(expected, rel=0.02)


def test_rotation_ramp_lag_matches_the_documented_formula() -> None:
    f = OneEuroPoseFilter(min_cutoff_hz=2.0, beta_rotation=4.0)
    rate = 1.0  # rad/s
    lag = 0.0
    for k in range(600):
        t = k * DT
        _, q = f(np.zeros(3), _yaw(rate * t), t)
        lag = quat_angle(q, _yaw(rate * t)) / rate
    assert lag == pytest.approx(steady_state_lag_s(2.0, 4.0, rate), rel=0.02)


def test_rotation_noise_around_plus_minus_pi_is_filtered_without_wrapping() -> None:
    f = OneEuroPoseFilter(min_cutoff_hz=1.0, beta_rotation=0.0)
    rng = np.random.default_rng(1)
    worst = 0.0
    for k in range(300):
        # Yaw jitters across +-pi: an Euler-angle average would swing toward 0.
        yaw = math.pi + rng.uniform(-0.1, 0.1)
        yaw = (yaw + math.pi) % (2 * math.pi) - math.pi
        _, q = f(np.zeros(3), _yaw(yaw), k * DT)
        worst = max(worst, quat_angle(q, _yaw(math.pi)))
    assert worst <= 0.1 + 1e-9


def test_rotation_is_smoothed_not_passed_through() -> None:
    f = OneEuroPoseFilter(min_cutoff_hz=1.0, beta_rotation=0.0)
    f(np.zeros(3), IDENTITY, 0.0)
    tilt = quat_multiply(_yaw(0.0), quat_from_axis_angle(np.array([1.0, 0.0, 0.0]), 0.5))
    _, q = f(np.zeros(3), tilt, DT)
    # One step of a 1 Hz low-pass at 100 Hz moves ~6% of the way, along the geodesic.
    assert quat_angle(q, IDENTITY) == pytest.approx(0.5 / (1 + 1 / (2 * math.pi * DT)), rel=1e-6)
    assert quat_angle(q, IDENTITY) + quat_angle(q, tilt) == pytest.approx(0.5, abs=1e-9)


def test_a_long_gap_restarts_at_the_input() -> None:
    f = OneEuroPoseFilter(max_gap_s=0.5)
    f(np.zeros(3), IDENTITY, 0.0)
    p, _ = f(np.ones(3), IDENTITY, 1.0)
    np.testing.assert_allclose(p, np.ones(3))


def test_stale_sample_returns_the_estimate_unchanged() -> None:
    f = OneEuroPoseFilter()
    f(np.zeros(3), IDENTITY, 1.0)
    p, _ = f(np.ones(3), IDENTITY, 0.5)
    np.testing.assert_allclose(p, np.zeros(3))


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"min_cutoff_hz": 0.0}, "min_cutoff_hz"),
        ({"beta": -1.0}, "beta"),
        ({"max_gap_s": math.nan}, "max_gap_s"),
    ],
)
def test_bad_parameters_name_the_parameter(kwargs: dict[str, float], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        OneEuroPoseFilter(**kwargs)
