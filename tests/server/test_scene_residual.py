"""The scene draws a robot's IK residual (issue 18: a typed RetargetResidual, in the robot's tick):
the flag and the metrics reach the page; undecodable, wrong-type, non-finite and JSON residuals
draw nothing and are counted, oversized ones are dropped unread, and the next good one draws again.
A real Mosquitto with the demo rig's ACL; the control node's login publishes."""

from __future__ import annotations

import json
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
from telerig.ir import wire
from telerig.ir.types import JointState, RetargetResidual, Stamp
from telerig.server.gateway import RigGateway
from telerig.server.scene import SceneHub

pytestmark = [pytest.mark.broker, pytest.mark.sim, pytest.mark.timeout(120)]

TICK = "telerig/v1/demo/arm0/tick"
METRICS = ("position_error_m", "orientation_error_rad")


class _Hub:
    def __init__(self) -> None:
        config = load_rig("demo").model_copy(update={"cameras": []})
        self.broker = MosquittoBroker(access=rig_access_policy(config), owner=STATION).start()
        self.gateway = RigGateway(config, self.broker.url_for(WEB)).start()
        self.hub = SceneHub(self.gateway)
        self.hub.start()
        self.robot = MqttBus(self.broker.url_for("ctl-arm0"), client_id="ctl-arm0").connect()
        self.seq = 0

    def residual(self, flagged: bool, values: tuple[float, ...]) -> None:
        self.seq += 1
        sample = RetargetResidual(Stamp.now("arm0", self.seq), flagged, METRICS, values)
        self.publish(wire.encode(sample))

    def publish(self, residual: bytes) -> None:
        """``residual`` as the residual part of a control tick."""
        self.robot.publish(TICK, wire.encode_bundle([("residual", residual)]))

    def drawn(self, until: Callable[[Any], bool], timeout_s: float = 5.0) -> Any:
        deadline = time.monotonic() + timeout_s
        residual = None
        while time.monotonic() < deadline:
            state: Any = self.hub.state()
            residual = state["robots"]["arm0"]["residual"]
            if until(residual):
                return residual
            time.sleep(0.05)
        raise AssertionError(f"residual never matched; last {residual}, dropped {self.hub.dropped}")

    def close(self) -> None:
        self.robot.close()
        self.gateway.close()
        self.broker.stop()


@pytest.fixture(scope="module")
def hub() -> Iterator[_Hub]:
    running = _Hub()
    try:
        yield running
    finally:
        running.close()


def test_a_typed_residual_reaches_the_page_with_its_flag_and_metrics(hub: _Hub) -> None:
    hub.residual(True, (0.12, 0.5))
    drawn = hub.drawn(lambda r: r is not None and r["flagged"])
    assert drawn == {"flagged": True, "position_error_m": 0.12, "orientation_error_rad": 0.5}
    json.dumps(drawn, allow_nan=False)
    hub.residual(False, (0.001, 0.0))
    assert hub.drawn(lambda r: r is not None and not r["flagged"])["position_error_m"] == 0.001
    hub.residual(True, (1e308, 0.0))  # finite, if absurd: shown as recorded
    assert hub.drawn(lambda r: r is not None and r["flagged"])["position_error_m"] == 1e308


def test_garbage_residuals_draw_nothing_are_counted_and_the_next_good_one_draws(hub: _Hub) -> None:
    state = JointState(Stamp.now("arm0", 1), ("j",), np.zeros(1), np.zeros(1))
    good = wire.encode(RetargetResidual(Stamp.now("arm0", 1), True, METRICS, (0.3, 0.0)))
    garbage: list[bytes] = [
        wire.encode(RetargetResidual(Stamp.now("arm0", 2), True, METRICS, (math.nan, 0.0))),
        wire.encode(RetargetResidual(Stamp.now("arm0", 3), True, METRICS, (0.1, math.inf))),
        good[: len(good) // 2],  # truncated
        b"\x00\xffnot a sample",
        wire.encode(state),  # another IR type on the residual topic
        b'{"capture_ns": 1, "position_error_m": 0.1, "flagged": true}',  # the JSON of earlier nodes
        b"[1, 2, 3]",
    ]
    for payload in garbage:
        bad = hub.hub.dropped["bad_residual"]
        hub.publish(good)
        hub.drawn(lambda r: r is not None and r.get("position_error_m") == 0.3)
        hub.publish(payload)
        hub.drawn(lambda r: r is None)  # not drawn with a stale or wrong value
        assert hub.hub.dropped["bad_residual"] == bad + 1, payload[:40]
    oversize = hub.hub.dropped["oversize"]
    hub.publish(b"\x00" * (65 * 1024))  # above the catalogue's 64 KiB: dropped unread
    deadline = time.monotonic() + 5
    while hub.hub.dropped["oversize"] == oversize and time.monotonic() < deadline:
        time.sleep(0.05)
    assert hub.hub.dropped["oversize"] == oversize + 1
    hub.residual(False, (0.004, 0.0))
    assert hub.drawn(lambda r: r is not None and r.get("position_error_m") == 0.004)["flagged"] is False
