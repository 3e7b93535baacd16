"""The real page in headless Chromium: desktop keys, and the XR path through an emulated navigator.xr."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from telerig.devices.webxr.device import WebXRDevice
from telerig.devices.webxr.fake import FAKE_XR_SHIM
from telerig.ir.frames import quat_rotate
from telerig.ir.types import ControllerState, HandPose, Pose, Sample

CHROMIUM = Path("/usr/bin/chromium")
TIMEOUT_S = 10.0
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]

pytestmark = pytest.mark.browser


@pytest.fixture(autouse=True)
def _chromium_installed() -> None:
    # A required component of the suite: a missing browser fails with the fix, it does not skip.
    if not CHROMIUM.exists():
        pytest.fail(
            f"Chromium is missing at {CHROMIUM}: run `make sysdeps-test` (apt-get install chromium)",
            pytrace=False,
        )


class Collector:
    """A sink that keeps every sample and lets a test wait for one matching a predicate."""

    def __init__(self) -> None:
        self.samples: list[Sample] = []
        self._cond = threading.Condition()

    def __call__(self, sample: Sample) -> None:
        with self._cond:
            self.samples.append(sample)
            self._cond.notify_all()

    def wait_for(self, predicate: Callable[[Sample], bool], what: str) -> Sample:
        found: list[Sample] = []

        def check() -> bool:
            found[:] = [s for s in self.samples if predicate(s)][-1:]
            return bool(found)

        with self._cond:
            assert self._cond.wait_for(check, TIMEOUT_S), f"timed out waiting for {what}"
        return found[0]


def controller(
    hand: str, predicate: Callable[[ControllerState], bool] = lambda _c: True
) -> Callable[[Sample], bool]:
    return lambda s: isinstance(s, ControllerState) and s.hand == hand and predicate(s)


@pytest.fixture
def device() -> Iterator[tuple[WebXRDevice, Collector]]:
    dev = WebXRDevice("xr0", host="127.0.0.1", port=0)
    sink = Collector()
    dev.start(sink)
    yield dev, sink
    dev.stop()


@pytest.fixture
def browser_context(tmp_path: Path) -> Iterator[Any]:
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        context = pw.chromium.launch_persistent_context(
            str(tmp_path / "profile"), executable_path=str(CHROMIUM), headless=True, args=CHROMIUM_ARGS
        )
        try:
            yield context
        finally:
            context.close()


def test_desktop_keys_move_the_virtual_controller(
    device: tuple[WebXRDevice, Collector], browser_context: Any, tmp_path: Path
) -> None:
    dev, sink = device
    page = browser_context.new_page()
    page.goto(dev.url)
    start = sink.wait_for(controller("right"), "a first desktop sample")
    assert isinstance(start, ControllerState)
    x0, y0, z0 = start.position
    page.keyboard.down("KeyW")  # forward: operator +x
    moved = sink.wait_for(controller("right", lambda c: c.position[0] > x0 + 0.1), "W to move the controller")
    page.keyboard.up("KeyW")
    assert isinstance(moved, ControllerState)
    np.testing.assert_allclose(moved.position[1:], [y0, z0], atol=1e-6)
    page.keyboard.down("KeyR")  # up: operator +z
    sink.wait_for(controller("right", lambda c: c.position[2] > z0 + 0.1), "R to raise the controller")
    page.keyboard.up("KeyR")
    page.keyboard.down("Space")
    page.keyboard.down("Digit1")
    pressed = sink.wait_for(
        controller("right", lambda c: "a" in c.buttons), "Space + 1 to press trigger and A"
    )
    assert isinstance(pressed, ControllerState)
    assert (pressed.trigger, "trigger" in pressed.buttons) == (1.0, True)
    page.screenshot(path=str(tmp_path / "desktop.png"))
    page.keyboard.up("Space")
    page.keyboard.up("Digit1")
    sink.wait_for(
        controller("right", lambda c: c.trigger == 0.0 and not c.buttons), "the keys to be released"
    )
    assert (tmp_path / "desktop.png").stat().st_size > 10_000


def test_emulated_xr_session_streams_head_controllers_and_hand(
    device: tuple[WebXRDevice, Collector], browser_context: Any
) -> None:
    dev, sink = device
    page = browser_context.new_page()
    page.add_init_script(FAKE_XR_SHIM)
    page.goto(dev.url)
    page.click("#enter-vr")
    right = sink.wait_for(controller("right", lambda c: c.trigger == 0.75), "the emulated right controller")
    left = sink.wait_for(controller("left", lambda c: c.grip == 1.0), "the emulated left controller")
    hand = sink.wait_for(lambda s: isinstance(s, HandPose), "the emulated left hand")
    first_head = sink.wait_for(lambda s: isinstance(s, Pose), "the emulated head")
    assert isinstance(first_head, Pose)
    head = sink.wait_for(
        lambda s: isinstance(s, Pose) and s.position[0] > first_head.position[0] + 0.02,
        "the head to walk forward",
    )
    assert isinstance(right, ControllerState)
    assert isinstance(left, ControllerState)
    assert isinstance(hand, HandPose)
    assert isinstance(head, Pose)
    np.testing.assert_allclose(right.position, [0.4, -0.25, 1.1], atol=1e-6)
    assert right.buttons == {"trigger", "a"}
    np.testing.assert_allclose(right.joystick, [0.5, 1.0])
    assert left.buttons == {"grip", "y"}
    # Grip turned 90 deg left: the pointing axis (controller +z) points to operator +y (left).
    np.testing.assert_allclose(quat_rotate(left.orientation, np.array([0.0, 0.0, 1.0])), [0, 1, 0], atol=1e-6)
    assert hand.handedness == "left"
    np.testing.assert_allclose(hand.wrist_position, [0.3, 0.2, 1.0], atol=1e-6)
    np.testing.assert_allclose(hand.keypoints[8], [0.4, 0.22, 1.0], atol=1e-6)  # index tip
    np.testing.assert_allclose(head.position[1:], [0.0, 1.6], atol=1e-6)
    assert page.evaluate("window.telerigXR.mode") == "immersive-vr"
