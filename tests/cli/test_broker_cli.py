"""``telerig broker acl``: the files it writes run a real Mosquitto that enforces the rig's ACL."""

from __future__ import annotations

import os
import pwd
import shutil
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from tests.ports import MOSQUITTO_RUNNING, free_port, on_a_free_port, start_listening

from telerig.bus.base import Message
from telerig.bus.broker import find_mosquitto
from telerig.bus.login import BusLogin
from telerig.bus.mqtt import MqttBus
from telerig.cli.main import main
from telerig.errors import BusError

pytestmark = pytest.mark.broker


def _acl(out: Path, port: int) -> Path:
    shutil.rmtree(out, ignore_errors=True)  # left by an attempt whose port was taken
    assert main(["broker", "acl", "fleet", "--out", str(out), "--address", f"mqtt://127.0.0.1:{port}"]) == 0
    return out


@pytest.fixture
def acl_dir(tmp_path: Path) -> tuple[Path, int]:
    port = free_port()
    return _acl(tmp_path / "fleet-broker", port), port


@pytest.fixture
def external_mosquitto(tmp_path: Path) -> Iterator[tuple[Path, int]]:
    """A Mosquitto started the way a lab would: only our generated passwd and acl files. Yields their
    folder and the port (which is part of the logins the command writes)."""
    log = tmp_path / "mosquitto.log"

    def start(port: int) -> tuple[Path, int, subprocess.Popen[bytes]]:
        out = _acl(tmp_path / "fleet-broker", port)
        log.unlink(missing_ok=True)
        conf = tmp_path / "mosquitto.conf"
        conf.write_text(
            f"listener {port} 127.0.0.1\n"
            "allow_anonymous false\n"
            f"password_file {out / 'passwd'}\n"
            f"acl_file {out / 'acl'}\n"
            f"log_dest file {log}\n"
            f"user {pwd.getpwuid(os.geteuid()).pw_name}\n"
        )
        proc = start_listening([str(find_mosquitto()), "-c", str(conf)], port, log, MOSQUITTO_RUNNING)
        return out, port, proc

    out, port, proc = on_a_free_port(start)
    try:
        yield out, port
    finally:
        proc.terminate()
        proc.wait(5.0)


def test_the_acl_files_are_private(acl_dir: tuple[Path, int]) -> None:
    out, _ = acl_dir
    assert out.stat().st_mode & 0o777 == 0o700
    for path in (out / "passwd", out / "acl", out / "logins" / "cli.json"):
        assert path.stat().st_mode & 0o777 == 0o600
    assert "password" not in (out / "passwd").read_text()
    assert "topic write telerig/v1/fleet/vr_ur5e/#" in (out / "acl").read_text()


def test_a_real_mosquitto_enforces_the_generated_acl(external_mosquitto: tuple[Path, int]) -> None:
    out, port = external_mosquitto
    login = {name: BusLogin.read(out / "logins" / f"{name}.json", rig="fleet") for name in ("station", "cli")}
    device = BusLogin.read(out / "logins" / "dev-vr_ur5e.json", rig="fleet")
    got: list[str] = []
    done = threading.Event()

    def on_message(message: Message) -> None:
        got.append(message.payload.decode())
        if message.payload == b"end":
            done.set()

    with (
        MqttBus(login["station"].url, client_id="station") as station,
        MqttBus(device.url, client_id="vr_ur5e") as dev,
        MqttBus(login["cli"].url, client_id="cli") as cli,
    ):
        station.subscribe("telerig/v1/fleet/safety/command", on_message, qos=1)
        time.sleep(0.2)
        dev.publish("telerig/v1/fleet/safety/command", b"forged by a device", qos=1)
        cli.publish("telerig/v1/fleet/safety/command", b"from the operator", qos=1)
        time.sleep(0.2)
        station.publish("telerig/v1/fleet/safety/command", b"end", qos=1)
        assert done.wait(3.0)
    assert got == ["from the operator", "end"]

    anonymous = MqttBus(f"mqtt://127.0.0.1:{port}", client_id="anonymous")
    with pytest.raises(BusError, match="refused client 'anonymous'"):
        anonymous.connect()
    anonymous.close()


def test_an_embedded_rig_needs_the_external_address(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["broker", "acl", "demo", "--out", str(tmp_path / "x")]) == 2
    assert "embeds its broker: pass --address" in capsys.readouterr().err


def test_a_folder_in_use_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "used").mkdir()
    (tmp_path / "used" / "keep.txt").write_text("x")
    args = ["broker", "acl", "fleet", "--out", str(tmp_path / "used"), "--address", "mqtt://h:1883"]
    assert main(args) == 2
    assert "is not an empty folder" in capsys.readouterr().err
