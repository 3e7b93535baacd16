"""Rate, gap and latency meters; they live in :mod:`telerig.bus.metrics` (record and store use them)."""

from telerig.bus.metrics import LatencySummary, LatencyTracker, StreamMeter, StreamSummary

__all__ = ["LatencySummary", "LatencyTracker", "StreamMeter", "StreamSummary"]
