"""The shipped tiago_wbc rig end to end: a scripted SpaceMouse drives the TIAGo through the whole-body
controller, behind the safety chain, with a mode switch mid-episode; residuals land in the episode."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from telerig.config import load_rig
from telerig.ir.mcap_log import read_log, read_residuals
from telerig.ir.types import GripperCommand, JointCommand, JointState
from telerig.retarget.wbc import WholeBodyController
from telerig.robots.models.tiago import TIAGO_JOINTS, build_tiago_kinematics
from telerig.runtime.rig import RigRuntime

pytestmark = [pytest.mark.sim, pytest.mark.broker, pytest.mark.slow]

DURATION_S = 5.0
#: Ticks the base takes to brake from the script's whole-body speed (see the test that uses it).
BRAKE_TICKS = 15


@pytest.fixture(scope="module")
def episode(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One episode of the shipped rig without its camera (rendering is not under test here)."""
    rig = load_rig("tiago_wbc").model_copy(update={"cameras": []})
    with RigRuntime(rig, data_root=tmp_path_factory.mktemp("data")) as runtime:
        result = runtime.run_episode(DURATION_S)
    assert result.status == "complete"
    return result.path / "episode.mcap"


def _streams(path: Path) -> dict[str, list[object]]:
    by_stream: dict[str, list[object]] = {}
    for entry in read_log(path):
        by_stream.setdefault(entry.topic.split("/", 3)[-1], []).append(entry.sample)
    return by_stream


def _residuals(path: Path) -> list[dict[str, float]]:
    """The typed residuals of ``tiago0`` as ``{capture_ns, flagged, <metric>...}``."""
    return [
        {"capture_ns": r.stamp.capture_ns, "flagged": r.flagged, **r.metrics()}
        for topic, r, _ in read_residuals(path)
        if topic.endswith("/tiago0/residual")
    ]


def test_residual_records_task_errors_mode_and_action(episode: Path) -> None:
    records = _residuals(episode)
    assert len(records) > 200
    keys = {"ee_linear", "ee_angular", "base_linear", "base_angular", "elbow", "hand_position"}
    keys |= {
        "hand_orientation",
        "mode",
        "a_vx",
        "a_vy",
        "a_vz",
        "a_wx",
        "a_wy",
        "a_wz",
        "a_gripper",
        "a_mode",
        "solve_s",
    }
    assert keys <= set(records[0])
    modes = [r["mode"] for r in records]
    assert modes[0] == 0.0
    assert 1.0 in modes  # the scripted left-button press switched to whole-body mode ...
    assert modes[-1] == 0.0  # ... and the second press back
    assert not any(r["flagged"] for r in records)
    solve_s = np.array([r["solve_s"] for r in records])
    assert np.all((solve_s > 0) & (solve_s < 1.0))  # measured, and a tick's worth, not a clock jump


def test_commands_come_from_the_twist_and_keep_the_driver_joint_order(episode: Path) -> None:
    requested = [
        s for s in _streams(episode)["tiago0/joint_command_requested"] if isinstance(s, JointCommand)
    ]
    assert len(requested) > 200
    assert all(s.names == TIAGO_JOINTS and s.stamp.source_id == "sm0" for s in requested)


def test_base_moves_only_in_whole_body_mode(episode: Path) -> None:
    mode_at = {int(r["capture_ns"]): r["mode"] for r in _residuals(episode)}
    requested = [
        s for s in _streams(episode)["tiago0/joint_command_requested"] if isinstance(s, JointCommand)
    ]
    # The recorder may stop between a tick's request and its residual: the last request can lack one.
    assert sum(s.stamp.capture_ns not in mode_at for s in requested) <= 1
    ticks = [
        (s.stamp.capture_ns, mode_at[s.stamp.capture_ns], s.positions[:3])
        for s in requested
        if s.stamp.capture_ns in mode_at
    ]
    base0 = ticks[0][2]
    ticks_since_wb = None
    moved_in_wb = 0
    for i, (_, mode, base) in enumerate(ticks[1:], start=1):
        step = np.abs(base - ticks[i - 1][2]).max()
        if mode == 1.0:
            ticks_since_wb = 0
            moved_in_wb += step > 0
        elif ticks_since_wb is None:
            assert np.array_equal(base, base0)  # EE mode before any whole-body phase: still
        else:
            ticks_since_wb += 1
            # The brake runs per tick (dt = the 10 ms period): 0.15 m/s at 1 m/s^2, or 0.3 rad/s at
            # 2 rad/s^2, is 15 ticks. Counted in ticks, not wall time, which late ticks stretch; a
            # tick the recording lost only makes the count lag the robot's.
            assert ticks_since_wb <= 2 * BRAKE_TICKS or step == 0.0
    assert moved_in_wb > 100


def test_robot_followed_the_script(episode: Path) -> None:
    streams = _streams(episode)
    states = [s for s in streams["tiago0/joint_state"] if isinstance(s, JointState)]
    first, last = states[0].positions, states[-1].positions
    # Whole-body mode backed the base away from the table and turned it left.
    assert last[0] < first[0] - 0.08
    assert last[2] > first[2] + 0.2
    # The hand rose in EE mode: the torso or arm moved, measured.
    wbc = WholeBodyController(build_tiago_kinematics())
    p0, _ = wbc.hand_in_base(first)
    p1, _ = wbc.hand_in_base(last)
    assert p1[2] > p0[2] + 0.03
    grips = [s for s in streams["tiago0/gripper_command_requested"] if isinstance(s, GripperCommand)]
    assert grips[0].opening == 1.0
    assert grips[-1].opening == 0.0  # the right-button press closed it


def test_sent_commands_never_jump_across_mode_switches(episode: Path) -> None:
    sent = [s for s in _streams(episode)["tiago0/joint_command_sent"] if isinstance(s, JointCommand)]
    limits = build_tiago_kinematics().limits
    q = np.array([s.positions for s in sent])
    assert len(q) > 200
    # No joint moved faster than its speed limit over the safety chain's longest tick (two
    # periods of 10 ms: a late tick may catch up one period, never more).
    assert np.all(np.abs(np.diff(q, axis=0)) <= limits.velocity * 0.02 + 1e-9)
    # The controller's own velocities stayed within the limits through both switches.
    requested = [
        s for s in _streams(episode)["tiago0/joint_command_requested"] if isinstance(s, JointCommand)
    ]
    assert np.all(np.abs([s.velocities for s in requested]) <= limits.velocity + 1e-9)
