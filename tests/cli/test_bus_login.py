"""``telerig safety`` logs in as the rig's ``cli`` principal: from the run's login file or as told."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from telerig.bus.acl import CLI, STATION, rig_access_policy
from telerig.bus.base import Message
from telerig.bus.broker import MosquittoBroker
from telerig.bus.login import BusLogin, login_path
from telerig.bus.mqtt import MqttBus
from telerig.cli.main import main
from telerig.config import load_rig

pytestmark = pytest.mark.broker


@pytest.fixture
def demo_broker() -> Iterator[MosquittoBroker]:
    with MosquittoBroker(access=rig_access_policy(load_rig("demo")), owner=STATION) as broker:
        yield broker


@pytest.fixture
def robot(demo_broker: MosquittoBroker) -> Iterator[list[dict[str, object]]]:
    """arm0's control node, as far as the CLI sees it: applies e-stops to its retained status."""
    commands: list[dict[str, object]] = []
    with (
        MqttBus(demo_broker.url, client_id="station") as station,
        MqttBus(demo_broker.url_for("ctl-arm0"), client_id="ctl-arm0") as control,
    ):
        ready = threading.Event()

        def on_command(message: Message) -> None:
            command = json.loads(message.payload)
            commands.append(command)
            control.publish("telerig/v1/demo/arm0/status", b"estopped", qos=1, retain=True)

        station.subscribe("telerig/v1/demo/safety/command", on_command, qos=1)
        station.subscribe("telerig/v1/demo/safety/ready", lambda m: ready.set(), qos=1)
        station.publish("telerig/v1/demo/safety/ready", b"", qos=1)
        assert ready.wait(3.0)
        yield commands


def _login(broker: MosquittoBroker) -> BusLogin:
    return BusLogin(broker.address, CLI, broker.access.password(CLI), "demo")


def test_safety_logs_in_with_the_runs_login_file(
    demo_broker: MosquittoBroker, robot: list[dict[str, object]], tmp_path: Path
) -> None:
    _login(demo_broker).write(login_path(tmp_path, "demo"))
    assert main(["safety", "estop", "--rig", "demo", "--data-root", str(tmp_path), "--timeout", "3"]) == 0
    assert robot[0]["source"] == "cli"


def test_safety_takes_an_explicit_login(
    demo_broker: MosquittoBroker, robot: list[dict[str, object]], tmp_path: Path
) -> None:
    password = demo_broker.access.password(CLI)
    base = ["safety", "estop", "--rig", "demo", "--broker", demo_broker.address, "--timeout", "3"]
    assert main([*base, "--username", CLI, "--password", password]) == 0
    copy = _login(demo_broker).write(tmp_path / "elsewhere.json")
    assert main([*base, "--credentials", str(copy)]) == 0
    # The robot's status is still "estopped" from the first command, so the CLI may return before
    # the second command reached the fake control node: wait for it (under load it lagged).
    deadline = time.monotonic() + 10.0
    while len(robot) < 2 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert len(robot) == 2


def test_without_a_login_the_error_says_where_it_looked(
    demo_broker: MosquittoBroker, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    args = ["safety", "estop", "--rig", "demo", "--broker", demo_broker.address, "--data-root", str(tmp_path)]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert f"no bus login at {tmp_path / '.bus-demo.json'}" in " ".join(err.split())


def test_a_wrong_password_is_one_line(
    demo_broker: MosquittoBroker, capsys: pytest.CaptureFixture[str]
) -> None:
    args = ["safety", "reset", "--rig", "demo", "--broker", demo_broker.address]
    assert main([*args, "--username", CLI, "--password", "guess"]) == 2
    assert "refused client" in capsys.readouterr().err


def test_a_login_file_others_can_read_is_refused(
    demo_broker: MosquittoBroker, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = _login(demo_broker).write(tmp_path / "login.json")
    path.chmod(0o644)
    assert main(["safety", "reset", "--rig", "demo", "--credentials", str(path)]) == 2
    assert f"chmod 600 {path}" in " ".join(capsys.readouterr().err.split())


def test_session_commands_log_in_with_the_runs_login_file(
    demo_broker: MosquittoBroker, tmp_path: Path
) -> None:
    got: list[dict[str, object]] = []
    arrived = threading.Event()

    def on_command(message: Message) -> None:
        got.append(json.loads(message.payload))
        arrived.set()

    _login(demo_broker).write(login_path(tmp_path, "demo"))
    with MqttBus(demo_broker.url, client_id="coordinator") as coordinator:
        subscribed = threading.Event()
        coordinator.subscribe("telerig/v1/demo/coordinator/command", on_command, qos=1)
        coordinator.subscribe("telerig/v1/demo/coordinator/ready", lambda m: subscribed.set(), qos=1)
        coordinator.publish("telerig/v1/demo/coordinator/ready", b"", qos=1)
        assert subscribed.wait(3.0)
        assert main(["session", "stop", "--rig", "demo", "--data-root", str(tmp_path)]) == 0
        assert arrived.wait(3.0)
    assert got[0]["command"] == "stop"
    assert got[0]["source"] == "cli"


def test_a_login_being_rewritten_is_never_read_half_written(tmp_path: Path) -> None:
    # `telerig run` writes the login while `telerig safety` may be reading it: the write is a rename
    # of a whole 0600 file, so a reader sees the old login or the new one, never a part of one.
    path = tmp_path / ".bus-demo.json"
    logins = [BusLogin("mqtt://127.0.0.1:1883", f"cli-{i}", "x" * (i % 50 + 1), "demo") for i in range(300)]
    logins[0].write(path)
    done = threading.Event()
    seen: list[str] = []
    errors: list[Exception] = []

    def read() -> None:
        while not done.is_set():
            try:
                seen.append(BusLogin.read(path, rig="demo").username)
            except Exception as exc:  # any failure to read is the bug
                errors.append(exc)

    reader = threading.Thread(target=read)
    reader.start()
    try:
        for login in logins:
            login.write(path)
    finally:
        done.set()
        reader.join()
    assert not errors, errors[:3]
    assert seen
    assert path.stat().st_mode & 0o777 == 0o600
    assert [p.name for p in tmp_path.iterdir()] == [path.name]  # no temporary file left behind
