"""A rig over two stations in two processes: the first coordinates and runs the arm, the second runs
the operator's device on its own host and records it under the coordinator's episode ids."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest
import yaml
from tests.ports import PortTakenError, free_port, on_a_free_port

from telerig.bus.base import Message
from telerig.bus.login import BusLogin
from telerig.bus.topics import Topic
from telerig.config import load_rig
from telerig.config.schema import RigConfig
from telerig.errors import BusError, ConfigError
from telerig.ir.mcap_log import iter_raw
from telerig.runtime.clock_sync import CLOCK_PING
from telerig.runtime.rig import RigRuntime
from telerig.store.episodes import EpisodeStore

pytestmark = [pytest.mark.sim, pytest.mark.broker, pytest.mark.slow]


def _two_station_rig(port: int) -> RigConfig:
    """The demo rig without its camera, with the VR operator moved to a second station."""
    raw = load_rig("demo").model_dump(mode="json", exclude_none=True)
    raw["name"] = "two_hosts"
    raw["broker"] = {"type": "embedded", "port": port}
    raw["stations"] = [{"id": "lab"}, {"id": "operator"}]
    raw["cameras"] = []
    for device in raw["devices"]:
        device["station"] = "operator"
    for robot in raw["robots"]:
        robot["station"] = "lab"
    return RigConfig.model_validate(raw)


def _open_lab(stack: contextlib.ExitStack, port: int, data_root: Path) -> tuple[RigConfig, RigRuntime]:
    """The lab's station, whose embedded broker listens on ``port`` (the rig names it, for the other)."""
    rig = _two_station_rig(port)
    try:
        return rig, stack.enter_context(RigRuntime(rig, data_root=data_root, station="lab"))
    except BusError as exc:
        if "is in use" in str(exc):
            raise PortTakenError(str(exc)) from None
        raise


def test_a_second_station_needs_the_coordinators_broker() -> None:
    rig = _two_station_rig(free_port())
    with pytest.raises(ConfigError, match="--broker mqtt://HOST:PORT"):
        RigRuntime(rig, station="operator")
    with pytest.raises(ConfigError, match="Valid: lab, operator"):
        RigRuntime(rig, station="kitchen")


def test_two_stations_in_two_processes_record_one_episode_under_one_id(tmp_path: Path) -> None:
    lab_root, operator_root = tmp_path / "lab", tmp_path / "operator"
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "osmesa")}
    with contextlib.ExitStack() as stack:
        rig, lab = on_a_free_port(lambda port: _open_lab(stack, port, lab_root))
        rig_file = tmp_path / "rig.yaml"
        rig_file.write_text(yaml.safe_dump(rig.model_dump(mode="json", exclude_none=True)))
        # The operator's host logs in as its station (telerig run on the lab writes this file).
        embedded = lab.broker.embedded
        assert embedded is not None
        password = embedded.access.password("station-operator")
        login = BusLogin(embedded.address, "station-operator", password, rig.name)
        cmd = [
            sys.executable, "-m", "telerig.cli.main", "run", str(rig_file),
            "--station", "operator", "--broker", embedded.address,
            "--episodes", "1", "--data-root", str(operator_root),
            "--credentials", str(login.write(tmp_path / "operator-login.json")),
        ]  # fmt: skip
        pinged = threading.Event()

        def on_ping(message: Message) -> None:
            pinged.set()

        lab.recorder.bus.subscribe(str(Topic(rig.name, "operator", CLOCK_PING)), on_ping)
        follower = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env)
        try:
            # The follower syncs its clock with the coordinator while it opens; give it a moment more
            # to start its device node (a late station would still join, just later).
            assert pinged.wait(60.0), "the operator station never asked for the coordinator's clock"
            threading.Event().wait(1.5)
            assert follower.poll() is None
            result = lab.run_episode(3.0)
            out, _ = follower.communicate(timeout=60.0)
        finally:
            if follower.poll() is None:
                follower.send_signal(signal.SIGINT)
                follower.wait(timeout=20.0)
    assert follower.returncode == 0, out.decode()
    assert result.status == "complete"

    lab_manifest = EpisodeStore(lab_root).get(result.episode_id)
    operator_manifest = EpisodeStore(operator_root).get(result.episode_id)  # same id on both stations
    assert operator_manifest.status == "complete"
    assert lab_manifest.extra["station"] == "lab"
    assert operator_manifest.extra["station"] == "operator"
    assert operator_manifest.extra["session_id"] == lab_manifest.extra["session_id"]
    clock = operator_manifest.extra["clock"]
    assert isinstance(clock, dict)
    assert clock["station"] == "operator"
    assert clock["synced"] is True

    # Each station records its own nodes: the operator's host its controller, the lab its arm.
    lab_topics = _topics(EpisodeStore(lab_root).episode_dir(result.episode_id) / "episode.mcap")
    operator_topics = _topics(EpisodeStore(operator_root).episode_dir(result.episode_id) / "episode.mcap")
    assert "telerig/v1/two_hosts/vr0/right_controller" in operator_topics
    assert "telerig/v1/two_hosts/vr0/right_controller" not in lab_topics
    assert "telerig/v1/two_hosts/arm0/joint_state" in lab_topics
    assert not any("/arm0/" in t for t in operator_topics)
    # ... and the arm followed the remote operator's device.
    applied = {s.name: s.messages for s in result.streams}
    assert applied["telerig/v1/two_hosts/arm0/joint_command_requested"] > 100


def _topics(path: Path) -> set[str]:
    return {topic for topic, *_ in iter_raw(path)}
