"""The dashboard's voice command box in headless Chromium: an operator types a phrase of the voice
grammar, the real coordinator (through Mosquitto with the rig's ACL) gets the episode command, and a
rejected phrase is said back on the page. A viewer has no box."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from argon2 import PasswordHasher

from telerig.bus.acl import STATION, WEB, rig_access_policy
from telerig.bus.broker import MosquittoBroker
from telerig.bus.mqtt import MqttBus
from telerig.config import load_rig
from telerig.runtime.session import Coordinator, SessionState
from telerig.server.accounts import AccountStore
from telerig.server.app import create_app
from telerig.server.gateway import RigGateway

PASSWORD = "correct horse battery"

pytestmark = [pytest.mark.browser, pytest.mark.broker]


@pytest.fixture
def served(tmp_path: Path, live_server: Callable[..., str]) -> Iterator[tuple[str, Coordinator]]:
    accounts = AccountStore.open(tmp_path, hasher=PasswordHasher(time_cost=1, memory_cost=64, parallelism=1))
    accounts.add_user("otto", "operator", PASSWORD)
    accounts.add_user("vic", "viewer", PASSWORD)
    config = load_rig("demo")
    broker = MosquittoBroker(access=rig_access_policy(config), owner=STATION).start()
    station = MqttBus(broker.url_for(STATION), client_id="station0").connect()
    coordinator = Coordinator(station, "demo", lead_s=0.1).start()
    gateway = RigGateway(config, broker.url_for(WEB)).start()
    try:
        yield live_server(create_app(accounts, gateway=gateway)), coordinator
    finally:
        gateway.close()
        coordinator.close()
        station.close()
        broker.stop()
        accounts.close()


def test_an_operator_types_a_voice_command_and_a_bad_one_is_said_back(
    served: tuple[str, Coordinator], page: Any, log_in: Callable[..., None], tmp_path: Path
) -> None:
    base, coordinator = served
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    log_in(page, base, "otto", PASSWORD)
    page.fill("#voice-text", "start recording")
    page.click("#voice-form button")
    page.locator("#command-result", has_text="done: episode starting").wait_for()
    # "done" says the command was published; the coordinator takes it off the bus a moment later
    deadline = time.monotonic() + 10.0
    while coordinator.state == SessionState.IDLE and time.monotonic() < deadline:
        time.sleep(0.02)
    assert coordinator.state in (SessionState.ARMED, SessionState.RECORDING)
    page.fill("#voice-text", "stop")
    page.click("#voice-form button")
    page.locator("#command-result", has_text="is ambiguous").wait_for()
    page.screenshot(path=str(tmp_path / "voice-box.png"), full_page=True)
    assert errors == []
    page.click("#logout")
    page.wait_for_url(f"{base}/login")
    log_in(page, base, "vic", PASSWORD)
    page.wait_for_selector("#session-state")
    assert page.locator("#voice-form").is_hidden()
