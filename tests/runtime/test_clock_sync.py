"""Clock sync: exchange arithmetic, lowest-delay filtering, drift fit, and the ping/pong protocol."""

from __future__ import annotations

import json
import time
from typing import Any

import pytest

from telerig.bus.memory import InMemoryBus
from telerig.errors import TelerigError
from telerig.runtime.clock_sync import (
    ClockSample,
    ClockSync,
    ClockSyncClient,
    ClockSyncServer,
    offset_clock,
)

MS = 1_000_000
S = 1_000_000_000


def _exchange(local_t1: int, offset: int, up: int, down: int, turnaround: int = 10_000) -> ClockSample:
    """An exchange starting at station time ``local_t1`` with true offset ``offset`` and leg delays [ns]."""
    t2 = local_t1 + offset + up
    t3 = t2 + turnaround
    t4 = t3 - offset + down
    return ClockSample(local_t1, t2, t3, t4)


def test_exchange_offset_and_delay_follow_the_ntp_formulas() -> None:
    s = ClockSample(t1=100, t2=1_150, t3=1_160, t4=230)
    assert s.offset_ns == ((1_150 - 100) + (1_160 - 230)) // 2
    assert s.delay_ns == (230 - 100) - (1_160 - 1_150)


def test_symmetric_legs_give_the_exact_offset() -> None:
    sync = ClockSync()
    sync.add(_exchange(5 * S, offset=-250 * MS, up=300_000, down=300_000))
    assert sync.offset_ns == -250 * MS
    assert sync.to_coordinator(6 * S) == 6 * S - 250 * MS


def test_the_lowest_delay_exchange_wins_over_slow_asymmetric_ones() -> None:
    sync = ClockSync(best=1)
    for i in range(10):
        sync.add(_exchange(i * 100 * MS, offset=7 * MS, up=5 * MS, down=100_000))  # queued on the way up
    sync.add(_exchange(S + 1, offset=7 * MS, up=50_000, down=50_000))
    assert sync.offset_ns == 7 * MS
    assert sync.estimate.delay_ns == 100_000
    assert sync.uncertainty_ns == 50_000


def test_drift_is_fitted_once_the_window_spans_enough_time() -> None:
    drift_ppm = 40.0
    sync = ClockSync(window=64, best=16, min_drift_span_s=10.0)
    for i in range(60):  # 30 s at 2 Hz
        local = 1_000 * S + i * 500 * MS
        offset = 3 * MS + round(drift_ppm * 1e-6 * (local - 1_000 * S))
        jitter = (i * 7919) % 40_000  # deterministic queueing noise [ns]
        sync.add(_exchange(local, offset=offset, up=100_000 + jitter, down=100_000))
    assert sync.drift_ppm == pytest.approx(drift_ppm, abs=2.0)
    later = 1_040 * S
    truth = later + 3 * MS + round(drift_ppm * 1e-6 * (later - 1_000 * S))
    assert abs(sync.to_coordinator(later) - truth) < 100_000
    assert abs(sync.to_local(truth) - later) < 100_000


def test_drift_stays_zero_within_a_short_burst() -> None:
    sync = ClockSync(min_drift_span_s=10.0)
    for i in range(8):
        sync.add(_exchange(i * 20 * MS, offset=i * 1_000, up=100_000, down=100_000))
    assert sync.drift_ppm == 0.0


def test_to_coordinator_before_any_exchange_says_to_wait() -> None:
    sync = ClockSync()
    assert not sync.synced
    with pytest.raises(TelerigError, match="wait_synced"):
        sync.to_coordinator(0)


def test_an_exchange_with_negative_delay_is_rejected() -> None:
    sync = ClockSync()
    sync.add(ClockSample(t1=1_000, t2=0, t3=5_000, t4=1_100))
    assert (sync.rejected, sync.synced) == (1, False)


def test_old_exchanges_leave_the_window() -> None:
    sync = ClockSync(window_s=10.0, best=1)
    sync.add(_exchange(0, offset=MS, up=10_000, down=10_000))  # fastest, but stale soon
    sync.add(_exchange(20 * S, offset=2 * MS, up=500_000, down=500_000))
    assert sync.estimate.samples == 1
    assert sync.offset_ns == 2 * MS


def test_estimate_exports_json_and_mcap_metadata() -> None:
    sync = ClockSync()
    sync.add(_exchange(S, offset=MS, up=1_000, down=1_000))
    record = sync.estimate.as_dict()
    assert json.loads(json.dumps(record)) == record
    assert record["offset_ns"] == MS
    metadata = sync.estimate.as_mcap_metadata()
    assert all(isinstance(v, str) for v in metadata.values())
    assert json.loads(metadata["offset_ns"]) == MS


def test_client_and_server_estimate_a_fake_offset_over_the_bus() -> None:
    bus = InMemoryBus()
    server = ClockSyncServer(bus, "demo").start()
    with ClockSyncClient(bus, "demo", "s1", clock=offset_clock(250 * MS), rate_hz=100.0) as client:
        assert client.wait_synced(2.0)
    assert client.received >= 1
    assert server.answered >= client.received
    # In-process delivery: both legs take microseconds, so the estimate is within a millisecond.
    assert abs(client.sync.offset_ns - (-250 * MS)) < MS
    assert client.record()["station"] == "s1"


def test_server_drops_malformed_pings_and_client_ignores_foreign_pongs() -> None:
    bus = InMemoryBus()
    server = ClockSyncServer(bus, "demo").start()
    bus.publish("telerig/v1/demo/s1/clock_ping", b"not json")
    bus.publish("telerig/v1/demo/s1/clock_ping", json.dumps({"seq": 1, "t1": "x"}).encode())
    assert (server.malformed, server.answered) == (2, 0)
    client = ClockSyncClient(bus, "demo", "s1")
    client.start()
    try:
        client.wait_synced(2.0)
        bus.publish(
            "telerig/v1/demo/s1/clock_pong", json.dumps({"seq": 999, "t1": 1, "t2": 2, "t3": 3}).encode()
        )
        assert client.ignored >= 1
    finally:
        client.close()
        server.close()


def test_client_rejects_bad_rates() -> None:
    with pytest.raises(ValueError, match="rate_hz > 0"):
        ClockSyncClient(InMemoryBus(), "demo", "s1", rate_hz=0)


def test_deeply_nested_json_pings_and_pongs_are_counted_not_raised(make_bus: Any) -> None:
    """Over Mosquitto: 100 000-deep JSON on clock_ping / clock_pong is a counted drop, no RecursionError."""
    server_bus, client_bus, forger = make_bus("coordinator"), make_bus("station"), make_bus("forger")
    deep = b"[" * 100_000 + b"]" * 100_000
    with (
        ClockSyncServer(server_bus, "rig") as server,
        ClockSyncClient(client_bus, "rig", "st1", burst=3) as client,
    ):
        assert client.wait_synced(10.0)  # both subscriptions are live: the forgeries reach them
        forger.publish("telerig/v1/rig/st1/clock_pong", deep, qos=1)
        forger.publish("telerig/v1/rig/st2/clock_ping", deep, qos=1)
        forger.publish("telerig/v1/rig/st1/clock_pong", b'[{"seq": 1}]', qos=1)  # not an object
        deadline = time.monotonic() + 15.0
        while time.monotonic() < deadline and (server.malformed < 1 or client.ignored < 2):
            time.sleep(0.01)
    assert server_bus.stats.handler_errors == 0
    assert client_bus.stats.handler_errors == 0
    assert server.malformed == 1
    assert client.ignored >= 2  # the deep one and the array (a late real pong may add one)
