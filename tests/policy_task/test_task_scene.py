"""The randomized pick-and-place scene: seeded draws, the success check on constructed states, the
stepped scene placing the cube and publishing object poses, and one-line errors for bad task config."""

from __future__ import annotations

import math

import numpy as np
import pytest

from telerig.config import parse_rig
from telerig.errors import ConfigError
from telerig.robots.base import EpisodicTask, ObjectSensor
from telerig.robots.sim.config import MujocoPickPlaceConfig
from telerig.robots.sim.pick_place import (
    CUBE_HALF,
    PickPlaceSpec,
    SceneState,
    draw_cube,
    judge,
)
from telerig.robots.sim.scene import TABLE_TOP
from telerig.runtime.task import (
    EVAL_SEED_BASE,
    check_seed_range,
    with_task_seed,
)

SPEC = PickPlaceSpec()
REST = TABLE_TOP + CUBE_HALF
IN_ZONE = np.array([SPEC.target[0] + 0.01, SPEC.target[1] - 0.02, REST])


def test_same_seed_same_cube_pose_and_seeds_differ() -> None:
    first = [draw_cube(SPEC, s) for s in range(40)]
    again = [draw_cube(SPEC, s) for s in range(40)]
    assert first == again
    assert len({(d.x, d.y, d.yaw) for d in first}) == 40
    for d in first:
        assert SPEC.cube_x[0] <= d.x <= SPEC.cube_x[1]
        assert SPEC.cube_y[0] <= d.y <= SPEC.cube_y[1]
        assert abs(d.yaw) <= SPEC.cube_yaw
        # Never starts solved or on the zone's border.
        gap = np.abs(np.array([d.x, d.y]) - np.array(SPEC.target)) - SPEC.target_half
        assert gap.max() >= SPEC.clearance


def test_draw_is_pinned_to_the_seed() -> None:
    # PCG64 from the seed alone: a change of the draw would change every recorded dataset's scenes.
    d = draw_cube(SPEC, 0)
    assert (round(d.x, 6), round(d.y, 6), round(d.yaw, 6)) == (0.529175, 0.083166, -0.367221)


def _state(cube: np.ndarray = IN_ZONE, opening: float = 1.0, speed: float = 0.0) -> SceneState:
    return SceneState(np.asarray(cube, float), opening, np.full(6, speed))


def test_success_on_a_constructed_solved_scene() -> None:
    check = judge(SPEC, _state())
    assert check.success
    assert check.reason == "ok"
    assert check.values["cube_offset_m"] == 0.0


@pytest.mark.parametrize(
    ("state", "reason"),
    [
        (_state(cube=np.array([0.52, 0.10, REST])), "outside the target zone"),
        # Just past the zone's edge in y.
        (_state(cube=np.array([SPEC.target[0], SPEC.target[1] + SPEC.target_half + 0.002, REST])), "outside"),
        (_state(opening=0.45), "gripper not open"),
        (_state(speed=0.2), "arm moving"),
        (_state(cube=IN_ZONE + np.array([0.0, 0.0, 0.05])), "above the table"),
        (_state(cube=np.array([math.nan, 0.0, REST])), "not finite"),
        (_state(speed=math.nan), "arm moving"),
        (_state(opening=math.nan), "gripper not open"),
    ],
)
def test_failure_names_the_condition(state: SceneState, reason: str) -> None:
    check = judge(SPEC, state)
    assert not check.success
    assert reason in check.reason


def test_stepped_scene_places_the_drawn_cube_and_publishes_poses() -> None:
    robot = MujocoPickPlaceConfig(id="arm0", realtime=False, seed=7).build()
    assert isinstance(robot, ObjectSensor)
    assert isinstance(robot, EpisodicTask)
    robot.connect()
    try:
        record = robot.begin_task(robot.task_seed + 2)
        robot.step(100)
        draw = draw_cube(robot.spec, 9)
        assert record["seed"] == 9
        cube = robot.read_object_pose("cube")
        target = robot.read_object_pose("target")
        assert cube.stamp.source_id == "arm0/cube"
        assert cube.frame_id == "world"
        assert np.allclose(cube.position, draw.position, atol=2e-3)
        assert np.allclose(cube.orientation, draw.orientation, atol=1e-3)
        assert np.allclose(target.position[:2], robot.spec.target)
        assert robot.observed_objects == ("cube", "target")
        check = robot.check_task()
        assert not check.success
        assert "outside the target zone" in check.reason
        # A new episode's draw replaces the cube; the scene state reads no stream sequence.
        robot.begin_task(10)
        assert np.allclose(robot.scene_state().cube_position, draw_cube(robot.spec, 10).position)
        assert robot.read_object_pose("cube").stamp.seq == 1
        with pytest.raises(Exception, match="no object 'ball'"):
            robot.read_object_pose("ball")
    finally:
        robot.close()


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"cube_x": [0.41, 0.51], "cube_y": [-0.2, -0.1]}, "lies inside the target zone"),
        ({"seed": -1}, "seed"),
        ({"cube_yaw_rad": 2.0}, "cube_yaw_rad"),
        ({"cube_x": [0.6, 0.5]}, "cube_x must be a finite range"),
        ({"target": "left"}, "target"),
        ({"target_half_m": 0}, "target_half_m"),
        ({"bogus": 1}, "bogus"),
    ],
)
def test_bad_task_config_is_one_line(change: dict[str, object], message: str) -> None:
    import yaml

    from telerig.config import shipped_rig_path

    data = yaml.safe_load(shipped_rig_path("pick_place").read_text())
    data["robots"][0].update(change)
    with pytest.raises(ConfigError) as info:
        parse_rig(data)
    text = str(info.value)
    assert message in text
    assert len(text.strip().splitlines()) == 1


def test_seed_ranges_of_collect_and_eval_are_disjoint() -> None:
    check_seed_range(0, 50, held_out=False)
    check_seed_range(EVAL_SEED_BASE, 50, held_out=True)
    with pytest.raises(ConfigError, match="held out"):
        check_seed_range(EVAL_SEED_BASE - 10, 50, held_out=False)
    with pytest.raises(ConfigError, match="evaluation seeds are held out"):
        check_seed_range(5, 50, held_out=True)
    with pytest.raises(ConfigError):
        check_seed_range(-3, 2, held_out=False)


def test_with_task_seed_sets_robot_and_operator_and_refuses_a_rig_without_task() -> None:
    from telerig.config import load_rig

    rig = with_task_seed(load_rig("pick_place"), 123)
    assert [getattr(r, "seed", None) for r in rig.robots] == [123]
    assert [getattr(d, "seed", None) for d in rig.devices] == [123]
    with pytest.raises(ConfigError, match="no task with a seed"):
        with_task_seed(load_rig("demo"), 1)
