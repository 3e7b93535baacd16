"""The scene draws the TIAGo's plan marker (issue 17): the marker device's pose, mapped by the plan
marker's alignment into the robot's world, is sent as ``plan_marker`` (labelled ``target``) where
"plan here" will plan the reach to; garbage, oversized and non-finite marker samples draw nothing and
the next good one draws again. A real Mosquitto with the rig's ACL; the device's login publishes."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest

from telerig.bus.acl import STATION, WEB, rig_access_policy
from telerig.bus.broker import MosquittoBroker
from telerig.bus.mqtt import MqttBus
from telerig.config import load_rig
from telerig.config.schema import RigConfig
from telerig.ir import wire
from telerig.ir.types import ControllerState, Stamp
from telerig.server.gateway import RigGateway
from telerig.server.scene import SceneHub

pytestmark = [pytest.mark.broker, pytest.mark.sim, pytest.mark.timeout(120)]

TOPIC = "telerig/v1/tiago_wbc/vr0/right_controller"
MARKER = np.array([0.4, -0.1, 1.1])  # operator frame [m]
TARGET = np.array([1.0, -0.2, 1.0])  # where the alignment below maps it in the robot's world [m]
ALIGNMENT = {
    "rotation": [math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)],
    "operator_origin": [0.3, -0.1, 1.0],
    "robot_origin": [1.0, -0.3, 0.9],
}


def _rig() -> RigConfig:
    doc: dict[str, Any] = load_rig("tiago_wbc").model_dump(mode="json")
    doc["cameras"] = []
    doc["devices"].append({"id": "vr0", "type": "scripted_vr"})
    doc["bindings"][0]["retargeter"]["plan_marker"] = {
        "device": "vr0",
        "part": "right_controller",
        "alignment": ALIGNMENT,
    }
    return RigConfig.model_validate(doc)


class _Hub:
    def __init__(self) -> None:
        config = _rig()
        self.broker = MosquittoBroker(access=rig_access_policy(config), owner=STATION).start()
        self.gateway = RigGateway(config, self.broker.url_for(WEB)).start()
        self.hub = SceneHub(self.gateway)
        self.hub.start()
        self.device = MqttBus(self.broker.url_for("dev-vr0"), client_id="dev-vr0").connect()
        self.seq = 0

    def controller(self, position: np.ndarray) -> None:
        self.seq += 1
        sample = ControllerState(
            Stamp.now("vr0/right", self.seq), "right", position, np.array([1.0, 0, 0, 0]), "operator"
        )
        self.device.publish(TOPIC, wire.encode(sample))

    def marker(self, until: Callable[[Any], bool], timeout_s: float = 5.0) -> Any:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            state: Any = self.hub.state()
            marker = state["robots"]["tiago0"]["plan_marker"]
            if until(marker):
                return marker
            time.sleep(0.05)
        raise AssertionError(f"plan marker never matched; last {marker}, dropped {self.hub.dropped}")

    def close(self) -> None:
        self.device.close()
        self.gateway.close()
        self.broker.stop()


@pytest.fixture(scope="module")
def hub() -> Iterator[_Hub]:
    running = _Hub()
    try:
        yield running
    finally:
        running.close()


def test_the_plan_marker_is_drawn_where_plan_here_plans_to(hub: _Hub) -> None:
    assert hub.hub.document()["plan_markers"] == [
        {"device": "vr0", "part": "right_controller", "robot": "tiago0"}
    ]
    hub.controller(MARKER)
    marker = hub.marker(lambda m: m is not None)
    assert marker["label"] == "target"
    assert np.linalg.norm(np.array(marker["pose"][:3]) - TARGET) < 1e-3
    assert marker["age_s"] < 5.0
    # The driving SpaceMouse has no alignment: no hand marker, only the plan marker.
    state: Any = hub.hub.state()
    assert state["robots"]["tiago0"]["hand"] is None


def test_garbage_marker_samples_draw_nothing_and_the_next_good_one_draws(hub: _Hub) -> None:
    hub.controller(MARKER)
    hub.marker(lambda m: m is not None)
    oversize = hub.hub.dropped["oversize"]
    for bad in (np.array([np.nan, 0.0, 1.0]), np.array([np.inf, 0.0, 1.0])):
        hub.controller(bad)
        hub.marker(lambda m: m is None)  # not drawn in the wrong place
        hub.controller(MARKER)
        hub.marker(lambda m: m is not None)
    hub.device.publish(TOPIC, b"\x00\xffnot a sample")
    hub.marker(lambda m: m is None)
    hub.device.publish(TOPIC, b"\x00" * (65 * 1024))  # above the catalogue's 64 KiB: dropped unread
    deadline = time.monotonic() + 5
    while hub.hub.dropped["oversize"] == oversize and time.monotonic() < deadline:
        time.sleep(0.05)
    assert hub.hub.dropped["oversize"] == oversize + 1
    hub.controller(np.array([1e6, 0.0, 1.0]))  # extreme but finite: drawn where it maps, finite
    far = hub.marker(lambda m: m is not None and m["pose"][1] > 1e5)
    assert all(math.isfinite(v) for v in far["pose"])
    hub.controller(MARKER)
    back = hub.marker(lambda m: m is not None and abs(m["pose"][1]) < 10)
    assert np.linalg.norm(np.array(back["pose"][:3]) - TARGET) < 1e-3
