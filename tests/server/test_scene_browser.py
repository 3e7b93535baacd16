"""The operator scene in a real Chromium (three.js from node_modules, WebGL in software), fed by a real
Mosquitto with the demo rig's ACL: the control node's, the device's and the camera's logins publish
what the runtime publishes (joint states, the fixture and motion scale aids, the controller, a JPEG
preview); the server's gateway logs in as ``web``.

The scene must render the UR5e at home like the committed reference (a tolerance for the software
rasteriser), move it when a joint state moves the arm, and draw a fixture's axis and plane when the
fixture is switched on. ``TELERIG_UPDATE_SCENE_REFERENCE=1`` writes the reference anew (look at it).
"""

from __future__ import annotations

import io
import json
import os
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from argon2 import PasswordHasher
from PIL import Image

from telerig.bus.acl import CLI, STATION, WEB, rig_access_policy
from telerig.bus.broker import MosquittoBroker
from telerig.bus.mqtt import MqttBus
from telerig.cameras.preview import stamp_jpeg
from telerig.config import load_rig
from telerig.ir import wire
from telerig.ir.types import ControllerState, JointCommand, JointState, RetargetResidual, Stamp
from telerig.robots.models import arm_model
from telerig.server.accounts import AccountStore
from telerig.server.app import create_app
from telerig.server.gateway import RigGateway
from telerig.server.scene import robot_geometry
from telerig.voice.dispatch import Dispatcher

pytestmark = [pytest.mark.browser, pytest.mark.broker, pytest.mark.sim, pytest.mark.timeout(120)]

PASSWORD = "correct horse battery"
REFERENCE = Path(__file__).parent / "data" / "scene_ur5e_home.png"
UR5E = arm_model("ur5e_robotiq85")
HOME, JOINTS = UR5E.home, UR5E.joints
R = "telerig/v1/demo"
VIEW = {"width": 480, "height": 360}
ORANGE = np.array([255, 167, 38])  # the fixture cue's colour (#ffa726)


class Demo:
    """The demo rig's broker, the control center on it, and publishers with the rig's logins."""

    def __init__(self, tmp: Path, serve: Callable[..., str]) -> None:
        self.config = load_rig("demo")
        self.broker = MosquittoBroker(access=rig_access_policy(self.config), owner=STATION).start()
        self.gateway = RigGateway(self.config, self.broker.url_for(WEB)).start()
        accounts = AccountStore.open(tmp, hasher=PasswordHasher(time_cost=1, memory_cost=64, parallelism=1))
        accounts.add_user("vic", "viewer", PASSWORD)
        self.base = serve(create_app(accounts, gateway=self.gateway))
        self.robot = MqttBus(self.broker.url_for("ctl-arm0"), client_id="ctl-arm0").connect()
        self.device = MqttBus(self.broker.url_for("dev-vr0"), client_id="dev-vr0").connect()
        self.camera = MqttBus(self.broker.url_for("cam-scene"), client_id="cam-scene").connect()
        self.seq = 0

    def joints(self, q: tuple[float, ...]) -> int:
        """Publish a joint state; returns its stamp's capture_ns [ns]."""
        self.seq += 1
        state = JointState(Stamp.now("arm0", self.seq), JOINTS, np.array(q), np.zeros(6))
        self.robot.publish(f"{R}/arm0/tick", wire.encode_bundle([("joint_state", wire.encode(state))]))
        return state.stamp.capture_ns

    def aid(self, stream: str, doc: dict[str, Any]) -> None:
        self.robot.publish(f"{R}/arm0/{stream}", json.dumps(doc).encode(), qos=1, retain=True)

    def close(self) -> None:
        for bus in (self.camera, self.device, self.robot):
            bus.close()
        self.gateway.close()
        self.broker.stop()


@pytest.fixture
def demo(tmp_path: Path, live_server: Callable[..., str]) -> Iterator[Demo]:
    rig = Demo(tmp_path, live_server)
    try:
        yield rig
    finally:
        rig.close()


def open_scene(page: Any, demo: Demo, log_in: Callable[..., None]) -> None:
    page.set_viewport_size(VIEW)
    log_in(page, demo.base, "vic", PASSWORD)
    page.goto(f"{demo.base}/scene")
    page.wait_for_function("() => window.sceneStats && window.sceneStats.scene !== null")
    hide = "for (const id of ['hud', 'robots']) document.getElementById(id).style.visibility = 'hidden'"
    page.evaluate(f"() => {{ {hide}; }}")  # screenshots of the 3D view alone


def states(page: Any) -> int:
    count: int = page.evaluate("() => window.sceneStats.states")
    return count


def settle(page: Any, mode: str, after: int) -> None:
    """Choose a view, wait for a state newer than ``after`` and for the camera to arrive."""
    page.evaluate("(mode) => { document.getElementById('mode').value = mode; }", mode)  # the HUD is hidden
    page.wait_for_function(f"() => window.sceneStats.states > {after} && window.sceneStats.settled")
    page.evaluate("() => new Promise((done) => requestAnimationFrame(() => requestAnimationFrame(done)))")


