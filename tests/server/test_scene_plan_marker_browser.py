"""The plan marker in a real Chromium (issue 17): the TIAGo rig's plan marker device publishes its pose,
the page draws the orange "target" cross where "plan here" will plan to and the robot's panel names its
coordinates; a non-finite marker sample takes it away."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from argon2 import PasswordHasher
from tests.server.test_scene_browser import PASSWORD, open_scene, settle, shot, states
from tests.server.test_scene_plan_marker import MARKER, TOPIC, _rig

from telerig.bus.acl import STATION, WEB, rig_access_policy
from telerig.bus.broker import MosquittoBroker
from telerig.bus.mqtt import MqttBus
from telerig.ir import wire
from telerig.ir.types import ControllerState, Stamp
from telerig.server.accounts import AccountStore
from telerig.server.app import create_app
from telerig.server.gateway import RigGateway

pytestmark = [pytest.mark.browser, pytest.mark.broker, pytest.mark.sim, pytest.mark.timeout(120)]

AIM = np.array([0xFF, 0x98, 0x00])  # the plan marker's colour


class _Tiago:
    """The TIAGo rig (with a plan marker) on Mosquitto, the control center, the marker device's login."""

    def __init__(self, tmp: Path, serve: Callable[..., str]) -> None:
        config = _rig()
        self.broker = MosquittoBroker(access=rig_access_policy(config), owner=STATION).start()
        self.gateway = RigGateway(config, self.broker.url_for(WEB)).start()
        accounts = AccountStore.open(tmp, hasher=PasswordHasher(time_cost=1, memory_cost=64, parallelism=1))
        accounts.add_user("vic", "viewer", PASSWORD)
        self.base = serve(create_app(accounts, gateway=self.gateway))
        self.device = MqttBus(self.broker.url_for("dev-vr0"), client_id="dev-vr0").connect()
        self.seq = 0

    def marker(self, position: np.ndarray[Any, Any]) -> None:
        self.seq += 1
        sample = ControllerState(
            Stamp.now("vr0/right", self.seq), "right", position, np.array([1.0, 0, 0, 0]), "operator"
        )
        self.device.publish(TOPIC, wire.encode(sample))

    def close(self) -> None:
        self.device.close()
        self.gateway.close()
        self.broker.stop()


@pytest.fixture
def tiago(tmp_path: Path, live_server: Callable[..., str]) -> Iterator[_Tiago]:
    rig = _Tiago(tmp_path, live_server)
    try:
        yield rig
    finally:
        rig.close()


def _aim(image: np.ndarray[Any, Any]) -> int:
    return int((np.abs(image - AIM).max(axis=2) < 60).sum())  # the software rasteriser blends edges


def test_the_plan_marker_is_drawn_as_the_target_and_leaves_on_garbage(
    page: Any, tiago: _Tiago, log_in: Callable[..., None]
) -> None:
    open_scene(page, tiago, log_in)  # type: ignore[arg-type]  # it reads .base only
    settle(page, "navigation", 0)  # top-down: the arm at zero points sideways, the target is ahead
    before = _aim(shot(page))  # the robot's own orange parts
    tiago.marker(np.array(MARKER))
    page.wait_for_function("() => document.querySelector('.plan-marker') !== null", timeout=10_000)
    assert page.evaluate("() => document.querySelector('.plan-marker').textContent") == "1.00, -0.20, 1.00 m"
    settle(page, "navigation", states(page))
    drawn = _aim(shot(page)) - before
    assert drawn > 40, f"the target marker covers {drawn} pixels"
    tiago.marker(np.array([np.nan, 0.0, 1.0]))
    page.wait_for_function("() => document.querySelector('.plan-marker') === null", timeout=10_000)
    settle(page, "navigation", states(page))
    assert _aim(shot(page)) <= before + 5
