"""benchmarks/fleet.py: a robot's recorded state times, their skips and gaps."""

from __future__ import annotations

from collections.abc import Callable
from types import ModuleType

import numpy as np


def test_skips_are_intervals_over_one_and_a_half_periods_and_gaps_over_two(
    load_benchmark: Callable[[str], ModuleType],
) -> None:
    state_skips = load_benchmark("fleet").state_skips
    ms = 1_000_000
    steady = np.arange(0, 100 * 10 * ms, 10 * ms, dtype=np.int64)
    assert state_skips(steady, 0.01) == (0, 0)
    # One state a wake off its turn, and a bit (a late tick, the physics waking at twice the rate):
    # 16 ms, a skip; then 4 ms.
    late = steady.copy()
    late[50] += 6 * ms
    assert state_skips(late, 0.01) == (1, 0)
    assert state_skips(steady + 5 * ms * (np.arange(steady.size) == 50), 0.01) == (0, 0)  # 15 ms: not over
    # One state never read (a tick next to a wake at the control rate): 20 ms and a bit, a gap.
    missing = np.delete(steady, 50)
    missing[50:] += ms // 10
    assert state_skips(missing, 0.01) == (1, 1)
    # Order does not matter; fewer than two states have no interval.
    assert state_skips(missing[::-1].copy(), 0.01) == (1, 1)
    assert state_skips(np.array([], dtype=np.int64), 0.01) == (0, 0)
    assert state_skips(np.array([5], dtype=np.int64), 0.01) == (0, 0)
