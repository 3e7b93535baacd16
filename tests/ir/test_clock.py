"""The shared device clock -> common clock offset estimator (windowed minimum of arrival - device)."""

from __future__ import annotations

import itertools

import pytest
from hypothesis import given
from hypothesis import strategies as st

from telerig.ir.clock import ClockOffsetEstimator

S = 1_000_000_000  # one second [ns]


def test_offset_is_none_before_the_first_update_and_after_reset() -> None:
    clock = ClockOffsetEstimator()
    assert clock.offset_ns is None
    assert clock.update(100, 150) == 50
    assert clock.offset_ns == 50
    clock.reset()
    assert clock.offset_ns is None
    assert clock.update(0, 90) == 90  # the old, smaller minimum is forgotten


def test_offset_is_the_minimum_difference_in_the_window() -> None:
    clock = ClockOffsetEstimator(10 * S)
    diffs = (50, 30, 40, 45, 60, 20, 70)
    assert [clock.update(k, k + d) for k, d in enumerate(diffs)] == [50, 30, 30, 30, 30, 20, 20]


def test_old_minima_expire_with_the_window() -> None:
    clock = ClockOffsetEstimator(3 * S)
    # (arrival [s], arrival - device [ns]): one fast packet at t = 1 s, slower ones after it.
    steps = [(0, 50), (1, 30), (2, 40), (3, 45), (4, 60), (5, 70), (9, 80)]
    got = [clock.update(t * S - d, t * S) for t, d in steps]
    # The window at 4 s is [1 s, 4 s] (the 30 is in), at 5 s [2 s, 5 s]; at 9 s only the new packet.
    assert got == [50, 30, 30, 30, 30, 40, 80]


def test_window_edge_is_inclusive() -> None:
    clock = ClockOffsetEstimator(2 * S)
    clock.update(0, 0)  # difference 0, arrived at 0
    assert clock.update(2 * S - 5, 2 * S) == 0  # arrived exactly window_ns later: still in
    assert clock.update(2 * S + 1 - 9, 2 * S + 1) == 5  # 1 ns later it has expired


def test_offset_follows_drift() -> None:
    clock = ClockOffsetEstimator(1 * S)
    # The device clock runs 0.1 % slow: the true offset grows by 1 ms per second of arrival time.
    period = 10_000_000  # 100 Hz
    for k in range(1000):  # 10 s
        arrival = k * period
        device = arrival - arrival // 1000 - 7
        clock.update(device, arrival)
    last = 999 * period
    # The estimate is the difference of the oldest packet still in the 1 s window, ~1 ms behind.
    assert clock.offset_ns == (last - S) // 1000 + 7
    assert abs(clock.offset_ns - (last // 1000 + 7)) <= S // 1000


def test_a_jump_beyond_reset_ns_restarts_the_estimate() -> None:
    clock = ClockOffsetEstimator(5 * S, reset_ns=S)
    assert clock.update(1_000, 6_000) == 5_000
    assert clock.update(2_000, 6_500) == 4_500
    assert clock.update(3_000, 9_000) == 4_500
    # Device restart: its clock starts over (device time goes back), the difference jumps by ~5 s.
    assert clock.update(500, 5 * S + 500) == 5 * S
    assert clock.update(1_500, 5 * S + 1_400) == 5 * S - 100
    # A jump the other way (clock stepped forward) restarts as well.
    assert clock.update(3 * S, 5 * S + 5_000) == 2 * S + 5_000


def test_a_stalled_stream_keeps_its_offset_and_even_capture_times() -> None:
    # 120 Hz; the whole process stalls 1.3 s, then the backlog arrives in a burst. The late
    # packets' device times continue where they stopped: transport delay, not a new clock.
    period = S // 120
    clock = ClockOffsetEstimator(5 * S, reset_ns=S)
    captures = []
    for k in range(600):
        device = k * period
        arrival = device + 7_000 + (13 * S // 10 if 240 <= k < 396 else 0)  # late by 1.3 s
        if 240 <= k < 396:
            arrival -= (k - 240) * period  # the backlog drains at once: ~simultaneous arrivals
        captures.append(device + clock.update(device, arrival))
    steps = {b - a for a, b in itertools.pairwise(captures)}
    assert steps == {period}, "the stall moved capture times"
    assert clock.offset_ns == 7_000


def test_a_jump_within_reset_ns_keeps_the_minimum() -> None:
    clock = ClockOffsetEstimator(5 * S, reset_ns=S)
    clock.update(0, 1_000)
    assert clock.update(0, S + 1_000) == 1_000  # exactly reset_ns away: a slow packet, not a jump


def test_without_reset_ns_a_jump_up_is_hidden_by_the_old_minimum() -> None:
    clock = ClockOffsetEstimator(5 * S)
    clock.update(0, 1_000)
    assert clock.update(0, 3 * S) == 1_000


@pytest.mark.parametrize(("window_ns", "reset_ns"), [(0, None), (-1, None), (S, 0), (S, -5)])
def test_rejects_non_positive_window_or_reset(window_ns: int, reset_ns: int | None) -> None:
    with pytest.raises(ValueError, match="must be > 0"):
        ClockOffsetEstimator(window_ns, reset_ns=reset_ns)


@given(
    window_ns=st.integers(1, 10 * S),
    reset_ns=st.none() | st.integers(1, 10 * S),
    steps=st.lists(
        st.tuples(st.integers(0, S), st.integers(-(10**12), 10**12)),  # (arrival step, difference)
        min_size=1,
        max_size=200,
    ),
)
def test_capture_is_never_after_arrival_and_matches_a_brute_force_minimum(
    window_ns: int, reset_ns: int | None, steps: list[tuple[int, int]]
) -> None:
    clock = ClockOffsetEstimator(window_ns, reset_ns=reset_ns)
    seen: list[tuple[int, int]] = []  # (arrival, difference) since the last restart
    arrival = 0
    last_device: int | None = None
    for step, diff in steps:
        arrival += step
        device = arrival - diff
        live = [(a, d) for a, d in seen if a >= arrival - window_ns]
        if reset_ns is not None and live:
            jump = diff - min(d for _, d in live)
            back = last_device is not None and device < last_device
            if jump < -reset_ns or (jump > reset_ns and back):
                live = []
        last_device = device
        seen = [*live, (arrival, diff)]
        offset = clock.update(device, arrival)
        assert device + offset <= arrival  # capture never after arrival
        assert offset == min(d for _, d in seen)
        assert clock.offset_ns == offset
