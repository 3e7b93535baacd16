"""The reach plan cue in a real Chromium (issue 17): a staged plan on a robot's retained ``plan`` stream
draws the base path, the grasp point path and the goal, and the HUD says how to run it; executing
recolours it, done removes it; a garbage plan draws nothing and is counted."""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from tests.server.test_scene_browser import HOME, Demo, R, open_scene, settle, shot, states

from telerig.server.scene import _plan_cue

pytestmark = [pytest.mark.browser, pytest.mark.broker, pytest.mark.sim, pytest.mark.timeout(120)]

STAGED = np.array([0x29, 0xB6, 0xF6])  # the staged plan's colour
EXECUTING = np.array([0x66, 0xBB, 0x6A])


def _pixels(image: np.ndarray[Any, Any], colour: np.ndarray[Any, Any]) -> int:
    return int((np.abs(image - colour).max(axis=2) < 25).sum())


def _plan(status: str, **extra: Any) -> dict[str, Any]:
    ee = [[0.5 + 0.01 * i, 0.1 - 0.01 * i, 0.5] for i in range(30)]
    base = [[0.01 * i, 0.0, 0.0] for i in range(30)]
    return {
        "id": "1-0a1b2c3d",
        "status": status,
        "reason": "base then arm; say 'robot please execute' to run it" if status == "staged" else "",
        "target": {"position": ee[-1], "orientation": [1, 0, 0, 0]},
        "base_path": base,
        "ee_path": ee,
        **extra,
    }


@pytest.fixture
def demo(tmp_path: Path, live_server: Callable[..., str]) -> Iterator[Demo]:
    rig = Demo(tmp_path, live_server)
    try:
        yield rig
    finally:
        rig.close()


def _show(page: Any, demo: Demo, doc: dict[str, Any] | bytes, status: str) -> np.ndarray[Any, Any]:
    payload = doc if isinstance(doc, bytes) else json.dumps(doc).encode()
    demo.robot.publish(f"{R}/arm0/plan", payload, qos=1, retain=True)
    page.wait_for_function(
        "(s) => document.querySelector('.plan')?.dataset.status === s", arg=status, timeout=10_000
    )
    settle(page, "manipulation", states(page))
    return shot(page)


def test_a_staged_plan_is_drawn_with_the_hud_line_and_leaves_when_done(
    page: Any, demo: Demo, log_in: Callable[..., None]
) -> None:
    open_scene(page, demo, log_in)
    demo.joints(HOME)
    settle(page, "manipulation", 0)
    assert _pixels(shot(page), STAGED) < 20

    staged = _show(page, demo, _plan("staged"), "staged")
    assert _pixels(staged, STAGED) > 60, f"the plan cue covers {_pixels(staged, STAGED)} pixels"
    hud = page.evaluate("() => document.querySelector('.plan').textContent")
    assert hud == "plan staged — say 'robot please execute'"

    executing = _show(page, demo, _plan("executing"), "executing")
    assert _pixels(executing, EXECUTING) > 60
    assert _pixels(executing, STAGED) < 20

    done = _show(page, demo, _plan("done", reason="reached the target"), "done")
    assert _pixels(done, EXECUTING) < 20
    assert (
        page.evaluate("() => document.querySelector('.plan').textContent") == "plan done: reached the target"
    )

    # Garbage after a staged plan: a non-finite point, an oversized path, not an object, an unknown
    # status. The hub drops each (the cue goes away), never draws it.
    nan = json.dumps(_plan("staged")).replace("0.5]", "NaN]", 1).encode()
    garbage: list[dict[str, Any] | bytes] = [
        nan,
        _plan("staged", ee_path=[[0.5, 0.0, 0.5]] * 65),
        _plan("armed"),
    ]  # more kinds in test_plan_cue_refuses_garbage
    for bad in garbage:
        _show(page, demo, _plan("staged"), "staged")
        assert _pixels(_show(page, demo, bad, "none"), STAGED) < 20


@pytest.mark.parametrize(
    "doc",
    [
        {"id": "1-a", "status": "staged", "reason": "", "ee_path": [[float("inf"), 0, 0]]},
        {"id": "1-a", "status": "staged", "reason": "", "ee_path": [[0, 0, 0]] * 65},
        {"id": "1-a", "status": "staged", "reason": "", "base_path": [[0, 0]]},
        {"id": "1-a", "status": "staged", "reason": "", "base_path": [[True, 0, 0]]},
        {"id": "1-a", "status": "staged", "reason": "", "ee_path": [[1e9, 0, 0]]},
        {"id": "x" * 65, "status": "staged", "reason": ""},
        {"id": None, "status": "launched", "reason": ""},
        {"id": None, "status": "none", "reason": 5},
        {"id": "1-a", "status": "staged", "reason": "", "base_path": [[0.0, 0.0, "x"]]},
    ],
)
def test_plan_cue_refuses_garbage(doc: dict[str, Any]) -> None:
    with pytest.raises(ValueError, match="plan"):
        _plan_cue(doc)
