"""Wilson interval and McNemar's exact test against hand-computed values and scipy's implementations."""

from __future__ import annotations

import math

import pytest
from scipy import stats  # type: ignore[import-untyped]  # no stubs installed

from telerig.runtime.evaluation import (
    TaskEpisode,
    compare_paired,
    mcnemar_exact,
    summarize,
    wilson_interval,
)


def test_wilson_matches_the_closed_form_for_40_of_50() -> None:
    # p = 0.8, n = 50, z^2 = 3.8415: centre (0.8 + 0.038415) / 1.07683 = 0.77860,
    # half 1.82011 * 0.059868 = 0.10897
    lo, hi = wilson_interval(40, 50)
    assert lo == pytest.approx(0.66963, abs=1e-4)
    assert hi == pytest.approx(0.88756, abs=1e-4)


@pytest.mark.parametrize(("k", "n"), [(0, 10), (10, 10), (1, 50), (25, 50), (49, 50), (7, 13), (0, 1)])
def test_wilson_matches_scipy(k: int, n: int) -> None:
    ci = stats.binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
    lo, hi = wilson_interval(k, n)
    assert lo == pytest.approx(ci.low, abs=1e-9)
    assert hi == pytest.approx(ci.high, abs=1e-9)
    assert 0.0 <= lo <= k / n <= hi <= 1.0


def test_wilson_refuses_impossible_counts() -> None:
    with pytest.raises(ValueError, match="successes must be in"):
        wilson_interval(5, 3)
    with pytest.raises(ValueError, match="successes must be in"):
        wilson_interval(-1, 3)
    assert wilson_interval(0, 0) == (0.0, 1.0)


def test_mcnemar_exact_known_values() -> None:
    # 10 vs 2 discordant pairs: 2 * P(X <= 2 | n=12, p=1/2) = 2 * (1 + 12 + 66) / 4096
    assert mcnemar_exact(10, 2) == pytest.approx(158 / 4096)
    assert mcnemar_exact(2, 10) == pytest.approx(158 / 4096)
    assert mcnemar_exact(0, 0) == 1.0
    assert mcnemar_exact(3, 3) == 1.0
    assert mcnemar_exact(6, 0) == pytest.approx(2 / 64)
    # Large counts stay exact (no float overflow of 2**n).
    assert 0.0 < mcnemar_exact(700, 600) < 0.01
    with pytest.raises(ValueError, match="discordant counts"):
        mcnemar_exact(-1, 2)


@pytest.mark.parametrize(("b", "c"), [(1, 0), (5, 1), (9, 4), (13, 13), (20, 7)])
def test_mcnemar_matches_scipy_binomial_test(b: int, c: int) -> None:
    assert mcnemar_exact(b, c) == pytest.approx(stats.binomtest(b, b + c, 0.5).pvalue, rel=1e-9)


def _run(outcomes: list[bool], times: list[float | None] | None = None) -> list[TaskEpisode]:
    times = times or [5.0 if ok else None for ok in outcomes]
    return [
        TaskEpisode(f"e{i}", "complete", 1_000_000 + i, ok, t, "ok" if ok else "cube outside", "pass")
        for i, (ok, t) in enumerate(zip(outcomes, times, strict=True))
    ]


def test_summary_rate_interval_time_and_gates() -> None:
    run = _run([True, True, False, True], [4.0, 6.0, None, 8.0])
    s = summarize(run)
    assert (s.episodes, s.successes, s.rate) == (4, 3, 0.75)
    assert s.interval == wilson_interval(3, 4)
    assert s.mean_time_to_success_s == pytest.approx(6.0)
    assert s.gates == {"pass": 4}
    empty = summarize([])
    assert math.isnan(empty.rate)
    assert math.isnan(empty.mean_time_to_success_s)


def test_paired_comparison_counts_discordant_seeds() -> None:
    a = _run([True] * 12 + [False] * 3)
    b = _run([True] * 2 + [False] * 10 + [True] * 1 + [False] * 2)
    c = compare_paired(a, b)
    assert (c.pairs, c.both, c.only_a, c.only_b, c.neither) == (15, 2, 10, 1, 2)
    assert c.p_value == pytest.approx(mcnemar_exact(10, 1))
    assert c.significant


def test_paired_comparison_needs_the_same_seeds() -> None:
    a = _run([True, False])
    b = _run([True, False, True])
    with pytest.raises(ValueError, match="same seeds"):
        compare_paired(a, b)
