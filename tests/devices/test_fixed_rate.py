"""FixedRate: the absolute-deadline tick loop the scripted devices share (issue 12 duplicates)."""

from __future__ import annotations

import threading
import time

from telerig.devices.worker import FixedRate, wait_until


def test_ticks_follow_absolute_deadlines_without_drift() -> None:
    rate = FixedRate(200.0)
    stop = threading.Event()
    times: list[float] = []
    for _device_ns, t_s in rate.ticks(stop):
        times.append(t_s)
        if len(times) == 40:
            stop.set()
    # Tick k lands at or after k / rate; absolute deadlines keep the last one near 39 / 200 s.
    assert all(t >= k / 200.0 - 1e-4 for k, t in enumerate(times))
    assert times[-1] < 39 / 200.0 + 0.05


def test_a_late_tick_skips_ahead_and_counts_overruns_instead_of_bursting() -> None:
    rate = FixedRate(100.0)
    stop = threading.Event()
    times: list[float] = []
    for _device_ns, t_s in rate.ticks(stop):
        times.append(t_s)
        if len(times) == 1:
            time.sleep(0.052)  # more than five periods late
        if len(times) == 3:
            stop.set()
    assert rate.overruns >= 4
    # Ticks 1..4 are skipped, not fired in a burst: the third tick waits for deadline 6 / 100 s.
    assert times[2] >= 0.06 - 1e-4


def test_a_set_stop_event_ends_the_loop_before_the_first_tick() -> None:
    stop = threading.Event()
    stop.set()
    assert list(FixedRate(50.0).ticks(stop)) == []


def test_device_ns_is_the_perf_counter_of_the_tick() -> None:
    stop = threading.Event()
    before = time.perf_counter_ns()
    device_ns, _t = next(iter(FixedRate(1000.0).ticks(stop)))
    assert before <= device_ns <= time.perf_counter_ns()


def test_wait_until_sleeps_to_the_deadline_and_says_whether_stopped() -> None:
    stop = threading.Event()
    deadline = time.perf_counter() + 0.02
    assert not wait_until(deadline, stop)
    assert time.perf_counter() >= deadline
    stop.set()
    began = time.perf_counter()
    assert wait_until(began + 5.0, stop)  # a set event returns at once
    assert time.perf_counter() - began < 1.0
