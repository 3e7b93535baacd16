"""Robot processes survive forged and malformed safety payloads: counted, dropped, robots still running."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import pytest

from telerig.bus.base import Message
from telerig.bus.mqtt import MqttBus
from telerig.config import load_rig
from telerig.config.schema import RigConfig
from telerig.runtime.rig import RigRuntime
from telerig.safety.commands import halt_topic, safety_command_topic

pytestmark = [pytest.mark.sim, pytest.mark.broker, pytest.mark.slow]


def _two_arms_in_processes() -> RigConfig:
    raw: dict[str, Any] = load_rig("demo").model_dump(mode="json")
    raw["cameras"] = []
    raw["devices"].append({**raw["devices"][0], "id": "vr1"})
    raw["robots"].append({**raw["robots"][0], "id": "arm1"})
    raw["bindings"] += [{**b, "device": "vr1", "robot": "arm1"} for b in raw["bindings"]]
    raw["safety"]["policy"] = "halt_all"
    raw["runtime"] = {"isolation": "processes"}
    return RigConfig.model_validate(raw)


def test_forged_and_malformed_halts_and_commands_stop_no_robot(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    status: dict[str, str] = {}
    changed = threading.Condition()

    def on_status(message: Message) -> None:
        with changed:
            status[message.topic.split("/")[3]] = message.payload.decode()
            changed.notify_all()

    def wait_for(robot: str, state: str) -> bool:
        with changed:
            return changed.wait_for(lambda: status.get(robot) == state, 5.0)

    with RigRuntime(_two_arms_in_processes(), data_root=tmp_path) as runtime:
        assert runtime.broker_url is not None
        with MqttBus(runtime.broker_url, client_id="intruder") as bus:
            bus.subscribe("telerig/v1/demo/+/status", on_status, qos=1)
            for payload in (b'{"robot": "nobody"}', b"[]", b'"stop"', b"42", b"null", b"[" * 3000):
                bus.publish(halt_topic("demo"), payload, qos=1)
                bus.publish(safety_command_topic("demo"), payload, qos=1)
            bus.publish(safety_command_topic("demo"), b'{"command": "estop", "robot": "nobody"}', qos=1)
            time.sleep(1.0)
            with changed:
                assert set(status) == {"arm0", "arm1"}
                assert "estopped" not in status.values()
            # Both processes still listen: a valid e-stop of one robot latches it, and only it.
            bus.publish(safety_command_topic("demo"), b'{"command": "estop", "robot": "arm1"}', qos=1)
            assert wait_for("arm1", "estopped")
            time.sleep(0.3)
            assert status["arm0"] != "estopped"
    err = capfd.readouterr().err  # the robot processes' log lines
    for robot in ("arm0", "arm1"):
        assert f"{robot}: dropped a halt notice on telerig/v1/demo/safety/halt: robot 'nobody'" in err
        assert f"{robot}: dropped a safety command on telerig/v1/demo/safety/command: e-stop" in err
    assert "Traceback" not in err
