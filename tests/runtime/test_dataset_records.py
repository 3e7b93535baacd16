"""What recorded episodes carry for quality gates and exports (issue 13): each robot's joint order,
limits, gripper and standing height, each camera's configured size, rate and codec, and the
measured gripper opening and wrist force/torque streams at the control rate."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from telerig.bus.base import Message
from telerig.bus.memory import InMemoryBus
from telerig.bus.ticks import TICK, picking
from telerig.bus.topics import Topic
from telerig.config import load_rig
from telerig.config.schema import RigConfig
from telerig.ir import wire
from telerig.ir.mcap_log import read_log
from telerig.ir.types import GripperCommand, Pose, Wrench
from telerig.robots.models.arms import UR5E_ROBOTIQ85
from telerig.robots.models.g1 import G1_PELVIS_HEIGHT, UPPER_BODY_JOINTS
from telerig.robots.sim.config import MujocoHumanoidConfig, MujocoTiagoConfig
from telerig.robots.sim.humanoid import MujocoHumanoid, build_humanoid_scene
from telerig.runtime.control_node import ControlNode
from telerig.runtime.rig import RigRuntime
from telerig.runtime.robot_record import robot_joints_record
from telerig.safety import SafetyChain
from telerig.store.episodes import EpisodeStore
from telerig.store.manifest_extra import EpisodeExtra

pytestmark = [pytest.mark.sim, pytest.mark.broker, pytest.mark.slow]


def _demo(*, isolated: bool, camera: bool) -> RigConfig:
    raw: dict[str, Any] = load_rig("demo").model_dump(mode="json")
    if camera:  # a small camera: the manifest must carry its configured size, rate and codec
        raw["cameras"][0].update(width=160, height=120, fps=10.0)
    else:
        raw["cameras"] = []
    if isolated:
        raw["runtime"] = {"isolation": "processes"}
    # What is recorded is under test here, not the gates (a loaded host's gaps would move it).
    raw["qa"] = {"after_commit": False}
    return RigConfig.model_validate(raw)


def _record(tmp_path: Path, rig: RigConfig, duration_s: float) -> tuple[EpisodeExtra, Path]:
    """Record one episode; its typed manifest extra and its MCAP file."""
    with RigRuntime(rig, data_root=tmp_path) as runtime:
        result = runtime.run_episode(duration_s)
    assert result.status == "complete"
    store = EpisodeStore(tmp_path)
    extra = EpisodeExtra.of(store.get(result.episode_id))
    return extra, store.episode_dir(result.episode_id) / "episode.mcap"


def _stream(extra: EpisodeExtra, stream: str) -> dict[str, object]:
    """The manifest's statistics of ``<node>/<stream>``."""
    by_name = {"/".join(str(s["name"]).split("/")[-2:]): s for s in extra.streams}
    return dict(by_name[stream])


def _assert_gripper_and_wrench_recorded(extra: EpisodeExtra, mcap: Path, duration_s: float) -> None:
    """``arm0/gripper_state`` and ``arm0/wrench`` once per control tick, as ``arm0/joint_state`` (a
    loaded host ticks less often than 100 Hz; every tick still publishes all three), of their IR types."""
    ticks = _stream(extra, "arm0/joint_state")["messages"]
    assert isinstance(ticks, int)
    assert ticks > 0.3 * 100 * duration_s
    for stream in ("arm0/gripper_state", "arm0/wrench"):
        stats = _stream(extra, stream)
        assert stats["expected_hz"] == 100.0, stream
        messages = stats["messages"]
        assert isinstance(messages, int)
        assert abs(messages - ticks) <= 2, stream
    topics = [f"telerig/v1/demo/arm0/{s}" for s in ("gripper_state", "wrench")]
    samples = [entry.sample for entry in read_log(mcap, topics=topics)]
    openings = [s.opening for s in samples if isinstance(s, GripperCommand)]
    wrenches = [s for s in samples if isinstance(s, Wrench)]
    assert openings
    assert all(0.0 <= o <= 1.0 for o in openings)
    assert wrenches
    assert {w.frame_id for w in wrenches} == {"arm0/ft_sensor"}


