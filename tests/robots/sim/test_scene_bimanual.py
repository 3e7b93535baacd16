"""Tests of the bimanual station: two arms in one physics, per-arm drivers, cameras and task objects."""

from __future__ import annotations

from collections.abc import Iterator

import mujoco
import numpy as np
import pytest

from telerig.ir.types import JointCommand, Stamp
from telerig.robots.sim.bimanual import BimanualScene, BimanualStation, build_bimanual_scene

pytestmark = pytest.mark.sim


@pytest.fixture(scope="module")
def bimanual() -> BimanualScene:
    return build_bimanual_scene()


@pytest.fixture
def station(bimanual: BimanualScene) -> Iterator[BimanualStation]:
    with BimanualStation(bimanual, realtime=False) as running:
        yield running


def test_arm_names_are_prefixed_by_side(station: BimanualStation) -> None:
    assert station.left.joint_names[0] == "left_shoulder_pan_joint"
    assert station.right.joint_names[0] == "right_shoulder_pan_joint"
    assert len(station.left.joint_names) + len(station.right.joint_names) == 12
    assert station.right.scene.ee_site == "right_gripper/grip_site"


def test_grippers_face_each_other_across_the_table(station: BimanualStation) -> None:
    station.step(100)
    with station.locked() as (_, data):
        left = data.site(station.left.scene.ee_site).xpos
        right = data.site(station.right.scene.ee_site).xpos
    np.testing.assert_allclose(left[:2], -right[:2], atol=1e-3)  # mirror images through the table centre
    assert left[0] < 0 < right[0]


def test_each_arm_commands_only_its_own_joints(station: BimanualStation) -> None:
    right_before = station.right.read_state().positions
    target = station.left.scene.home + 0.2
    station.left.send(JointCommand(Stamp.now("test", 0), station.left.joint_names, target))
    station.step(500)
    np.testing.assert_allclose(station.left.read_state().positions, target, atol=5e-3)
    np.testing.assert_allclose(station.right.read_state().positions, right_before, atol=1e-3)


def test_estop_of_one_arm_leaves_the_other_running(station: BimanualStation) -> None:
    station.left.estop()
    target = station.right.scene.home - 0.2
    applied = station.right.send(JointCommand(Stamp.now("test", 0), station.right.joint_names, target))
    np.testing.assert_allclose(applied.positions, target)
    assert not station.right.estopped


def test_physics_runs_until_the_last_arm_closes(bimanual: BimanualScene) -> None:
    station = BimanualStation(bimanual, realtime=False)
    station.connect()
    station.left.close()
    station.right.step(10)  # still running for the right arm
    assert station.physics.running
    station.right.close()
    assert not station.physics.running


def test_shared_station_is_one_per_key() -> None:
    first = BimanualStation.shared("bench_a")
    assert BimanualStation.shared("bench_a") is first
    assert BimanualStation.shared("bench_b") is not first


@pytest.mark.parametrize("camera", ["scene", "left_wrist", "right_wrist"])
def test_cameras_see_the_station(station: BimanualStation, camera: str) -> None:
    with station.locked() as (model, _):
        renderer = mujoco.Renderer(model, 120, 160)
    try:
        with station.locked() as (_, data):
            renderer.update_scene(data, camera)
        image = renderer.render()
    finally:
        renderer.close()
    assert image.std() > 10


def test_reset_objects_puts_the_balls_back_in_the_cup(station: BimanualStation) -> None:
    with station.locked() as (model, data):
        ball = model.body("ball0")
        adr = model.jnt_qposadr[ball.jntadr[0]]
        data.qpos[adr : adr + 3] = [0.3, -0.3, 0.82]
    station.reset_objects()
    with station.locked() as (model, data):
        np.testing.assert_allclose(data.qpos[adr : adr + 7], model.qpos0[adr : adr + 7])


def test_a_closed_shared_station_is_replaced_not_reused() -> None:
    """A rig closes its arms; a later rig of the same station key (one still alive through a
    lingering reference) gets a new station, not arms that can never connect again."""
    station = BimanualStation.shared("closed-test", realtime=False)
    assert BimanualStation.shared("closed-test", realtime=False) is station
    station.left.close()
    assert station.closed
    again = BimanualStation.shared("closed-test", realtime=False)
    assert again is not station
    assert not again.closed
