"""``hand_vector`` bound to a hand robot: target and joint checks, command order, stamps, residuals, holds."""

from __future__ import annotations

import numpy as np
import pytest

from telerig.devices.glove.kinematics import HandModel
from telerig.errors import ConfigError
from telerig.ir.types import ControllerState, HandPose, Pose, Stamp
from telerig.retarget.binding import BindContext
from telerig.retarget.hand.config import HandVectorConfig
from telerig.retarget.hand.joints import HandJointsRetargeter
from telerig.robots.sim.hand import MujocoHand, build_hand_scene

pytestmark = pytest.mark.sim

_ROBOTS: dict[str, MujocoHand] = {}


def _robot(model: str = "inspire") -> MujocoHand:
    if model not in _ROBOTS:  # never connected: binding only reads names
        _ROBOTS[model] = MujocoHand(build_hand_scene(model, with_objects=False), realtime=False)  # type: ignore[arg-type]
    return _ROBOTS[model]


def _context(robot: MujocoHand, target: str = "hand") -> BindContext:
    return BindContext("rig", "hand0", robot, target, "glove", "right_hand", ("glove",))


def _pose(closing: float, *, hand: str = "right", conf: float = 0.95, seq: int = 7) -> HandPose:
    angles = closing * np.array([[-0.2, 0.6, 0.7, 0.5]] + [[0.0, 1.5, 1.7, 0.9]] * 4)
    kp = HandModel.default().keypoints(angles, hand)  # type: ignore[arg-type]
    return HandPose(
        Stamp("glove/right", seq, 1000 + seq, 2000 + seq),
        hand,  # type: ignore[arg-type]
        kp[0],
        np.array([1.0, 0.0, 0.0, 0.0]),
        kp,
        np.full(21, conf),
        "right_glove",
    )


def _bound(**fields: object) -> HandJointsRetargeter:
    bound = HandVectorConfig(**fields).bind(_context(_robot()))  # type: ignore[arg-type]
    assert bound.gripper is None
    assert bound.base is None
    assert isinstance(bound.joints, HandJointsRetargeter)
    return bound.joints


def test_bind_drives_the_robot_joints_in_driver_order_stamped_with_the_sample() -> None:
    retargeter = _bound()
    robot = _robot()
    assert retargeter.accepts == (HandPose,)
    sample = _pose(0.8)
    command, residual = retargeter(sample, np.zeros(6), 0.01)
    assert command is not None
    assert residual is not None
    assert command.names == robot.joint_names
    assert command.stamp == sample.stamp
    index = robot.joint_names.index("joint_r_index_proximal")
    assert command.positions[index] > 0.8  # a closing hand bends the index
    assert np.all(command.positions >= robot.limits.lower - 1e-12)
    assert np.all(command.positions <= robot.limits.upper + 1e-12)


def test_residual_reports_the_mean_vector_error_and_the_valid_vectors() -> None:
    _, residual = _bound()(_pose(0.5), np.zeros(6), 0.01)
    assert residual is not None
    metrics = residual.metrics()
    assert set(metrics) == {"vector_error_m", "vector_error_max_m", "vectors_valid", "solve_s"}
    assert 0.0 <= metrics["vector_error_m"] <= metrics["vector_error_max_m"] < 0.05
    assert metrics["vectors_valid"] == 6.0  # wrist to five tips and to the thumb knuckle
    assert not residual.flagged
    tight = _bound(residual_threshold_m=1e-6)(_pose(0.5), np.zeros(6), 0.01)[1]
    assert tight is not None
    assert tight.flagged


@pytest.mark.parametrize(
    "sample",
    [
        _pose(0.5, hand="left"),
        _pose(0.5, conf=0.1),
    ],
    ids=["other_hand", "low_confidence"],
)
def test_unusable_samples_send_nothing_so_the_safety_chain_holds(sample: HandPose) -> None:
    assert _bound()(sample, np.zeros(6), 0.01) == (None, None)


def test_reset_restarts_from_the_open_hand() -> None:
    retargeter = _bound()
    retargeter(_pose(1.0), np.zeros(6), 0.01)
    retargeter.reset()
    np.testing.assert_allclose(retargeter.retargeter.q, retargeter.retargeter.hand.neutral())


def test_only_hand_samples_are_accepted() -> None:
    accepted = _bound().accepts
    assert not issubclass(ControllerState, accepted)
    assert not issubclass(Pose, accepted)


def test_wrong_target_is_a_one_line_error() -> None:
    with pytest.raises(ConfigError, match=r"cannot drive target 'arm'\. Valid: hand") as info:
        HandVectorConfig().bind(_context(_robot(), target="arm"))
    assert "\n" not in str(info.value)


@pytest.mark.parametrize(
    ("fields", "expected"),
    [
        ({"hand": "ability"}, "missing thumb_q1"),
        ({"command": "all"}, "missing joint_r_thumb_middle"),
        ({"handedness": "left"}, "unexpected joint_r_thumb_proximal_1"),
    ],
)
def test_robot_of_another_hand_model_is_a_one_line_error_naming_the_mismatch(
    fields: dict[str, object], expected: str
) -> None:
    with pytest.raises(ConfigError) as info:
        HandVectorConfig(**fields).bind(_context(_robot()))  # type: ignore[arg-type]
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith("binding glove.right_hand → hand0.hand: robot 'hand0': ")
    assert expected in message


def test_ability_robot_binds_its_own_six_motors() -> None:
    bound = HandVectorConfig(hand="ability").bind(_context(_robot("ability")))
    assert isinstance(bound.joints, HandJointsRetargeter)
    assert bound.joints.joint_names == _robot("ability").joint_names
    assert len(bound.joints.joint_names) == 6
