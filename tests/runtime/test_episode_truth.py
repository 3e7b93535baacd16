"""Manifests tell the truth (issue 11 finding 6): safety counters and events of the episode only, and
an episode whose bound device delivered nothing is incomplete, with a warning naming the device and
the address it waited on."""

from __future__ import annotations

import logging
import math
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from telerig.bus.mqtt import MqttBus
from telerig.bus.topics import Topic
from telerig.config import load_rig
from telerig.devices.udp_vr.config import UdpVrConfig
from telerig.ir import wire
from telerig.ir.types import ControllerState, Stamp, now_ns
from telerig.runtime.rig import RigRuntime
from telerig.store.episodes import EpisodeStore
from telerig.store.manifest_extra import EpisodeExtra

pytestmark = [pytest.mark.sim, pytest.mark.broker, pytest.mark.slow]


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_safety_counters_and_events_are_those_of_the_episode(tmp_path: Path) -> None:
    # In this process: the tests reach into the robot's control node.
    rig = load_rig("demo").with_isolation("threads").model_copy(update={"cameras": []})
    with RigRuntime(rig, data_root=tmp_path) as runtime:
        control = runtime.controls["arm0"]
        fault = threading.Timer(1.0, lambda: control.fault("encoder error (injected)"))
        fault.start()
        first = runtime.run_episode(2.0)
        fault.join()
        assert runtime.supervisor is not None
        runtime.supervisor.reset()
        second = runtime.run_episode(2.0)
    store = EpisodeStore(tmp_path)
    one, two = (EpisodeExtra.of(store.get(r.episode_id)) for r in (first, second))
    assert one.safety_events["arm0"]["driver_fault"] == 1
    assert two.safety_events["arm0"]["driver_fault"] == 0  # was a running total: 1 again
    faults = [e for e in one.safety_log if e.code == "driver_fault"]
    assert [(e.robot, e.code) for e in faults] == [("arm0", "driver_fault")]
    assert "encoder error (injected)" in faults[0].reason
    assert not [e for e in two.safety_log if e.code == "driver_fault"]


def test_a_bound_device_that_delivers_nothing_makes_the_episode_incomplete_and_names_its_address(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    port = _free_udp_port()
    demo = load_rig("demo").with_isolation("threads")  # the device's warnings are logged here
    silent = UdpVrConfig(id="vr0", port=port)  # no headset app sends to it
    rig = demo.model_copy(update={"cameras": [], "devices": [silent]})
    with caplog.at_level(logging.WARNING), RigRuntime(rig, data_root=tmp_path) as runtime:
        result = runtime.run_episode(1.5)
    assert result.status == "incomplete"
    manifest = EpisodeStore(tmp_path).get(result.episode_id, include_unfinished=True)
    assert manifest.reason is not None
    assert "vr0/right_controller" in manifest.reason
    assert f"127.0.0.1:{port}" in manifest.reason
    assert EpisodeExtra.of(manifest).missing_streams == {
        "telerig/v1/demo/vr0/right_controller": f"127.0.0.1:{port}"
    }
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert any("vr0" in w and f"127.0.0.1:{port}" in w for w in warnings)


def test_rejected_inputs_and_tick_faults_are_counted_per_episode_in_the_manifest(tmp_path: Path) -> None:
    rig = load_rig("demo").with_isolation("threads").model_copy(update={"cameras": []})
    topic = str(Topic(rig.name, "vr0", "right_controller"))
    with RigRuntime(rig, data_root=tmp_path) as runtime:
        assert runtime.broker_url is not None
        forger = MqttBus(runtime.broker_url, client_id="forger").connect()
        try:

            def poison() -> None:
                for seq in range(5):
                    stamp = Stamp(source_id="vr0/right", seq=10**6 + seq, device_ns=0, capture_ns=now_ns())
                    bad = ControllerState(
                        stamp,
                        "right",
                        np.array([math.nan, 0.0, 0.0]),
                        np.array([1.0, 0.0, 0.0, 0.0]),
                        "operator",
                    )
                    forger.publish(topic, wire.encode(bad))
                    time.sleep(0.02)

            timer = threading.Timer(0.8, poison)
            timer.start()
            first = runtime.run_episode(2.0)
            timer.join()
            second = runtime.run_episode(1.5)
        finally:
            forger.close()
    store = EpisodeStore(tmp_path)
    one, two = (EpisodeExtra.of(store.get(r.episode_id)) for r in (first, second))
    assert one.input_rejected["arm0"].get("non_finite", 0) >= 1
    assert two.input_rejected["arm0"] == {}  # counted for the episode it happened in only
    assert one.tick_faults == {"arm0": 0}
    assert two.tick_faults == {"arm0": 0}


def test_the_watchdog_stop_after_the_devices_stop_is_not_the_episodes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # After the recording window the devices stop, and each robot's watchdog stops it 250 ms
    # later. Reading a long episode's log for its instruction count took longer than that, so the
    # counters read after it took the stop in: every 20 s pick_place demonstration had one
    # watchdog_stop and one input_stale and the gates rejected it. Here the read takes 0.6 s.
    from telerig.runtime import recording

    read = recording._instructions

    def slow(*args: object, **kwargs: object) -> object:
        time.sleep(0.6)
        return read(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(recording, "_instructions", slow)
    rig = load_rig("demo").with_isolation("threads").model_copy(update={"cameras": []})
    with RigRuntime(rig, data_root=tmp_path) as runtime:
        result = runtime.run_episode(2.0)
        after = dict(runtime.controls["arm0"].safety.counts)
    events = EpisodeExtra.of(EpisodeStore(tmp_path).get(result.episode_id)).safety_events["arm0"]
    assert after.get("watchdog_stop", 0) >= 1, after  # the stop happened, after the episode
    assert events["watchdog_stop"] == 0, events
    assert events["input_stale"] == 0, events