def rendered_stage(page: Any, demo: Demo, timeout_s: float = 10.0) -> dict[str, Any]:
    """arm0's ``rendered`` stage in the server's /api/rig once it has a sample (its window is 2 s)."""
    deadline = time.monotonic() + timeout_s
    while True:
        snapshot = page.request.get(f"{demo.base}/api/rig").json()
        (arm,) = [s for s in snapshot["latency_stages"] if s["node"] == "arm0"]
        stages: dict[str, dict[str, Any]] = {s["stage"]: s for s in arm["stages"]}
        if stages.get("rendered", {}).get("count", 0) > 0 or time.monotonic() > deadline:
            assert "rendered" in stages, (stages, demo.gateway.view.counts())
            return stages["rendered"]
        time.sleep(0.1)


def shot(page: Any) -> np.ndarray[Any, np.dtype[np.int16]]:
    png = page.locator("#view").screenshot()
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.int16)


def changed(a: np.ndarray[Any, Any], b: np.ndarray[Any, Any], threshold: int = 40) -> float:
    """Fraction of pixels whose largest channel difference exceeds ``threshold``."""
    return float((np.abs(a - b).max(axis=2) > threshold).mean())


def red(image: np.ndarray[Any, Any]) -> int:
    return int((np.abs(image - np.array([230, 20, 20])).max(axis=2) < 40).sum())


def orange(image: np.ndarray[Any, Any]) -> int:
    return int((np.abs(image - ORANGE).max(axis=2) < 25).sum())


def test_the_scene_renders_the_robot_like_the_reference_and_joint_updates_move_it(
    page: Any, demo: Demo, log_in: Callable[..., None]
) -> None:
    open_scene(page, demo, log_in)
    # The page's latency socket has its clock exchange before the first state (else its one report of
    # that stamp is dropped as unsynced).
    page.wait_for_function("() => window.sceneStats.latency?.syncs > 0", timeout=10_000)
    stamp = demo.joints(HOME)
    settle(page, "manipulation", 0)
    home = shot(page)
    # Drawn, reported (static/latency.js) and taken: the server's latency view has the robot's
    # `rendered` stage (issue 17), from this page alone.
    rendered = rendered_stage(page, demo)
    assert rendered["count"] == 1, rendered  # one report per stamp, however often the frame is drawn
    assert 0.0 <= rendered["p50_ms"] < (time.time_ns() - stamp) / 1e6, rendered
    assert demo.gateway.view.counts().get("rendered") == 1, demo.gateway.view.counts()
    if os.environ.get("TELERIG_UPDATE_SCENE_REFERENCE") == "1":
        REFERENCE.parent.mkdir(exist_ok=True)
        Image.fromarray(home.astype(np.uint8)).save(REFERENCE, optimize=True)
    assert REFERENCE.is_file(), f"no reference image {REFERENCE}: run with TELERIG_UPDATE_SCENE_REFERENCE=1"
    reference = np.asarray(Image.open(REFERENCE).convert("RGB"), dtype=np.int16)
    assert reference.shape == home.shape
    # Software rasterisers differ in edge pixels: at most 1 % of the pixels may differ visibly.
    assert changed(home, reference) < 0.01, f"{changed(home, reference):.2%} of the pixels differ"
    background = np.array([0x1D, 0x23, 0x2A])
    robot_pixels = (np.abs(home - background).max(axis=2) > 60).mean()
    assert robot_pixels > 0.03, f"only {robot_pixels:.1%} of the view is not background: no robot?"

    # Top-down, the camera does not follow the arm: what moves on screen is the arm itself.
    before = states(page)
    settle(page, "navigation", before)
    top = shot(page)
    turned = (0.9, -1.2, 1.2, -1.5708, -1.5708, 0.0)
    before = states(page)
    demo.joints(turned)
    settle(page, "navigation", before)
    moved = shot(page)
    assert changed(top, moved) > 0.005, f"only {changed(top, moved):.2%} of the pixels moved"
    before = states(page)
    demo.joints(HOME)
    settle(page, "navigation", before)
    assert changed(top, shot(page)) < 0.001, "back home, the view is not what it was"

    # The camera's JPEG preview shows as a panel beside the robot, in the same view.
    before = states(page)
    settle(page, "manipulation", before)
    assert red(shot(page)) < 50
    jpeg = io.BytesIO()
    Image.new("RGB", (160, 120), (230, 20, 20)).save(jpeg, format="JPEG")
    captured = time.time_ns() - 30_000_000  # stamped like the camera node's previews
    demo.camera.publish(f"{R}/scene/preview", stamp_jpeg(jpeg.getvalue(), captured, captured + 5_000_000))
    page.wait_for_function("() => window.sceneStats.previews > 0")
    page.evaluate("() => new Promise((done) => requestAnimationFrame(() => requestAnimationFrame(done)))")
    assert red(shot(page)) > 2000, f"the preview panel covers {red(shot(page))} pixels"
    # The page reported the stamped preview it drew: the camera's video_display stage.
    deadline = time.monotonic() + 10.0
    while demo.gateway.view.counts().get("displayed", 0) < 1 and time.monotonic() < deadline:
        time.sleep(0.1)
    assert demo.gateway.view.counts().get("displayed") == 1, demo.gateway.view.counts()


