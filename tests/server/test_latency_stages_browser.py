"""The dashboard's per-stage latency table in a real headless Chromium (issue 17): a control node's
stage reports (real :class:`~telerig.runtime.control_health.ControlHealth`) and a camera node's
stamped previews (real :class:`~telerig.cameras.preview.PreviewPublisher`) through Mosquitto with the
rig's ACL, the gateway as ``web``, the app on uvicorn. The page's own ``latency.js`` reports each
preview it displays over ``/api/latency``, so the camera's ``video_display`` stage fills in; a stage
pushed over its budget turns its row red and raises its alert on the page."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from argon2 import PasswordHasher

from telerig.bus.acl import STATION, WEB, rig_access_policy
from telerig.bus.broker import MosquittoBroker
from telerig.bus.mqtt import MqttBus
from telerig.cameras.preview import PreviewPublisher
from telerig.config import load_rig
from telerig.runtime.control_health import ControlHealth
from telerig.server.accounts import AccountStore
from telerig.server.app import create_app
from telerig.server.gateway import RigGateway

pytestmark = [pytest.mark.browser, pytest.mark.broker]

PASSWORD = "correct horse battery"
MS = 1_000_000


class _Rig:
    """100 Hz of applied commands, each stage ``stage_ms`` long (``bus_ms`` for the bus stage), into
    a real report publisher; and a camera offering a frame captured 20 ms ago every 0.1 s."""

    def __init__(self, health: ControlHealth, preview: PreviewPublisher) -> None:
        self.health = health
        self.preview = preview
        self.bus_ms = 1.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        image = np.full((120, 160, 3), 90, np.uint8)
        n = 0
        while not self._stop.wait(0.01):
            t = time.time_ns() - 20 * MS
            c, bus = t - 30 * MS, round(self.bus_ms * MS)
            self.health.sent(
                c,
                c + 4 * MS + bus,
                c + 2 * MS + bus,
                arrival_ns=c + MS,
                received_ns=c + MS + bus,
                retargeted_ns=c + 3 * MS + bus,
            )
            self.health.measured(c + 5 * MS + bus, t)
            n += 1
            if n % 10 == 0:
                self.preview.offer(image, t)

    def __enter__(self) -> _Rig:
        self._thread.start()
        self.health.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.health.stop()
        self._stop.set()
        self._thread.join()
        self.preview.close()


def test_the_dashboard_shows_each_stage_against_its_budget_and_reports_what_it_displays(
    tmp_path: Path, page: Any, live_server: Callable[..., str], log_in: Callable[..., None]
) -> None:
    rig = load_rig("demo")
    broker = MosquittoBroker(access=rig_access_policy(rig), owner=STATION).start()
    accounts = AccountStore.open(tmp_path, hasher=PasswordHasher(time_cost=1, memory_cost=64, parallelism=1))
    accounts.add_user("vic", "viewer", PASSWORD)
    gateway = RigGateway(rig, broker.url_for(WEB)).start()
    robot = MqttBus(broker.url_for("ctl-arm0"), client_id="ctl-arm0").connect()
    camera = MqttBus(broker.url_for("cam-scene"), client_id="cam-scene").connect()
    try:
        base = live_server(create_app(accounts, gateway=gateway))
        health = ControlHealth(rig.name, "arm0", robot, budgets_ms={"bus": 5.0})
        with _Rig(health, PreviewPublisher(camera, rig.name, "scene", rate_hz=2.0)) as loop:
            log_in(page, base, "vic", PASSWORD)
            bus_row = page.locator('#latency tr[data-key="arm0/bus"][data-light=green]')
            bus_row.wait_for()
            # The window fills at the loop's rate: wait for 50 samples (a loaded host is slower).
            count = "document.querySelector('#latency tr[data-key=\"arm0/bus\"] td:last-child')"
            page.wait_for_function(f"() => Number({count}?.textContent) > 50")
            cells = bus_row.locator("td").all_text_contents()
            assert cells[1:] == ["arm0", "bus", "1.0 ms", "1.0 ms", "5 ms", cells[-1]]
            assert int(cells[-1]) > 50
            page.wait_for_selector('#latency tr[data-key="arm0/end_to_end"].total')
            # The page displays a preview, reports it, and the server's table has the display stage.
            display = page.locator('#latency tr[data-key="scene/video_display"]')
            page.wait_for_function(
                "() => Number(document.querySelector('#latency tr[data-key=\"scene/video_display\"]')"
                "?.lastElementChild?.textContent || 0) >= 1",
                timeout=15_000,
            )
            assert display.get_attribute("data-light") in ("green", "amber", "red")
            encode = page.locator('#latency tr[data-key="scene/video_encode"] td').all_text_contents()
            assert float(encode[3].split()[0]) >= 20.0  # captured 20 ms before it was offered
            assert gateway.view.counts().get("displayed", 0) >= 1
            # The bus stage over its budget (5 ms; 12 ms is over twice it): red, and its alert shows.
            loop.bus_ms = 12.0
            page.wait_for_selector('#latency tr[data-key="arm0/bus"][data-light=red]', timeout=10_000)
            page.wait_for_function(
                "() => [...document.querySelectorAll('#active-alerts li')]"
                ".some(li => li.textContent.includes('bus: p99'))",
                timeout=10_000,
            )
    finally:
        camera.close()
        robot.close()
        gateway.close()
        broker.stop()
