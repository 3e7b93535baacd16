"""Rate, drop and latency meters."""

from __future__ import annotations

import math

import pytest

from telerig.runtime.metrics import LatencyTracker, StreamMeter


def test_stream_meter_rate_from_capture_times() -> None:
    meter = StreamMeter("s", 100.0)
    for i in range(101):
        meter.add(i * 10_000_000, seq=i)
    summary = meter.summary()
    assert summary.measured_hz == pytest.approx(100.0)
    assert summary.drops == 0
    assert summary.max_gap_ms == pytest.approx(10.0)


def test_stream_meter_counts_sequence_gaps_as_drops() -> None:
    meter = StreamMeter("s", 100.0)
    for seq in (0, 1, 2, 5, 6, 10):
        meter.add(seq * 10_000_000, seq=seq)
    assert meter.summary().drops == 5


def test_latency_tracker_percentiles() -> None:
    tracker = LatencyTracker(capacity=1000)
    for ms in range(1, 101):
        tracker.add(ms * 1_000_000)
    s = tracker.summary()
    assert s.count == 100
    assert s.p50_ms == pytest.approx(50.5)
    assert s.max_ms == pytest.approx(100.0)


def test_latency_tracker_keeps_the_newest_values_when_full() -> None:
    tracker = LatencyTracker(capacity=10)
    for i in range(25):
        tracker.add(i)
    assert sorted(tracker.values_ns().tolist()) == list(range(15, 25))


def test_empty_latency_summary_is_nan() -> None:
    assert math.isnan(LatencyTracker().summary().p50_ms)
