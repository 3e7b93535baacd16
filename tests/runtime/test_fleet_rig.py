"""The shipped fleet rig: six simulated robot kinds at once, each driven by its own device, nothing jumps."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from telerig.config import load_rig
from telerig.ir.mcap_log import read_log
from telerig.ir.types import GripperCommand, JointCommand, JointState
from telerig.robots.base import JointLimits
from telerig.runtime import streams
from telerig.runtime.process_settings import control_process
from telerig.runtime.rig import RigRuntime
from telerig.runtime.robot_host import Limits

if str(Path(__file__).parent) not in sys.path:
    sys.path.insert(0, str(Path(__file__).parent))
from command_steps import assert_steps_bounded

pytestmark = [pytest.mark.sim, pytest.mark.broker, pytest.mark.slow]

DURATION_S = 4.0
ROBOTS = ("ur5e", "panda", "gripper", "hand", "g1", "tiago")
RATES = {r.id: float(getattr(r, "control_rate_hz", 100.0)) for r in load_rig("fleet").robots}


@pytest.fixture(scope="module")
def fleet(
    tmp_path_factory: pytest.TempPathFactory,
) -> tuple[dict[str, dict[str, list[object]]], dict[str, JointLimits]]:
    """One recorded episode of the fleet: samples by robot and stream, and each robot's limits."""
    rig = load_rig("fleet")
    assert rig.cameras == []  # the shipped fleet renders nothing (software GL on this host)
    with (
        control_process(realtime_priority=rig.runtime.realtime_priority),  # as `telerig run` does
        RigRuntime(rig, data_root=tmp_path_factory.mktemp("data")) as runtime,
    ):
        result = runtime.run_episode(DURATION_S)
        assert set(runtime.hosts) == set(ROBOTS)  # one process per robot
        limits = {rid: host.call(Limits()) for rid, host in runtime.hosts.items()}
    assert result.status == "complete"
    by_robot: dict[str, dict[str, list[object]]] = {}
    for entry in read_log(result.path / "episode.mcap"):
        node, _, stream = entry.topic.split("/", 3)[-1].partition("/")
        by_robot.setdefault(node, {}).setdefault(stream, []).append(entry.sample)
    return by_robot, limits


def test_fleet_runs_all_six_sim_robot_kinds_each_on_its_own_device() -> None:
    rig = load_rig("fleet")
    assert tuple(r.id for r in rig.robots) == ROBOTS
    kinds = {r.type for r in rig.robots}
    assert kinds == {"mujoco_arm", "mujoco_gripper", "mujoco_hand", "mujoco_humanoid", "mujoco_tiago"}
    assert {getattr(r, "model", None) for r in rig.robots if r.type == "mujoco_arm"} == {
        "ur5e_robotiq85",
        "panda",
    }
    devices_of = {r.id: {b.device for b in rig.bindings if b.robot == r.id} for r in rig.robots}
    assert all(len(d) == 1 for d in devices_of.values())
    assert len({next(iter(d)) for d in devices_of.values()}) == len(ROBOTS)  # no device drives two robots


@pytest.mark.parametrize("robot", [r for r in ROBOTS if r != "gripper"])
def test_robot_received_retargeted_commands_and_its_joints_moved(
    fleet: tuple[dict[str, dict[str, list[object]]], dict[str, JointLimits]], robot: str
) -> None:
    samples, _ = fleet
    requested = [c for c in samples[robot][streams.JOINT_REQUESTED] if isinstance(c, JointCommand)]
    sent = [c for c in samples[robot][streams.JOINT_SENT] if isinstance(c, JointCommand)]
    states = [s for s in samples[robot][streams.JOINT_STATE] if isinstance(s, JointState)]
    assert len(requested) > 20
    assert len(sent) > 20
    measured = np.array([s.positions for s in states])
    assert float(np.max(np.ptp(measured, axis=0))) > 0.02  # [rad] or [m]: the robot moved


def test_gripper_alone_followed_its_trigger(
    fleet: tuple[dict[str, dict[str, list[object]]], dict[str, JointLimits]],
) -> None:
    samples, _ = fleet
    requested = [g for g in samples["gripper"][streams.GRIPPER_REQUESTED] if isinstance(g, GripperCommand)]
    sent = [g for g in samples["gripper"][streams.GRIPPER_SENT] if isinstance(g, GripperCommand)]
    states = [s for s in samples["gripper"][streams.JOINT_STATE] if isinstance(s, JointState)]
    # A gripper alone has no joint input: it applies every trigger request as it comes. The control
    # node publishes each tick's request and then what the driver applied; the recording window can
    # open or close between the two, so a pair may be cut at either end of the episode.
    assert len(requested) > 20
    assert _same_but_cut_pairs([g.opening for g in sent], [g.opening for g in requested])
    # Its one joint is the gripper's: nothing commands it as a joint, which would fight the trigger.
    assert streams.JOINT_SENT not in samples["gripper"]
    if min(g.opening for g in requested) < 0.5:  # the trigger closes 2 s into its (device) timeline
        finger = np.array([s.positions[0] for s in states])
        assert float(finger.max() - finger[0]) > 0.1  # [rad]: the fingers closed


@pytest.mark.parametrize("robot", [r for r in ROBOTS if r != "gripper"])
def test_sent_joint_steps_stay_within_velocity_limits(
    fleet: tuple[dict[str, dict[str, list[object]]], dict[str, JointLimits]], robot: str
) -> None:
    samples, limits = fleet
    sent = [c for c in samples[robot][streams.JOINT_SENT] if isinstance(c, JointCommand)]
    states = [s for s in samples[robot][streams.JOINT_STATE] if isinstance(s, JointState)]
    # The chain bounds each tick's step by the velocity limit times the time since its previous tick,
    # that time capped at two control periods: a step above that is a jump, unless it is a watchdog
    # stop on a starved loop, which commands the measured pose (a hand's fingers held by the object
    # they grip sit far from their command).
    period = 1.0 / RATES[robot]
    assert_steps_bounded(
        [(c.stamp.capture_ns / 1e9, np.asarray(c.positions)) for c in sent],
        [(s.stamp.capture_ns / 1e9, np.asarray(s.positions)) for s in states],
        limits[robot].velocity * 2 * period,
    )


def _same_but_cut_pairs(sent: list[float], requested: list[float]) -> bool:
    """Whether ``sent`` is ``requested`` tick for tick, but for at most one unpaired sample at each end
    (a request recorded without its send, or a send without its request)."""
    for head_sent, head_req in ((0, 0), (1, 0), (0, 1)):
        a, b = sent[head_sent:], requested[head_req:]
        n = min(len(a), len(b))
        if abs(len(a) - len(b)) <= 1 and a[:n] == pytest.approx(b[:n]):
            return True
    return False
