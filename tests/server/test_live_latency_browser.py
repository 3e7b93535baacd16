"""The dashboard's robot card shows the robot's live input-to-actuation latency against its budget, in a
real headless Chromium (issue 14): the control node's report publisher (real
:class:`~telerig.runtime.control_health.ControlHealth`) through Mosquitto with the rig's ACL, the
gateway as ``web``, the app on uvicorn."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from argon2 import PasswordHasher

from telerig.bus.acl import STATION, WEB, rig_access_policy
from telerig.bus.broker import MosquittoBroker
from telerig.bus.mqtt import MqttBus
from telerig.config import load_rig
from telerig.runtime.control_health import ControlHealth
from telerig.server.accounts import AccountStore
from telerig.server.app import create_app
from telerig.server.gateway import RigGateway

pytestmark = [pytest.mark.browser, pytest.mark.broker]

PASSWORD = "correct horse battery"
MS = 1_000_000
CARD = "#robots li[data-key=arm0]"


class _Loop:
    """A control loop's applied commands at 100 Hz, each ``latency_ms`` after its input's capture,
    into a real report publisher running its 2 Hz reports."""

    def __init__(self, health: ControlHealth) -> None:
        self.health = health
        self.latency_ms = 3.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.wait(0.01):
            tick = time.time_ns()
            self.health.sent(tick - round(self.latency_ms * MS), tick, tick)

    def __enter__(self) -> _Loop:
        self._thread.start()
        self.health.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.health.stop()
        self._stop.set()
        self._thread.join()


def test_the_robot_card_shows_its_latency_against_the_budget(
    tmp_path: Path, page: Any, live_server: Callable[..., str], log_in: Callable[..., None]
) -> None:
    rig = load_rig("demo")
    broker = MosquittoBroker(access=rig_access_policy(rig), owner=STATION).start()
    accounts = AccountStore.open(tmp_path, hasher=PasswordHasher(time_cost=1, memory_cost=64, parallelism=1))
    accounts.add_user("vic", "viewer", PASSWORD)
    gateway = RigGateway(rig, broker.url_for(WEB)).start()
    robot = MqttBus(broker.url_for("ctl-arm0"), client_id="ctl-arm0").connect()
    try:
        base = live_server(create_app(accounts, gateway=gateway))
        health = ControlHealth(rig.name, "arm0", robot, budget_ms=20.0, hold_ms=100.0)
        with _Loop(health) as loop:
            log_in(page, base, "vic", PASSWORD)
            badge = page.locator(f"{CARD}[data-latency-light=green] .latency")
            badge.wait_for()
            assert "p50 3.0 / p99 3.0 ms (budget 20)" in (badge.text_content() or "")
            assert "hold time" in (badge.get_attribute("title") or "")
            loop.latency_ms = 60.0  # over the budget, within the hold time: amber once the window has it
            page.wait_for_selector(f"{CARD}[data-latency-light=amber] .latency[data-light=amber]")
            loop.latency_ms = 150.0  # past the hold time: the chain would hold the robot
            page.wait_for_selector(f"{CARD}[data-latency-light=red]")
            page.wait_for_function(  # the whole window at 150 ms
                "s => (document.querySelector(s)?.textContent || '').includes('p50 150.0 / p99 150.0')",
                arg=f"{CARD} .latency",
            )
    finally:
        robot.close()
        gateway.close()
        broker.stop()
