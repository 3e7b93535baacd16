"""The rig's safety settings reach every robot: workspace guard, alerts on the safety topic, fault policy."""

from __future__ import annotations

import json
import threading
from typing import Any

import numpy as np
import pytest

from telerig.config import load_rig
from telerig.config.schema import RigConfig
from telerig.robots.sim.arm import MujocoArm
from telerig.runtime.rig import RigRuntime

pytestmark = [pytest.mark.sim, pytest.mark.broker, pytest.mark.slow]

_FLOOR_M = 0.15  # the scripted operator picks the cube at ~0.02 m: well below this floor


def _rig(safety: dict[str, Any]) -> RigConfig:
    raw = load_rig("demo").with_isolation("threads").model_dump(mode="json", exclude_none=True)
    raw["cameras"] = []
    raw["safety"].update(safety)
    return RigConfig.model_validate(raw)


def test_the_workspace_floor_stops_the_arm_above_it_and_alerts(tmp_path: Any) -> None:
    rig = _rig(
        {
            "robots": {
                "arm0": {"workspace": {"box": {"lower": [-1.0, -1.0, _FLOOR_M], "upper": [1.0, 1.0, 1.5]}}}
            }
        }
    )
    alerts: list[dict[str, Any]] = []
    lowest = [np.inf]
    with RigRuntime(rig, data_root=tmp_path) as runtime:
        runtime.recorder.bus.subscribe(
            "telerig/v1/demo/safety/alerts", lambda m: alerts.append(json.loads(m.payload))
        )
        arm = runtime.robots["arm0"]
        assert isinstance(arm, MujocoArm)
        done = threading.Event()

        def watch() -> None:
            site = arm.scene.ee_site
            while not done.wait(0.01):
                with arm.locked() as (_, data):
                    base = data.body(arm.scene.base_body)
                    p = base.xmat.reshape(3, 3).T @ (data.site(site).xpos - base.xpos)  # base frame
                lowest[0] = min(lowest[0], float(p[2]))

        watcher = threading.Thread(target=watch)
        watcher.start()
        try:
            runtime.run_episode(6.0)  # the scripted pick reaches down at ~4 s
        finally:
            done.set()
            watcher.join()
        counts = runtime.controls["arm0"].safety.counts
    assert counts["workspace"] > 0
    assert lowest[0] > _FLOOR_M - 0.01  # never below the floor (braking stays inside the margin)
    codes = {a["code"] for doc in alerts for a in doc.get("active_alerts", [])}
    assert "workspace" in codes


def test_safety_settings_of_an_unknown_robot_are_refused() -> None:
    raw = load_rig("demo").model_dump(mode="json", exclude_none=True)
    raw["safety"]["robots"] = {"ghost": {"self_collision": True}}
    with pytest.raises(ValueError, match=r"safety.robots.ghost.*'ghost'"):
        RigConfig.model_validate(raw)


def test_a_deadman_on_an_unknown_device_is_refused() -> None:
    raw = load_rig("demo").model_dump(mode="json", exclude_none=True)
    raw["safety"]["robots"] = {"arm0": {"deadman": {"stream": "pedal0/pedal", "button": "press"}}}
    with pytest.raises(ValueError, match=r"deadman.stream.*'pedal0'"):
        RigConfig.model_validate(raw)
