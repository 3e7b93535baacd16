"""Per-device pause and calibration launch from the dashboard in headless Chromium: an operator clicks
Pause on a device's row, the real coordinator (through Mosquitto with the rig's ACL) pauses it and the
row says so; Resume brings it back; Calibrate asks which operator and the device node's answer and
result show on the page. A viewer's rows have no buttons."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from argon2 import PasswordHasher

from telerig.bus.acl import STATION, WEB, rig_access_policy
from telerig.bus.broker import MosquittoBroker
from telerig.bus.mqtt import MqttBus
from telerig.config import load_rig
from telerig.runtime.device_node import DeviceNode
from telerig.runtime.session import Coordinator
from telerig.server.accounts import AccountStore
from telerig.server.app import create_app
from telerig.server.gateway import RigGateway

PASSWORD = "correct horse battery"

pytestmark = [pytest.mark.browser, pytest.mark.broker]


@pytest.fixture
def served(tmp_path: Path, live_server: Callable[..., str]) -> Iterator[tuple[str, Coordinator, DeviceNode]]:
    accounts = AccountStore.open(tmp_path, hasher=PasswordHasher(time_cost=1, memory_cost=64, parallelism=1))
    accounts.add_user("otto", "operator", PASSWORD)
    accounts.add_user("vic", "viewer", PASSWORD)
    config = load_rig("demo")
    broker = MosquittoBroker(access=rig_access_policy(config), owner=STATION).start()
    station = MqttBus(broker.url_for(STATION), client_id="station0").connect()
    device_bus = MqttBus(broker.url_for("dev-vr0"), client_id="demo-dev-vr0").connect()
    coordinator = Coordinator(station, "demo", devices=["vr0"]).start()
    node = DeviceNode("demo", config.devices[0].build(), device_bus, profile_root=tmp_path)
    gateway = RigGateway(config, broker.url_for(WEB)).start()
    try:
        yield live_server(create_app(accounts, gateway=gateway)), coordinator, node
    finally:
        node.calibration.cancel_own()  # the dashboard's calibration runs 33 s
        gateway.close()
        coordinator.close()
        for bus in (device_bus, station):
            bus.close()
        broker.stop()
        accounts.close()


def test_an_operator_pauses_resumes_and_calibrates_a_device_from_its_row(
    served: tuple[str, Coordinator, DeviceNode], page: Any, log_in: Callable[..., None], tmp_path: Path
) -> None:
    base, coordinator, _ = served
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.on("dialog", lambda dialog: dialog.accept("ana"))  # the calibration's operator prompt
    log_in(page, base, "otto", PASSWORD)
    row = page.locator('#devices tbody tr[data-key="vr0"]')
    row.locator("button.device-pause", has_text="Pause").click()
    page.locator('#devices tbody tr[data-key="vr0"][data-paused="1"]').wait_for()
    assert coordinator.status.paused_devices == ("vr0",)
    assert row.locator(".device-state").text_content() == "paused"
    assert "pause vr0: paused devices vr0" in (page.text_content("#command-result") or "")
    page.screenshot(path=str(tmp_path / "device-paused.png"), full_page=True)
    row.locator("button.device-pause", has_text="Resume").click()
    page.locator('#devices tbody tr[data-key="vr0"][data-paused="0"]').wait_for()
    assert list(coordinator.status.paused_devices) == []
    row.locator("button.device-calibrate").click()
    page.locator("#command-result", has_text="calibrating operator ana with vr0").wait_for()
    # The device node's progress shows on the row (the result comes after the 33 s window).
    row.locator(".calibration", has_text="progress: operator ana").wait_for()
    page.screenshot(path=str(tmp_path / "device-calibrating.png"), full_page=True)
    assert errors == []
    # A viewer sees which devices are paused, without the buttons.
    coordinator.pause_device("vr0")
    page.click("#logout")
    page.wait_for_url(f"{base}/login")
    log_in(page, base, "vic", PASSWORD)
    viewer_row = page.locator('#devices tbody tr[data-key="vr0"][data-paused="1"]')
    viewer_row.wait_for()
    assert viewer_row.locator("button").count() == 0
