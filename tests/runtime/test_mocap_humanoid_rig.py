"""The shipped mocap_humanoid rig: a BVH body skeleton drives the simulated G1's upper body end to end."""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from telerig.config import load_rig, parse_rig, shipped_rig_path
from telerig.errors import ConfigError
from telerig.ir.mcap_log import read_log, read_residuals
from telerig.ir.types import BodySkeleton, JointCommand, JointState
from telerig.runtime.rig import RigRuntime

pytestmark = [pytest.mark.sim, pytest.mark.broker, pytest.mark.slow]

_PELVIS_HEIGHT = 0.795  # [m], standing, as built (the G1 URDF on straight legs)


def _streams(mcap: Path) -> tuple[dict[str, list[Any]], list[dict[str, Any]]]:
    """IR samples by stream (``<node>/<stream>``) and the residuals of ``g1`` as
    ``{capture_ns, flagged, <metric>...}``."""
    samples: dict[str, list[Any]] = {}
    for entry in read_log(mcap):
        samples.setdefault(entry.topic.split("/", 3)[-1], []).append(entry.sample)
    residuals = [
        {"capture_ns": r.stamp.capture_ns, "flagged": r.flagged, **r.metrics()}
        for topic, r, _ in read_residuals(mcap)
        if topic.endswith("/g1/residual")
    ]
    return samples, residuals


def test_body_mocap_drives_the_humanoid_arms_smoothly_with_residuals_recorded(tmp_path: Path) -> None:
    rig = load_rig("mocap_humanoid").model_copy(update={"cameras": []})
    with RigRuntime(rig, data_root=tmp_path) as runtime:
        result = runtime.run_episode(3.0)
        pelvis, _ = runtime.robots["g1"].pelvis_pose()  # type: ignore[attr-defined]
        robot = runtime.robots["g1"]
        limits = robot.limits
        flagged_ticks = runtime.controls["g1"].stats.ik_flagged
    period = 1.0 / 100.0  # the rig's control_rate_hz
    assert result.status == "complete"
    samples, residuals = _streams(result.path / "episode.mcap")
    assert all(isinstance(s, BodySkeleton) for s in samples["mocap0/body"])
    requested = samples["g1/joint_command_requested"]
    assert len(requested) > 60  # 60 Hz skeletons for 3 s, with slack for a loaded machine
    assert all(isinstance(c, JointCommand) and c.stamp.source_id == "mocap0/body" for c in requested)
    assert all(c.names == robot.joint_names for c in requested)

    # The arms follow: the clip reaches forward with the right arm (shoulder pitch swings > 0.5 rad).
    sent = [c for c in samples["g1/joint_command_sent"] if isinstance(c, JointCommand)]
    q = np.array([c.positions for c in sent])
    shoulder = robot.joint_names.index("right_shoulder_pitch_joint")
    assert np.ptp(q[:, shoulder]) > 0.5
    states = [s for s in samples["g1/joint_state"] if isinstance(s, JointState)]
    measured = np.array([s.positions for s in states])
    assert np.ptp(measured[:, shoulder]) > 0.5

    # Residuals: one record per solved skeleton (the stop may fall between a command and its
    # residual), flagged exactly when a wrist misses by more than the rig's 5 cm, and small once
    # the arms caught up with the performer.
    assert abs(len(residuals) - len(requested)) <= 1
    wrist = np.array([[r["right_wrist_error_m"], r["left_wrist_error_m"]] for r in residuals])
    flagged = np.array([r["flagged"] for r in residuals])
    np.testing.assert_array_equal(flagged, wrist.max(axis=1) > 0.05)
    assert 0 < int(flagged.sum()) <= flagged_ticks  # the approach from home is flagged
    settled = wrist[len(wrist) // 3 :]  # the first second covers the approach from home
    assert float(np.median(settled.max(axis=1))) < 0.05

    # Nothing jumps: no sent step exceeds the speed limit over the longest tick the chain allows
    # (two control periods), and neither does the measured motion between states.
    steps = np.abs(np.diff(q, axis=0))
    assert np.all(steps <= limits.velocity * 2 * period + 1e-9)
    assert float(np.max(np.abs(np.diff(measured, axis=0)))) < 0.15  # [rad] between 100 Hz states

    # The harness holds the pelvis up while the arms swing.
    assert abs(float(pelvis[2]) - _PELVIS_HEIGHT) < 0.02


@pytest.fixture
def rig_data() -> dict[str, Any]:
    data = yaml.safe_load(shipped_rig_path("mocap_humanoid").read_text())
    assert isinstance(data, dict)
    return data


@pytest.mark.parametrize(
    ("mutate", "expected"),
    [
        (lambda d: d["robots"][0].update(control_rate_hz=300), "whole multiple of control_rate_hz"),
        (lambda d: d["robots"][0].update(support="rope"), "robots[0].support: Input should be 'fixed' or"),
        (lambda d: d["robots"][0].update(model="h1"), "robots[0].model: Input should be 'g1'"),
        (
            lambda d: d["bindings"][0]["retargeter"].update(profile="kinect"),
            "bindings[0].retargeter.profile: Input should be 'mediapipe', 'cmu' or 'motive'",
        ),
        (
            lambda d: d["bindings"][0]["retargeter"].update(residual_threshold_m=0),
            "bindings[0].retargeter.residual_threshold_m: Input should be greater than 0",
        ),
    ],
)
def test_bad_humanoid_rig_fails_with_one_line_naming_the_field(
    rig_data: dict[str, Any], mutate: Any, expected: str
) -> None:
    data = copy.deepcopy(rig_data)
    mutate(data)
    with pytest.raises(ConfigError) as info:
        parse_rig(data, source="rig.yaml")
    assert "\n" not in str(info.value)
    assert expected in str(info.value)


def test_a_gripper_bound_to_the_handless_g1_is_refused_before_anything_runs(tmp_path: Path) -> None:
    raw = load_rig("mocap_humanoid").model_dump(mode="json", exclude_none=True)
    raw["cameras"] = []
    raw["devices"].append({"id": "vr0", "type": "scripted_vr"})
    raw["bindings"].append(
        {
            "device": "vr0",
            "part": "right_controller",
            "robot": "g1",
            "target": "gripper",
            "retargeter": {"type": "trigger_gripper"},
        }
    )
    runtime = RigRuntime(parse_rig(raw, source="rig.yaml"), data_root=tmp_path)
    refused = r"^binding vr0.right_controller → g1.gripper: robot 'g1' has no gripper for 'trigger_gripper'"
    with pytest.raises(ConfigError, match=refused):
        runtime.open()
    runtime.close()