def test_a_fixture_switched_on_draws_its_axis_or_plane_and_the_aids_show(
    page: Any, demo: Demo, log_in: Callable[..., None]
) -> None:
    open_scene(page, demo, log_in)
    demo.joints(HOME)
    settle(page, "manipulation", 0)
    free = shot(page)
    assert orange(free) < 20, "a fixture cue is drawn while no fixture is on"

    fixture = {"name": "along-x", "kind": "axis", "axis": [1.0, 0.0, 0.0], "keep_orientation": False}
    demo.aid("fixture", {**fixture, "frame": "base", "options": ["free", "along-x", "table"]})
    page.wait_for_function("() => document.querySelector('.fixture')?.textContent === 'along-x'")
    before = states(page)
    settle(page, "manipulation", before)
    axis = shot(page)
    assert orange(axis) > 100, f"the axis cue covers {orange(axis)} pixels"

    plane = {"name": "table", "kind": "plane", "axis": [0.0, 0.0, 1.0], "keep_orientation": True}
    demo.aid("fixture", {**plane, "frame": "base", "options": ["free", "along-x", "table"]})
    page.wait_for_function("() => document.querySelector('.fixture')?.textContent === 'table'")
    before = states(page)
    settle(page, "manipulation", before)
    sheet = shot(page)
    assert changed(axis, sheet) > 0.01, "the plane cue looks like the axis cue"

    demo.aid("fixture", {"name": "free", "kind": "free", "axis": [0, 0, 0], "frame": "base", "options": []})
    page.wait_for_function("() => document.querySelector('.fixture')?.textContent === 'free'")
    before = states(page)
    settle(page, "manipulation", before)
    assert orange(shot(page)) < 20, "the cue stays after the fixture is switched off"

    # Motion scale and the hand <-> end-effector distance (the controller, aligned into the base frame).
    demo.aid("motion_scale", {"scale": 0.25, "min": 0.01, "max": 4.0, "step_factor": 2.0})
    at = np.array([0.45, 0.0, 1.10])  # 5 cm ahead of the operator origin: base (0.54, 0.134, 0.345)
    hand = ControllerState(Stamp.now("vr0", 1), "right", at, np.array([1.0, 0, 0, 0]), "operator")
    demo.device.publish(f"{R}/vr0/right_controller", wire.encode(hand))
    page.wait_for_function("() => document.querySelector('.distance') !== null")
    aids = "document.querySelector('.robot .aids').textContent"
    page.wait_for_function(f"() => {aids}.includes('scale \u00d70.250')")
    _, ee = robot_geometry(demo.config.robots[0]).poses(dict(zip(JOINTS, HOME, strict=True)))
    assert ee is not None
    expected = float(np.linalg.norm(np.array([0.54, 0.134, 0.345]) - np.array(ee, dtype=float)))
    shown = page.text_content(".distance")
    assert shown is not None
    assert abs(float(shown.split()[0]) - 1000 * expected) <= 2, (shown, expected)

    # Reachability, the commanded target and the safety state.
    demo.robot.publish(f"{R}/arm0/status", b"estopped", qos=1, retain=True)
    page.wait_for_function("() => document.querySelector('.status')?.dataset.status === 'estopped'")
    command = JointCommand(Stamp.now("arm0", 500), JOINTS, np.array(HOME))
    demo.robot.publish(
        f"{R}/arm0/tick", wire.encode_bundle([("joint_command_requested", wire.encode(command))])
    )
    page.wait_for_function("() => document.querySelector('.reach')?.textContent === 'target reachable'")
    metrics = ("position_error_m", "orientation_error_rad")
    residual = RetargetResidual(Stamp.now("arm0", 1), True, metrics, (0.12, 0.0))
    demo.robot.publish(f"{R}/arm0/tick", wire.encode_bundle([("residual", wire.encode(residual))]))
    page.wait_for_function("() => document.querySelector('.reach.warn')?.textContent.includes('by 120 mm')")

    # A perspective said or typed (telerig say, through the cli login) picks the view and shows the reply.
    cli = MqttBus(demo.broker.url_for(CLI), client_id="cli").connect()
    try:

        def publish(topic: str, payload: bytes, qos: int, retain: bool) -> None:
            cli.publish(topic, payload, qos=qos, retain=retain)

        assert Dispatcher("demo", publish, source="cli").handle("inverted perspective").status == "done"
        page.wait_for_function("() => document.getElementById('mode').value === 'ee-inverted'")
        reply = "document.getElementById('voice').textContent"
        page.wait_for_function(f"() => {reply}.includes('inverted perspective')")
    finally:
        cli.publish(f"{R}/voice/view", b"", qos=1, retain=True)
        cli.close()
