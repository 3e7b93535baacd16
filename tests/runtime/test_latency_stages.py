"""Latency per stage of the operator loop (issue 17): the control node's stage rows in a real rig run.

The demo rig runs through its embedded Mosquitto with its scripted VR device's capture stamps set
back by a known delay (a slow tracker): each applied command's stamps are monotonic, its stages add
up to its end-to-end latency, the delay shows in the ``receive`` stage and nowhere else, the stage
over its budget raises its alert on ``<robot>/alerts``, and the ``latency`` and ``alerts`` streams
are in the recorded episode.
"""

from __future__ import annotations

import dataclasses
import json
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader

from telerig.bus.memory import InMemoryBus
from telerig.bus.mqtt import MqttBus
from telerig.bus.topics import Topic
from telerig.config import load_rig
from telerig.config.latency import ROBOT_STAGES, VIDEO_STAGES, LatencyConfig
from telerig.devices.base import Device, SampleSink
from telerig.ir.types import Sample
from telerig.runtime.control_health import ALERT_CODE, MIN_COUNT, STAGES_TYPE, ControlHealth
from telerig.runtime.metrics import LatencyWindow
from telerig.runtime.rig import RigRuntime

MS = 1_000_000


def test_stage_rows_split_each_sample_and_add_up_to_its_total() -> None:
    window = LatencyWindow(1.0, 16, stages=("a", "b", "c"))
    window.add_stamps(1_000 * MS, 990 * MS, 991 * MS, 995 * MS, 996 * MS)
    window.add_stamps(1_001 * MS, 990 * MS, 989 * MS, 995 * MS, 999 * MS)  # b before a: out of order
    s = window.stage_summary(1_001 * MS)
    assert s.stages["a"].count == 2
    assert s.stages["b"].max_ms == pytest.approx(6.0)
    assert s.total.max_ms == pytest.approx(9.0)
    assert s.out_of_order == 1
    assert window.stage_summary(3_000 * MS).total.count == 0
    with pytest.raises(ValueError, match="give 4 stamps"):
        window.add_stamps(1_000 * MS, 1, 2)