def _assert_camera_recorded(extra: EpisodeExtra) -> None:
    """The small camera's format, and its own counters of the episode (each counted, none raised)."""
    camera = extra.cameras["scene"]
    assert (camera.width, camera.height, camera.fps, camera.codec) == (160, 120, 10.0, "h264")
    assert camera.frames > 0
    assert camera.skipped is not None
    assert camera.late is not None
    assert camera.skipped <= camera.frames  # a loaded host skips some of 10 frames a second, not most
    assert camera.callback_errors == 0


def test_the_manifest_records_the_arms_joints_limits_and_gripper_and_the_cameras_format(
    tmp_path: Path,
) -> None:
    extra, mcap = _record(tmp_path, _demo(isolated=False, camera=True), 2.0)
    # The recorder was told the episode's start: what it left out as captured before it is counted.
    assert "samples_before_start" in extra.model_fields_set
    arm = extra.robot_joints["arm0"]
    assert (arm.type, arm.model) == ("mujoco_arm", "ur5e_robotiq85")
    assert arm.joints == list(UR5E_ROBOTIQ85.joints)
    assert arm.velocity == list(UR5E_ROBOTIQ85.velocity)
    assert arm.acceleration == list(UR5E_ROBOTIQ85.acceleration)
    bounds = list(zip(arm.lower, arm.upper, strict=True))
    assert all(lo is not None and hi is not None and lo < hi for lo, hi in bounds)
    assert arm.gripper
    assert arm.standing_height_m is None  # an arm on a table does not fall
    _assert_camera_recorded(extra)
    _assert_gripper_and_wrench_recorded(extra, mcap, 2.0)


def test_a_robot_in_its_own_process_reports_its_joints_and_records_its_gripper_wrench_and_camera(
    tmp_path: Path,
) -> None:
    extra, mcap = _record(tmp_path, _demo(isolated=True, camera=True), 1.5)
    arm = extra.robot_joints["arm0"]
    assert arm.joints == list(UR5E_ROBOTIQ85.joints)
    assert arm.gripper
    _assert_camera_recorded(extra)  # the scene camera runs in the robot's process with it
    _assert_gripper_and_wrench_recorded(extra, mcap, 1.5)


def test_the_humanoid_and_the_mobile_base_record_their_standing_height() -> None:
    g1_cfg = MujocoHumanoidConfig(id="g1", type="mujoco_humanoid")
    g1 = robot_joints_record(g1_cfg, g1_cfg.build())
    assert g1.joints == list(UPPER_BODY_JOINTS)
    assert g1.standing_height_m == pytest.approx(G1_PELVIS_HEIGHT)
    assert not g1.gripper
    tiago_cfg = MujocoTiagoConfig(id="tiago", type="mujoco_tiago")
    tiago = robot_joints_record(tiago_cfg, tiago_cfg.build())
    assert tiago.standing_height_m == pytest.approx(0.098, abs=0.01)  # base_link, on the wheels
    assert tiago.lower[:3] == [None, None, None]  # the base's x, y, yaw are unbounded
    assert tiago.gripper


def test_a_harnessed_humanoid_publishes_its_pelvis_pose_every_tick() -> None:
    g1 = MujocoHumanoid(build_humanoid_scene(support="harness"), realtime=False, name="g1")
    g1.connect()
    bus = InMemoryBus()
    poses: list[Pose] = []

    def keep(message: Message) -> None:
        sample = wire.decode(message.payload)
        assert isinstance(sample, Pose)
        poses.append(sample)

    bus.subscribe(str(Topic("t", "g1", TICK)), picking({"base_pose"}, keep))
    node = ControlNode("t", g1, SafetyChain.default(g1.limits), bus, control_rate_hz=100.0)
    try:
        assert node.sensed_streams == ("base_pose",)  # no gripper, no F/T sensor
        for _ in range(10):
            g1.step(5)
            node._tick([])  # one control period without input, as the loop's idle tick
    finally:
        node.stop()
        g1.close()
    assert len(poses) == 10
    assert poses[-1].frame_id == "world"
    assert poses[-1].position[2] == pytest.approx(G1_PELVIS_HEIGHT, abs=0.02)
