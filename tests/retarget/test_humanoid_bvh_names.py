"""The humanoid retargeter drives a robot from BVH files of either arm naming and either unit system
(issue 11, finding 11): the player finds the arms by structure and the scale by proportions."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from telerig.devices.mocap import BvhPlayer
from telerig.devices.mocap.bvh import CMU_UNIT_M
from telerig.retarget.humanoid import KEYPOINTS, HumanoidRetargeter, KeypointMap
from telerig.robots.models.g1 import build_humanoid_kinematics

pytestmark = pytest.mark.sim

_spec = importlib.util.spec_from_file_location(
    "bvh_bodies", Path(__file__).resolve().parents[1] / "devices" / "mocap" / "test_bvh_structure.py"
)
assert _spec is not None
assert _spec.loader is not None
bodies = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bodies)


@pytest.mark.parametrize("unit", [CMU_UNIT_M, 0.01])
@pytest.mark.parametrize("body", ["cmu_names", "anatomical_names"])
def test_either_naming_in_either_unit_gives_the_same_keypoints(
    body: str, unit: float, tmp_path: Path
) -> None:
    path = tmp_path / "body.bvh"
    path.write_text(bodies.bvh_text(bodies.BODIES[body](), unit))
    frame = BvhPlayer(path).frames()[0]
    keypoints = KeypointMap()(frame)
    file_names = list(BvhPlayer(path, normalize_names=False).frames()[0].joint_names)
    for k, keypoint in enumerate(KEYPOINTS):
        row = file_names.index(bodies.EXPECTED[body][keypoint])
        np.testing.assert_allclose(keypoints[k], frame.positions[row])
    # Metres, both ways: the shoulder line is 2 x (collar 0.17 m) wide and the arm 0.54 m long.
    right, left = keypoints[0], keypoints[3]
    assert float(np.linalg.norm(left - right)) == pytest.approx(0.34, abs=1e-3)
    assert float(
        np.linalg.norm(keypoints[2] - keypoints[1]) + np.linalg.norm(keypoints[1] - keypoints[0])
    ) == (pytest.approx(0.54, abs=1e-3))


@pytest.mark.parametrize("body", ["cmu_names", "anatomical_names"])
def test_the_retargeter_solves_a_frame_of_either_naming(body: str, tmp_path: Path) -> None:
    from telerig.retarget.humanoid import HumanoidIK

    path = tmp_path / "body.bvh"
    path.write_text(bodies.bvh_text(bodies.BODIES[body](), CMU_UNIT_M))
    frame = BvhPlayer(path).frames()[0]
    ik = HumanoidIK(build_humanoid_kinematics())
    command, result = HumanoidRetargeter(ik)(frame, np.array(ik.home), 0.01)
    assert command is not None
    assert result is not None
    assert np.all(np.isfinite(command.positions))