def test_a_stage_over_budget_raises_its_alert_and_clears_it() -> None:
    bus = InMemoryBus()
    alerts: list[dict[str, Any]] = []
    bus.subscribe(str(Topic("r", "arm0", "alerts")), lambda m: alerts.append(json.loads(m.payload)))
    t = [10_000 * MS]
    health = ControlHealth("r", "arm0", bus, clock=lambda: t[0], budgets_ms={"bus": 2.0})
    for i in range(MIN_COUNT):  # the bus stage takes 3 ms, over its 2 ms budget; the rest 0.5 ms
        c = 9_000 * MS + i * 10 * MS
        stamps = [c + k * MS // 2 for k in range(7)]
        stamps[2:] = [s + 3 * MS for s in stamps[2:]]
        health.sent(
            stamps[0],
            stamps[5],
            stamps[3],
            arrival_ns=stamps[1],
            received_ns=stamps[2],
            retargeted_ns=stamps[4],
        )
        health.measured(stamps[6], 9_500 * MS + i)
    health.publish()
    health.publish()  # unchanged: not published again
    assert len(alerts) == 1
    (alert,) = alerts[0]["active_alerts"]
    assert alert["code"] == ALERT_CODE
    assert alert["stage"] == "bus"
    assert alert["robot"] == "arm0"
    assert "over its 2 ms budget" in alert["reason"]
    assert alert["suggested_action"]
    report = health.stage_report()
    assert report["type"] == STAGES_TYPE
    assert report["stages"]["bus"]["p50_ms"] == pytest.approx(3.5)  # type: ignore[index]
    t[0] = 20_000 * MS  # the window moved on: back under budget (no commands), the alert clears
    health.publish()
    assert len(alerts) == 2
    assert alerts[1]["active_alerts"] == []


class _SetBack:
    """The demo rig's own device with every capture stamp set back by ``delay_ns`` (a slow tracker)."""

    def __init__(self, inner: Device, delay_ns: int) -> None:
        self._inner = inner
        self._delay_ns = delay_ns

    @property
    def id(self) -> str:
        return self._inner.id

    def start(self, sink: SampleSink) -> None:
        def late(sample: Sample) -> None:
            stamp = dataclasses.replace(sample.stamp, capture_ns=sample.stamp.capture_ns - self._delay_ns)
            sink(dataclasses.replace(sample, stamp=stamp))

        self._inner.start(late)

    def stop(self) -> None:
        self._inner.stop()


@pytest.mark.sim
@pytest.mark.broker
@pytest.mark.slow
def test_stages_of_a_real_rig_are_monotonic_add_up_and_put_the_delay_in_receive(tmp_path: Path) -> None:
    delay_ms = 30.0
    # receive is judged by 10 ms (the delay is over it); the other stages get room for a loaded host.
    budgets = dict.fromkeys((*ROBOT_STAGES, "end_to_end"), 1000.0) | {"receive": 10.0}
    rig = (
        load_rig("demo")
        .with_isolation("threads")
        .model_copy(  # its device node delays, here
            update={"cameras": [], "latency": LatencyConfig.model_validate({"budgets_ms": budgets})}
        )
    )
    reports: list[tuple[float, dict[str, Any]]] = []
    alerts: list[dict[str, Any]] = []
    with RigRuntime(rig, data_root=tmp_path) as runtime:
        node = runtime.devices["vr0"]
        node.swap(_SetBack(node.device, round(delay_ms * MS)))
        assert runtime.broker_url is not None
        watcher = MqttBus(runtime.broker_url, client_id="stage-watcher").connect()
        try:
            watcher.subscribe(
                str(Topic(rig.name, "arm0", "latency")),
                lambda m: reports.append((time.monotonic(), json.loads(m.payload))),
                qos=1,
            )
            watcher.subscribe(
                str(Topic(rig.name, "arm0", "alerts")), lambda m: alerts.append(json.loads(m.payload)), qos=1
            )
            live = runtime.controls["arm0"].live
            seen: list[np.ndarray] = []
            done = threading.Event()

            def sample_rows() -> None:  # the 2 s window, read while the episode runs
                while not done.wait(0.25):
                    seen.append(live.stages.rows(time.time_ns()))

            sampler = threading.Thread(target=sample_rows)
            sampler.start()
            t0 = time.monotonic()
            try:
                result = runtime.run_episode(3.0)
            finally:
                t1 = time.monotonic()
                done.set()
                sampler.join()
        finally:
            watcher.close()

    rows = np.unique(np.concatenate(seen), axis=0)
    # Every applied command's stamps, in the order of the stages: never earlier than the one before.
    assert rows.shape[0] > 20  # ~250 on a quiet host; a host at load 20 gave 40
    assert rows.shape[1] == len(ROBOT_STAGES) + 1
    steps = np.diff(rows, axis=1)
    assert (steps >= 0).all(), rows[(steps < 0).any(axis=1)][:3]
    receive, rest = steps[:, 0] / MS, steps[:, 1:].sum(axis=1) / MS
    # The delay is in the receive stage (capture -> device node) and not in the later ones.
    assert np.median(receive) == pytest.approx(delay_ms, abs=3.0)
    assert np.median(rest) < 40.0

    during = [doc for t, doc in reports if t0 + 1.0 < t <= t1]
    assert during, f"no report on arm0/latency during the episode ({len(reports)} in all)"
    doc = during[-1]
    assert doc["out_of_order"] == 0
    stages, e2e = doc["stages"], doc["end_to_end"]
    assert list(stages) == list(ROBOT_STAGES)
    assert e2e["count"] > 10
    # The stages' medians add up to the end-to-end median within a tolerance (medians of parts are
    # not the median of the sum; the rows themselves add up exactly, checked above).
    total_p50 = sum(s["p50_ms"] for s in stages.values())
    assert total_p50 == pytest.approx(e2e["p50_ms"], rel=0.2, abs=2.0), (stages, e2e)
    assert e2e["p50_ms"] >= delay_ms
    assert stages["receive"]["over"] is True
    assert stages["receive"]["budget_ms"] == 10.0
    assert not any(s["over"] for name, s in stages.items() if name != "receive")
    # The receive stage's alert was raised, and only it.
    raised = [a for doc in alerts for a in doc["active_alerts"]]
    assert {a["stage"] for a in raised} == {"receive"}, alerts
    # Bounded rate: ~2 Hz, whatever the 100 Hz control loop does.
    rate = len([t for t, _ in reports if t0 <= t <= t1]) / (t1 - t0)
    assert 1.0 <= rate <= 2.6, rate

    # Recorded: the episode's MCAP has the latency reports and the alert.
    with open(result.path / "episode.mcap", "rb") as f:
        topics = [channel.topic for _, channel, _ in make_reader(f).iter_messages()]
    assert topics.count(str(Topic(rig.name, "arm0", "latency"))) >= 3
    assert str(Topic(rig.name, "arm0", "alerts")) in topics


@pytest.mark.parametrize(
    ("budgets", "error"),
    [
        ({"bogus": 3.0}, "'receive', 'bus'"),  # names the valid stages
        ({"bus": 0.0}, "greater than 0"),
        ({"bus": -5.0}, "greater than 0"),
        ({"bus": float("inf")}, "finite number"),
        ({"bus": float("nan")}, "finite number"),
        ({"bus": 1e9}, "less than or equal to 60000"),
        ({"bus": "fast"}, "valid number"),
    ],
)
def test_a_wrong_budget_in_the_rig_file_fails_naming_the_field(
    budgets: dict[str, object], error: str
) -> None:
    with pytest.raises(ValueError, match=r"latency\.budgets_ms") as failed:
        load_rig("demo").model_validate({**load_rig("demo").model_dump(), "latency": {"budgets_ms": budgets}})
    assert error in str(failed.value)


def test_budgets_not_given_keep_their_defaults() -> None:
    config = LatencyConfig.model_validate({"budgets_ms": {"bus": 2.5}})
    assert config.budget_ms("bus") == 2.5
    assert config.budget_ms("state") == 20.0
    assert set(config.budgets()) == {*ROBOT_STAGES, "rendered", "end_to_end", *VIDEO_STAGES}
