"""Stream health monitor: rates, gaps, drops, overflow, and stall alerts within a second."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable
from typing import Any

import pytest

from telerig.bus.base import Message
from telerig.bus.memory import InMemoryBus
from telerig.errors import ConfigError
from telerig.ir import wire
from telerig.ir.types import JointCommand, JointState, Stamp, now_ns
from telerig.record.health import StreamHealthMonitor

RIG = "test"
JOINTS = "telerig/v1/test/arm/joint_state"
HEAD = "telerig/v1/test/vr0/head"
ALERTS = "telerig/v1/test/recorder/alerts"
HEALTH = "telerig/v1/test/recorder/health"
MS = 1_000_000
S = 1_000_000_000
T0 = 1_700_000_000 * S


class Clock:
    """Injected common clock [ns]."""

    def __init__(self) -> None:
        self.now = T0

    def __call__(self) -> int:
        return self.now


class Listener:
    """Collects the JSON published on one topic."""

    def __init__(self, bus: InMemoryBus, topic: str) -> None:
        self.docs: list[dict[str, Any]] = []
        bus.subscribe(topic, lambda m: self.docs.append(json.loads(m.payload)))


def _monitor(bus: InMemoryBus, clock: Clock, **options: Any) -> StreamHealthMonitor:
    rates = options.pop("expected_rates", {JOINTS: 100.0})
    monitor = StreamHealthMonitor(RIG, "recorder", bus, rates, check_interval_s=None, clock=clock, **options)
    monitor.start()
    return monitor


def _feed(
    monitor: StreamHealthMonitor,
    clock: Clock,
    seconds: float,
    *,
    hz: float = 100.0,
    topic: str = JOINTS,
    seq0: int = 0,
    skip: Callable[[int], bool] = lambda i: False,
) -> int:
    """Deliver ``seconds`` of a stream at ``hz``, ticking every 50 ms; returns the next seq."""
    period = round(S / hz)
    start = clock.now
    n = round(seconds * hz)
    next_tick = start
    for i in range(n):
        clock.now = start + i * period
        if not skip(seq0 + i):
            monitor.observe(topic, capture_ns=clock.now, seq=seq0 + i, received_ns=clock.now)
        if clock.now >= next_tick:
            monitor.tick()
            next_tick += 50 * MS
    clock.now = start + n * period
    return seq0 + n


def _silence(monitor: StreamHealthMonitor, clock: Clock, seconds: float) -> list[int]:
    """Advance time without messages, ticking every 50 ms; returns the tick times that raised alerts."""
    raised = []
    for _ in range(round(seconds / 0.05)):
        clock.now += 50 * MS
        if any(a.active for a in monitor.tick()):
            raised.append(clock.now)
    return raised


def test_stalled_stream_raises_an_alert_within_one_second() -> None:
    bus, clock = InMemoryBus(), Clock()
    alerts = Listener(bus, ALERTS)
    monitor = _monitor(bus, clock)
    _feed(monitor, clock, 1.0)
    last = clock.now - 10 * MS
    raised = _silence(monitor, clock, 2.0)
    assert len(raised) == 1
    assert raised[0] - last <= 1 * S
    doc = alerts.docs[-1]
    assert {k: doc[k] for k in ("code", "stream", "severity", "since_ns", "active")} == {
        "code": "stream_stalled",
        "stream": JOINTS,
        "severity": "error",
        "since_ns": last,
        "active": True,
    }
    assert doc["reason"].startswith(f"no message on {JOINTS}")
    assert "arm" in doc["suggested_action"]


def test_stall_threshold_is_three_periods_with_a_200_ms_floor() -> None:
    bus, clock = InMemoryBus(), Clock()
    monitor = _monitor(bus, clock, expected_rates={JOINTS: 100.0, HEAD: 2.0})
    _feed(monitor, clock, 1.0)
    start = clock.now - 10 * MS  # the last joint message
    monitor.observe(HEAD, capture_ns=start, seq=0, received_ns=start)
    clock.now = start + 200 * MS
    assert monitor.tick() == []
    clock.now = start + 201 * MS
    assert [a.stream for a in monitor.tick()] == [JOINTS]
    clock.now = start + 1500 * MS
    assert monitor.tick() == []
    clock.now = start + 1501 * MS
    assert [a.stream for a in monitor.tick()] == [HEAD]


def test_a_few_lost_samples_do_not_alert() -> None:
    bus, clock = InMemoryBus(), Clock()
    alerts = Listener(bus, ALERTS)
    monitor = _monitor(bus, clock)
    _feed(monitor, clock, 2.0, skip=lambda i: 100 <= i < 115)  # a 150 ms hole
    assert alerts.docs == []


def test_recovery_publishes_a_cleared_alert() -> None:
    bus, clock = InMemoryBus(), Clock()
    alerts = Listener(bus, ALERTS)
    monitor = _monitor(bus, clock)
    seq = _feed(monitor, clock, 1.0)
    _silence(monitor, clock, 1.0)
    resumed = clock.now
    _feed(monitor, clock, 0.5, seq0=seq)
    cleared = alerts.docs[-1]
    assert (cleared["code"], cleared["active"], cleared["cleared_ns"]) == ("stream_stalled", False, resumed)
    assert cleared["active_alerts"] == []
    assert monitor.active_alerts() == []


def test_late_subscriber_sees_every_active_alert_in_the_retained_message() -> None:
    bus, clock = InMemoryBus(), Clock()
    monitor = _monitor(bus, clock, expected_rates={JOINTS: 100.0, HEAD: 100.0})
    for i in range(10):
        clock.now += 10 * MS
        monitor.observe(JOINTS, capture_ns=clock.now, seq=i, received_ns=clock.now)
        monitor.observe(HEAD, capture_ns=clock.now, seq=i, received_ns=clock.now)
    _silence(monitor, clock, 0.5)
    late = Listener(bus, ALERTS)
    assert len(late.docs) == 1
    assert sorted(a["stream"] for a in late.docs[0]["active_alerts"]) == [JOINTS, HEAD]


def test_rates_are_measured_over_the_window() -> None:
    bus, clock = InMemoryBus(), Clock()
    monitor = _monitor(bus, clock, window_s=2.0)
    _feed(monitor, clock, 3.0, hz=70.0)
    health = monitor.health()[JOINTS]
    assert health.measured_hz == pytest.approx(70.0, rel=0.01)
    assert (health.state, health.expected_hz, health.drops, health.gaps) == ("degraded", 100.0, 0, 0)


def test_drops_come_from_sequence_gaps() -> None:
    bus, clock = InMemoryBus(), Clock()
    monitor = _monitor(bus, clock)
    _feed(monitor, clock, 1.0, skip=lambda i: i in (10, 11, 12, 50))
    assert monitor.health()[JOINTS].drops == 4
    summary: Any = monitor.summary()
    assert summary["streams"][JOINTS]["drops"] == 4


def test_gaps_count_intervals_over_twice_the_period() -> None:
    bus, clock = InMemoryBus(), Clock()
    monitor = _monitor(bus, clock)
    _feed(monitor, clock, 1.0, skip=lambda i: i in (10, 50, 51, 80, 81, 82))
    health = monitor.health()[JOINTS]
    assert (health.gaps, health.max_gap_ms) == (2, pytest.approx(40.0))


def test_health_is_published_once_a_second() -> None:
    bus, clock = InMemoryBus(), Clock()
    reports = Listener(bus, HEALTH)
    monitor = _monitor(bus, clock)
    _feed(monitor, clock, 3.0)
    assert len(reports.docs) == 3
    doc = reports.docs[-1]
    assert doc["type"] == "stream_health"
    assert doc["streams"][JOINTS]["state"] == "ok"


def test_expected_stream_that_never_starts_is_missing_after_the_grace() -> None:
    bus, clock = InMemoryBus(), Clock()
    monitor = _monitor(bus, clock, startup_grace_s=1.0)
    clock.now += 1000 * MS
    assert monitor.tick() == []
    clock.now += 1 * MS
    assert [(a.code, a.since_ns) for a in monitor.tick()] == [("stream_missing", T0)]
    assert monitor.health()[JOINTS].state == "waiting"


def test_queue_overflow_alerts_then_clears_after_a_quiet_window() -> None:
    bus, clock = InMemoryBus(), Clock()
    overflow = [0]
    monitor = StreamHealthMonitor(RIG, "recorder", bus, {}, window_s=1.0, check_interval_s=None, clock=clock)
    monitor.watch_counter("recorder.inbox_overflow", lambda: overflow[0])
    monitor.start()
    assert monitor.tick() == []
    clock.now += 100 * MS
    overflow[0] = 5
    assert [(a.code, a.severity, a.active) for a in monitor.tick()] == [("queue_overflow", "warning", True)]
    clock.now += 900 * MS
    assert monitor.tick() == []
    clock.now += 200 * MS
    assert [(a.code, a.active) for a in monitor.tick()] == [("queue_overflow", False)]
    monitor.stop()
    overflow[0] = 9  # after the episode: not counted in it
    assert monitor.summary()["overflow"] == {"recorder.inbox_overflow": 5}


def test_stop_clears_active_alerts() -> None:
    bus, clock = InMemoryBus(), Clock()
    alerts = Listener(bus, ALERTS)
    monitor = _monitor(bus, clock)
    _feed(monitor, clock, 0.5)
    _silence(monitor, clock, 0.5)
    monitor.stop()
    assert (alerts.docs[-1]["active"], alerts.docs[-1]["active_alerts"]) == (False, [])
    monitor.stop()  # idempotent


def test_summary_is_json_for_the_manifest() -> None:
    bus, clock = InMemoryBus(), Clock()
    monitor = _monitor(bus, clock)
    seq = _feed(monitor, clock, 1.0)
    _silence(monitor, clock, 1.0)
    _feed(monitor, clock, 1.0, seq0=seq)
    monitor.stop()
    summary: Any = monitor.summary()
    json.dumps(summary, allow_nan=False)
    joints = summary["streams"][JOINTS]
    assert (joints["messages"], joints["stalls"], joints["drops"]) == (200, 1, 0)
    assert joints["stalled_s"] == pytest.approx(1.0, abs=0.02)
    assert [(a["code"], a["active"]) for a in summary["alerts"]] == [
        ("stream_stalled", True),
        ("stream_stalled", False),
    ]


def test_observe_message_counts_no_drop_where_a_command_skips_its_inputs_seq() -> None:
    # A requested command carries its input's stamp: a skipped seq is an input the loop superseded.
    bus, clock = InMemoryBus(), Clock()
    monitor = _monitor(bus, clock)
    requested, sent = "telerig/v1/test/arm/joint_command_requested", "telerig/v1/test/arm/joint_command_sent"
    for seq in (0, 1, 3):
        t = T0 + seq * 10_000_000
        command = JointCommand(Stamp("vr0/right", seq, t, t), ("j1",), (0.0,))
        monitor.observe_message(Message(requested, wire.encode(command), t))
        own = JointCommand(Stamp("arm", seq, t, t), ("j1",), (0.0,))
        monitor.observe_message(Message(sent, wire.encode(own), t))
    streams = monitor.summary()["streams"]
    assert (streams[requested]["messages"], streams[requested]["drops"]) == (3, 0)
    assert (streams[sent]["messages"], streams[sent]["drops"]) == (3, 1)


def test_observe_message_ignores_json_state_messages() -> None:
    bus, clock = InMemoryBus(), Clock()
    monitor = _monitor(bus, clock)
    sample = JointState(Stamp("arm", 7, T0, T0), ("j1",), (0.0,), (0.0,))
    monitor.observe_message(Message(JOINTS, wire.encode(sample), T0))
    monitor.observe_message(Message("telerig/v1/test/arm/status", b'{"ok":true}', T0))
    assert monitor.summary()["streams"] == {
        JOINTS: {
            "expected_hz": 100.0,
            "measured_hz": 0.0,
            "messages": 1,
            "drops": 0,
            "gaps": 0,
            "max_gap_ms": 0.0,
            "stalls": 0,
            "stalled_s": 0.0,
        }
    }


@pytest.mark.parametrize("option", ["window_s", "min_stall_s", "publish_interval_s"])
def test_non_positive_settings_are_rejected(option: str) -> None:
    with pytest.raises(ConfigError, match=f"{option} must be > 0"):
        StreamHealthMonitor(RIG, "recorder", InMemoryBus(), **{option: 0.0})


@pytest.mark.broker
def test_alert_reaches_a_subscriber_within_a_second_of_the_publisher_stopping(make_bus: Any) -> None:
    publisher, recorder, dashboard = make_bus("pub"), make_bus("rec"), make_bus("dash")
    arrived = threading.Event()
    arrival: list[int] = []

    def on_alert(message: Message) -> None:
        doc = json.loads(message.payload)
        if doc["code"] == "stream_stalled" and doc["active"]:
            arrival.append(now_ns())
            arrived.set()

    dashboard.subscribe(ALERTS, on_alert, qos=1)
    monitor = StreamHealthMonitor(RIG, "recorder", recorder, {JOINTS: 100.0})
    recorder.subscribe("telerig/v1/test/+/+", monitor.observe_message)
    with monitor:
        last = 0
        for i in range(50):
            last = now_ns()
            publisher.publish(
                JOINTS, wire.encode(JointState(Stamp("arm", i, last, last), ("j1",), (0.0,), (0.0,)))
            )
            time.sleep(0.01)
        assert arrived.wait(5.0), "no stream_stalled alert within 5 s"
    assert arrival[0] - last < 1 * S


def test_a_report_being_written_never_holds_up_a_message_being_counted(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The recorder's delivery thread counts every message under the monitor's lock; the monitor's
    own thread, below it in priority, writes the report. The report's sums run outside the lock:
    a report stuck mid-way (here: waiting on an event) leaves ``observe`` free."""
    clock = Clock()
    monitor = _monitor(InMemoryBus(), clock)
    _feed(monitor, clock, 1.0)
    summing, release = threading.Event(), threading.Event()
    real = monitor._window_counts

    def slow_counts(*args: Any) -> Any:
        summing.set()
        release.wait(5.0)
        return real(*args)

    monkeypatch.setattr(monitor, "_window_counts", slow_counts)
    clock.now += 2 * S  # a report is due
    reporter = threading.Thread(target=monitor.tick)
    reporter.start()
    try:
        assert summing.wait(5.0)
        counted = threading.Thread(
            target=monitor.observe,
            args=(JOINTS,),
            kwargs={"capture_ns": clock.now, "seq": 500, "received_ns": clock.now},
        )
        counted.start()
        counted.join(1.0)
        assert not counted.is_alive(), "observe waited for the report"
    finally:
        release.set()
        reporter.join(5.0)
    assert monitor.summary()["streams"][JOINTS]["messages"] == 101


def test_a_feeder_running_behind_raises_no_stall_for_what_it_still_holds() -> None:
    """The recorder's writer thread observes messages after the bus delivered them: silence is
    measured up to the oldest message it holds (``watch_backlog``), not up to now."""
    bus, clock = InMemoryBus(), Clock()
    monitor = _monitor(bus, clock)
    held: list[int] = []
    monitor.watch_backlog(lambda: held[0] if held else None)
    _feed(monitor, clock, 1.0)
    held.append(clock.now)  # received now, still in the feeder's queue...
    assert _silence(monitor, clock, 1.0) == []  # ...for a second: no stall
    held.clear()  # the feeder caught up and observed nothing newer: the stream is silent
    assert len(_silence(monitor, clock, 0.1)) == 1
