"""A running rig's nodes log in to its embedded broker as their own principals; operators get a login file."""

from __future__ import annotations

import re
import threading
import time
from pathlib import Path
from typing import Literal

import pytest

from telerig.bus.login import BusLogin, login_path
from telerig.cli.main import main
from telerig.config import load_rig
from telerig.runtime.rig import RigRuntime

pytestmark = [pytest.mark.sim, pytest.mark.broker, pytest.mark.slow]


def _logins(log: str) -> dict[str, str]:
    """Client id → username of every connection in a Mosquitto log."""
    return dict(re.findall(r"as (\S+) \(.*?u'([^']+)'\)", log))


@pytest.mark.parametrize(
    ("isolation", "device", "control"),
    [
        ("threads", "dev-vr0", "ctl-arm0"),
        # The robot's process logs its nodes in as itself (acl.py: it hosts the devices bound to it alone).
        ("processes", "robot-arm0", "robot-arm0"),
    ],
)
def test_each_node_logs_in_as_its_own_principal(
    tmp_path: Path, isolation: Literal["threads", "processes"], device: str, control: str
) -> None:
    rig = load_rig("demo").with_isolation(isolation).model_copy(update={"cameras": []})
    with RigRuntime(rig, data_root=tmp_path) as runtime:
        broker = runtime.broker.embedded
        assert broker is not None
        assert broker.log_path is not None
        logins = _logins(broker.log_path.read_text())
    assert logins["demo-dev-vr0"] == device
    assert logins["demo-ctl-arm0"] == control
    assert logins["demo-recorder"] == "station"
    assert set(logins.values()) <= {device, control, "station"}


def test_telerig_run_keeps_a_private_operator_login_while_it_runs(tmp_path: Path) -> None:
    path = login_path(tmp_path, "demo")
    seen: list[tuple[int, BusLogin]] = []
    done = threading.Event()

    def watch() -> None:
        while not done.is_set() and not seen:
            if path.exists():
                seen.append((path.stat().st_mode & 0o777, BusLogin.read(path, rig="demo")))
            time.sleep(0.05)

    watcher = threading.Thread(target=watch)
    watcher.start()
    try:
        code = main(
            ["demo", "--episodes", "1", "--duration", "1", "--no-replay", "--data-root", str(tmp_path)]
        )
    finally:
        done.set()
        watcher.join()
    assert code == 0
    mode, login = seen[0]
    assert mode == 0o600
    assert login.username == "cli"
    assert login.address.startswith("mqtt://127.0.0.1:")
    assert not path.exists()  # removed at exit


def test_a_rig_runs_on_an_external_broker_over_tls(tmp_path: Path, tls_pki: tuple[Path, Path, Path]) -> None:
    from telerig.bus.broker import MosquittoBroker
    from telerig.config.schema import RigConfig

    ca, cert, key = tls_pki
    with MosquittoBroker(certfile=cert, keyfile=key) as external:
        raw = load_rig("demo").model_dump(mode="json")
        raw["cameras"] = []
        raw["broker"] = {"type": "external", "url": external.url, "tls": {"ca_file": str(ca)}}
        with RigRuntime(RigConfig.model_validate(raw), data_root=tmp_path / "data") as runtime:
            result = runtime.run_episode(1.5)
    assert result.status == "complete"
    counts = {s.name.split("/", 3)[-1]: s.messages for s in result.streams}
    assert counts["arm0/joint_command_sent"] > 50


def test_tls_options_need_an_mqtts_url() -> None:
    from pydantic import ValidationError

    from telerig.config.schema import ExternalBrokerConfig

    with pytest.raises(ValidationError, match="is not mqtts://; use mqtts://"):
        ExternalBrokerConfig(url="mqtt://user:secret@lab:1883", tls={"ca_file": "ca.pem"})  # type: ignore[arg-type]
