"""Robots in processes of their own (``runtime.isolation: processes``): same episodes, same files,
and a fault under ``halt_all`` still halts every robot across processes."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from telerig.bus.mqtt import MqttBus
from telerig.bus.topics import Topic
from telerig.cli.main import main
from telerig.config import load_rig
from telerig.config.latency import ROBOT_STAGES
from telerig.config.schema import RigConfig
from telerig.errors import DeviceError, RobotError
from telerig.ir import wire
from telerig.ir.types import ControllerState, Stamp, now_ns
from telerig.runtime.rig import RigRuntime
from telerig.runtime.robot_host import (
    Estopped,
    Fault,
    HostPlan,
    ReplayDevices,
    StageRows,
    Stats,
    plan_hosts,
)
from telerig.store.episodes import EpisodeStore

pytestmark = [pytest.mark.sim, pytest.mark.broker, pytest.mark.slow]


def _isolated(raw: dict[str, Any]) -> RigConfig:
    raw["runtime"] = {"isolation": "processes"}
    return RigConfig.model_validate(raw)


def _two_arms() -> RigConfig:
    """The demo rig without its camera, twice: arm0 and arm1, each with its own scripted operator."""
    raw = load_rig("demo").model_dump(mode="json")
    raw["cameras"] = []
    vr1 = {**raw["devices"][0], "id": "vr1"}
    raw["devices"].append(vr1)
    raw["robots"].append({**raw["robots"][0], "id": "arm1"})
    raw["bindings"] += [{**b, "device": "vr1", "robot": "arm1"} for b in raw["bindings"]]
    raw["safety"]["policy"] = "halt_all"
    return _isolated(raw)


def test_each_robot_gets_its_devices_and_cameras() -> None:
    rig = load_rig("demo")
    assert plan_hosts(rig, "station0") == [HostPlan("arm0", ("vr0",), ("scene",))]


def test_an_episode_with_the_robot_in_its_own_process_records_everything(tmp_path: Path) -> None:
    rig = _isolated(load_rig("demo").model_dump(mode="json"))
    with RigRuntime(rig, data_root=tmp_path) as runtime:
        assert set(runtime.hosts) == {"arm0"}
        assert not runtime.robots  # the station runs no robot itself
        result = runtime.run_episode(3.0)
        # The robot's per-stage latency rows, read across the process boundary as a station reads
        # its own (benchmarks/latency_stages.py): the commands of the live window, just ended.
        rows = runtime.hosts["arm0"].call(StageRows(time.time_ns()))
        assert runtime.go_home(timeout_s=15.0)
    assert result.status == "complete"
    assert rows.dtype == np.int64
    assert rows.shape[1] == len(ROBOT_STAGES) + 1
    assert rows.shape[0] > 50  # ~100 commands a second, a 2 s window
    end_to_end = rows[:, -1] - rows[:, 0]
    assert (end_to_end > 0).all()
    assert (end_to_end < 1e9).all()
    counts = {s.name.split("/", 3)[-1]: s.messages for s in result.streams}
    assert counts["vr0/right_controller"] > 150
    assert counts["arm0/joint_command_requested"] > 150
    # Written by the robot's process into the episode. The renderer runs below the control loop's
    # priority by design, so a loaded host drops frames first (27 of 90 seen under a full suite).
    assert result.camera_frames["scene"] > 10
    assert (result.path / "cameras" / "scene.mp4").stat().st_size > 0
    assert result.latency.count > 100
    manifest = EpisodeStore(tmp_path).get(result.episode_id)
    safety = manifest.extra["safety_events"]
    assert isinstance(safety, dict)
    assert "arm0" in safety


def test_a_fault_under_halt_all_halts_every_process_and_telerig_safety_resets_them_and_estops_one(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # One test (was two, each starting this rig: two robot processes) since the reset needs the halt.
    rig = _two_arms()
    rig_file = tmp_path / "two_arms.yaml"
    rig_file.write_text(yaml.safe_dump(rig.model_dump(mode="json")))
    with RigRuntime(rig, data_root=tmp_path / "data") as runtime:
        arm0, arm1 = runtime.hosts["arm0"], runtime.hosts["arm1"]
        assert not arm1.call(Estopped())
        # A fault under halt_all in one robot's process halts the robot of the other process.
        arm0.call(Fault("encoder error (injected)"))
        _wait_until(lambda: arm1.call(Estopped()))
        assert arm0.call(Estopped())
        assert arm1.call(Estopped())
        base = ["safety", "--rig", str(rig_file), "--broker", str(runtime.broker_url)]

        # Both robots are in other processes: the reset reaches each over the bus, the CLI
        # confirms from their retained status.
        assert main([base[0], "reset", *base[1:], "--operator", "op7"]) == 0
        assert not arm0.call(Estopped())
        assert not arm1.call(Estopped())
        out = capsys.readouterr().out
        assert "arm0: stopped" in out
        assert "arm1: stopped" in out

        assert main([base[0], "estop", *base[1:], "--robot", "arm1", "--reason", "hand in the cell"]) == 0
        assert arm1.call(Estopped())
        assert not arm0.call(Estopped())  # an operator's e-stop names what it stops
        assert "arm1: estopped" in capsys.readouterr().out

        # A robot the rig does not have is one line naming the valid ones.
        assert main([base[0], "reset", *base[1:], "--robot", "arm7"]) == 2
        assert "--robot 'arm7' is not a robot of rig 'demo'. Valid: arm0, arm1" in capsys.readouterr().err


def _wait_until(condition: Callable[[], object], timeout_s: float = 5.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.05)


@pytest.fixture(scope="class")
def one_arm(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RigRuntime]:
    """The demo rig without its camera, its robot in a process of its own. Neither test changes
    what the other sees (a rejected sample is counted, an unknown request refused)."""
    raw = load_rig("demo").model_dump(mode="json")
    raw["cameras"] = []
    with RigRuntime(_isolated(raw), data_root=tmp_path_factory.mktemp("one_arm")) as runtime:
        yield runtime


class TestOneRobotProcess:
    """Tests that only talk to one robot process share its rig (a start-up costs a Python and MuJoCo
    start-up of its own); the class scope stops it before the next test's rig starts."""

    def test_a_robot_process_drops_an_unusable_sample_and_keeps_its_loop(self, one_arm: RigRuntime) -> None:
        runtime = one_arm
        assert runtime.broker_url is not None
        host = runtime.hosts["arm0"]
        before = host.call(Stats()).rejected["non_finite"]
        client = MqttBus(runtime.broker_url, client_id="bad-sender").connect()
        try:
            t = now_ns()
            nan_pose = ControllerState(
                Stamp("vr0/right", 1, t, t), "right", (math.nan, 0.0, 1.1), (1, 0, 0, 0), "op"
            )
            client.publish(str(Topic("demo", "vr0", "right_controller")), wire.encode(nan_pose), qos=1)
            _wait_until(lambda: host.call(Stats()).rejected["non_finite"] == before + 1)
            stats = host.call(Stats())
        finally:
            client.close()
        assert before == 0
        assert stats.alive
        assert stats.tick_faults == 0

    def test_a_request_the_host_does_not_know_is_a_clear_error(self, one_arm: RigRuntime) -> None:
        with pytest.raises(RobotError, match="robot 'arm0': unknown request 'reboot'"):
            one_arm.hosts["arm0"].call("reboot")  # type: ignore[arg-type]  # not a request type
        assert one_arm.hosts["arm0"].call(Estopped()) is False  # still serving

    def test_a_failed_request_raises_its_own_error_class_in_the_station(self, one_arm: RigRuntime) -> None:
        # A telerig error in the child (here: a replay of a device it does not run) arrives as the
        # same class with its message, not as a generic robot error, and the host keeps serving.
        with pytest.raises(
            DeviceError, match=r"robot 'arm0': replay_devices: device\(s\) ghost do not run here"
        ):
            one_arm.hosts["arm0"].call(
                ReplayDevices("/nonexistent.mcap", {"ghost": "telerig/v1/demo/ghost/x"})
            )
        assert one_arm.hosts["arm0"].call(Estopped()) is False
