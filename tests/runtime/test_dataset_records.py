"""What recorded episodes carry for quality gates and exports (issue 13): each robot's joint order,
limits, gripper and standing height, and each camera's configured size, rate and codec."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from telerig.config import load_rig
from telerig.config.schema import RigConfig
from telerig.robots.models.arms import UR5E_ROBOTIQ85
from telerig.robots.models.g1 import G1_PELVIS_HEIGHT, UPPER_BODY_JOINTS
from telerig.robots.sim.config import MujocoHumanoidConfig, MujocoTiagoConfig
from telerig.runtime.rig import RigRuntime
from telerig.runtime.robot_record import robot_joints_record
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
    return RigConfig.model_validate(raw)


def _extra(tmp_path: Path, rig: RigConfig, duration_s: float) -> EpisodeExtra:
    with RigRuntime(rig, data_root=tmp_path) as runtime:
        result = runtime.run_episode(duration_s)
    assert result.status == "complete"
    return EpisodeExtra.of(EpisodeStore(tmp_path).get(result.episode_id))


def test_the_manifest_records_the_arms_joints_limits_and_gripper_and_the_cameras_format(
    tmp_path: Path,
) -> None:
    extra = _extra(tmp_path, _demo(isolated=False, camera=True), 2.0)
    arm = extra.robot_joints["arm0"]
    assert (arm.type, arm.model) == ("mujoco_arm", "ur5e_robotiq85")
    assert arm.joints == list(UR5E_ROBOTIQ85.joints)
    assert arm.velocity == list(UR5E_ROBOTIQ85.velocity)
    assert arm.acceleration == list(UR5E_ROBOTIQ85.acceleration)
    bounds = list(zip(arm.lower, arm.upper, strict=True))
    assert all(lo is not None and hi is not None and lo < hi for lo, hi in bounds)
    assert arm.gripper
    assert arm.standing_height_m is None  # an arm on a table does not fall
    camera = extra.cameras["scene"]
    assert (camera.width, camera.height, camera.fps, camera.codec) == (160, 120, 10.0, "h264")
    assert camera.frames > 5


def test_a_robot_in_its_own_process_reports_its_joints_to_the_manifest(tmp_path: Path) -> None:
    extra = _extra(tmp_path, _demo(isolated=True, camera=False), 1.5)
    arm = extra.robot_joints["arm0"]
    assert arm.joints == list(UR5E_ROBOTIQ85.joints)
    assert arm.gripper


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
