"""The WebXR page in a real Chromium, served by the control center over TLS behind its login, driving a
real rig (issue 14: one web server for the control center and the operator pages).

The shipped webxr rig (simulated UR5e, its camera left out) runs in-process with its embedded
Mosquitto and records an episode; the control center (gateway as ``web``, uvicorn over HTTPS with
a generated certificate) serves the dashboard and the page. Chromium logs in as an operator, follows
the dashboard's Teleoperate link, and the page, without a headset, streams its virtual controllers
(desktop mode, 60 Hz); a held key moves the right one. The robot's retargeted commands
(``arm0/joint_command_requested``) arrive on the rig's bus only once the page streams. A viewer
sees no Teleoperate link and is refused the page.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from argon2 import PasswordHasher

from telerig.bus.acl import STATION, WEB
from telerig.bus.base import Message
from telerig.bus.mqtt import MqttBus
from telerig.bus.ticks import picking
from telerig.config import load_rig
from telerig.config.schema import RigConfig
from telerig.devices.webxr.fake import FAKE_XR_SHIM
from telerig.devices.webxr.pairing import self_signed_pair
from telerig.ir import wire
from telerig.ir.types import ControllerState, HandPose, Pose, Sample
from telerig.runtime.session import EpisodeCommand
from telerig.server.accounts import AccountStore
from telerig.server.app import create_app
from telerig.server.gateway import RigGateway

pytestmark = [pytest.mark.browser, pytest.mark.sim, pytest.mark.broker, pytest.mark.timeout(180)]

PASSWORD = "correct horse battery"
TICK = "telerig/v1/webxr/arm0/tick"  # joint_command_requested travels in the robot's tick
SAMPLES = "telerig/v1/webxr/browser/+"


class Rig:
    """The webxr rig recording one episode in-process, and what its bus carried."""

    def __init__(self, tmp: Path) -> None:
        from telerig.runtime.rig import RigRuntime

        raw = load_rig("webxr").model_dump(mode="json")
        raw["cameras"] = []  # a camera costs this 2-core host frames; the page drives the arm alone
        self.config = RigConfig.model_validate(raw)
        self.runtime = RigRuntime(self.config, data_root=tmp / "data").__enter__()
        embedded = self.runtime.broker.embedded
        assert embedded is not None
        self.web_url = embedded.url_for(WEB)
        self.requested: list[float] = []
        self.samples: list[Sample] = []
        self.watch = MqttBus(embedded.url_for(STATION), client_id="xr-browser-test").connect()
        requested = picking({"joint_command_requested"}, lambda _m: self.requested.append(time.monotonic()))
        self.watch.subscribe(TICK, requested)
        self.watch.subscribe(SAMPLES, self._on_sample)
        self.episode = threading.Thread(target=self.runtime.run_episode, args=(60.0,), daemon=True)

    def _on_sample(self, message: Message) -> None:
        if message.topic.rsplit("/", 1)[-1] in ("health", "events", "page_out", "page_in"):
            return
        self.samples.append(wire.decode(message.payload))

    def latest(self, what: Callable[[Sample], bool]) -> Sample | None:
        return next((s for s in reversed(self.samples) if what(s)), None)

    def close(self) -> None:
        self.watch.close()
        self.runtime.__exit__(None, None, None)


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[Rig]:
    rig = Rig(tmp_path)
    try:
        yield rig
    finally:
        rig.close()


def wait_for(condition: Callable[[], object], what: str, timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return
        time.sleep(0.05)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


def test_an_operator_drives_the_robot_from_the_xr_page_and_a_viewer_may_not(
    rig: Rig,
    tmp_path: Path,
    live_server: Callable[..., str],
    browser_context: Any,
    log_in: Callable[..., None],
) -> None:
    accounts = AccountStore.open(
        tmp_path / "web", hasher=PasswordHasher(time_cost=1, memory_cost=64, parallelism=1)
    )
    accounts.add_user("otto", "operator", PASSWORD)
    accounts.add_user("vic", "viewer", PASSWORD)
    gateway = RigGateway(rig.config, rig.web_url).start()
    try:
        base = live_server(
            create_app(accounts, gateway=gateway), tls=self_signed_pair(tmp_path / "tls", "127.0.0.1")
        )
        assert base.startswith("https://")
        rig.episode.start()
        wait_for(
            lambda: (s := gateway.snapshot(alerts=0).session) is not None and s.state == "recording",
            "recording",
        )
        time.sleep(0.5)
        assert rig.requested == []  # nothing moves the robot before the page streams

        page = browser_context.new_page()
        page.add_init_script(FAKE_XR_SHIM)  # an emulated headset, used once Enter VR is pressed
        errors: list[str] = []
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        log_in(page, base, "otto", PASSWORD, start="/xr")  # the page sends a stranger to the login
        page.click("#xr-link")  # the dashboard's Teleoperate link
        page.wait_for_url(f"{base}/xr")
        page.wait_for_selector("#dot.ok")  # its WebSocket is open
        assert page.text_content("#device") == "browser"
        assert page.text_content("#mode") == "desktop"  # no session yet: the virtual controllers stream
        wait_for(lambda: rig.requested, "the robot's retargeted commands")
        start = rig.latest(_right())
        assert isinstance(start, ControllerState)
        page.keyboard.down("KeyW")  # move the right controller forward: operator +x
        wait_for(
            lambda: rig.latest(_right(lambda c: c.position[0] > start.position[0] + 0.1)), "W to move it"
        )
        page.keyboard.up("KeyW")
        page.screenshot(path=str(tmp_path / "xr-desktop.png"), full_page=True)

        page.click("#enter-vr")  # the emulated immersive session (fake-xr.js): head, controllers, hand
        wait_for(lambda: rig.latest(_right(lambda c: c.trigger == 0.75)), "the emulated right controller")
        right = rig.latest(_right(lambda c: c.trigger == 0.75))
        assert isinstance(right, ControllerState)
        np.testing.assert_allclose(right.position, [0.4, -0.25, 1.1], atol=1e-6)
        assert right.buttons == {"trigger", "a"}
        wait_for(lambda: rig.latest(lambda s: isinstance(s, HandPose)), "the emulated left hand")
        hand = rig.latest(lambda s: isinstance(s, HandPose))
        assert isinstance(hand, HandPose)
        np.testing.assert_allclose(hand.wrist_position, [0.3, 0.2, 1.0], atol=1e-6)
        wait_for(lambda: rig.latest(lambda s: isinstance(s, Pose)), "the emulated head")
        assert page.text_content("#mode") == "immersive-vr"
        # (its left controller holds Y, which discards the episode: the webxr rig's episode buttons)
        # the server counts the stream's frames; how many a headless page draws per second is the
        # host's business, so wait for them rather than read them once
        wait_for(lambda: _xr(page, base)[0]["counters"]["frames"] > 30, "30 frames counted")
        counters = _xr(page, base)[0]["counters"]
        assert not [k for k in counters if k.startswith("drop_")], counters
        assert errors == []

        viewer = browser_context.browser.new_context(ignore_https_errors=True).new_page()
        log_in(viewer, base, "vic", PASSWORD)
        viewer.wait_for_selector("#who:has-text('viewer')")
        assert viewer.is_hidden("#xr-link")
        assert viewer.goto(f"{base}/xr").status == 403
        viewer.context.close()
    finally:
        if gateway.connected and rig.episode.is_alive():
            gateway.send_session(EpisodeCommand(command="stop", source="web"))
        rig.episode.join(30)
        gateway.close()
        accounts.close()
    assert not rig.episode.is_alive()


def _xr(page: Any, base: str) -> list[dict[str, Any]]:
    reply = page.request.get(f"{base}/api/xr")
    assert reply.status == 200
    devices: list[dict[str, Any]] = reply.json()
    return devices


def _right(what: Callable[[ControllerState], bool] = lambda _c: True) -> Callable[[Sample], bool]:
    return lambda s: isinstance(s, ControllerState) and s.hand == "right" and what(s)
