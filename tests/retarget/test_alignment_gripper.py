"""Absolute alignment and trigger-to-gripper retargeting."""

from __future__ import annotations

import math

import numpy as np
import pytest

from telerig.config.schema import AlignmentConfig
from telerig.ir.frames import quat_from_axis_angle
from telerig.ir.types import ControllerState, HandPose, Stamp
from telerig.retarget.alignment import Alignment
from telerig.retarget.gripper import PinchGripper, TriggerGripper

IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


def _controller(trigger: float = 0.0, grip: float = 0.0) -> ControllerState:
    return ControllerState(
        Stamp("vr0", 1, 10, 10), "right", np.zeros(3), IDENTITY, "operator", trigger=trigger, grip=grip
    )


def test_identity_alignment_keeps_the_pose() -> None:
    a = Alignment.from_config(AlignmentConfig())
    p, q = a.apply(np.array([0.1, 0.2, 0.3]), IDENTITY)
    np.testing.assert_allclose(p, [0.1, 0.2, 0.3])
    np.testing.assert_allclose(q, IDENTITY)


def test_alignment_rotates_scales_and_offsets() -> None:
    yaw90 = quat_from_axis_angle(np.array([0.0, 0.0, 1.0]), math.pi / 2)
    a = Alignment(
        yaw90, operator_origin=np.array([1.0, 0.0, 0.0]), robot_origin=np.array([0.0, 0.0, 0.5]), scale=2.0
    )
    p, q = a.apply(np.array([1.1, 0.0, 0.0]), IDENTITY)
    np.testing.assert_allclose(p, [0.0, 0.2, 0.5], atol=1e-12)
    np.testing.assert_allclose(q, yaw90)


def test_alignment_rejects_non_positive_scale() -> None:
    with pytest.raises(ValueError, match="scale must be > 0"):
        Alignment(IDENTITY, np.zeros(3), np.zeros(3), scale=0.0)


@pytest.mark.parametrize(("trigger", "opening"), [(0.0, 1.0), (1.0, 0.0), (0.25, 0.75), (3.0, 0.0)])
def test_trigger_pressed_closes_the_gripper(trigger: float, opening: float) -> None:
    command = TriggerGripper()(_controller(trigger=trigger))
    assert command is not None
    assert command.opening == pytest.approx(opening)


def test_nan_trigger_gives_no_command() -> None:
    assert TriggerGripper()(_controller(trigger=float("nan"))) is None


def test_grip_source_reads_the_grip_axis() -> None:
    command = TriggerGripper("grip")(_controller(trigger=1.0, grip=0.0))
    assert command is not None
    assert command.opening == 1.0


def test_gripper_command_keeps_the_sample_stamp() -> None:
    sample = _controller(trigger=1.0)
    command = TriggerGripper()(sample)
    assert command is not None
    assert command.stamp == sample.stamp


def _hand(pinch_m: float) -> HandPose:
    keypoints = np.zeros((21, 3))
    keypoints[PinchGripper.THUMB_TIP] = [0.05, 0.0, 0.0]
    keypoints[PinchGripper.INDEX_TIP] = [0.05, pinch_m, 0.0]
    return HandPose(Stamp("g/right", 1, 1, 1), "right", np.zeros(3), IDENTITY, keypoints, np.ones(21), "g")


@pytest.mark.parametrize(
    ("pinch_m", "opening"), [(0.0, 0.0), (0.02, 0.0), (0.05, 0.5), (0.08, 1.0), (0.2, 1.0)]
)
def test_pinch_distance_maps_to_opening(pinch_m: float, opening: float) -> None:
    command = PinchGripper(0.02, 0.08)(_hand(pinch_m))
    assert command is not None
    assert command.opening == pytest.approx(opening)


def test_pinch_gripper_ignores_controllers_and_trigger_ignores_hands() -> None:
    assert PinchGripper()(_controller(trigger=1.0)) is None
    assert TriggerGripper()(_hand(0.0)) is None


def test_pinch_gripper_rejects_inverted_thresholds() -> None:
    with pytest.raises(ValueError, match="closed_at_m < open_at_m"):
        PinchGripper(0.08, 0.02)
