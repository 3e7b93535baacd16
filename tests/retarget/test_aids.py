"""Supervisory aids and controller-mode base drive: scale knob, virtual fixtures, base velocity, configs."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import pytest

from telerig.ir.types import ControllerState, Pose, Stamp
from telerig.registry import RETARGETERS
from telerig.retarget.base_drive import BaseDrive
from telerig.retarget.fixtures import FREE, Fixture, FixtureSet
from telerig.retarget.scaling import ScaleKnob

IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])
TURN = np.array([np.cos(0.2), 0.0, 0.0, np.sin(0.2)])


def _buttons(*names: str, stick: Iterable[float] = (0.0, 0.0)) -> ControllerState:
    return ControllerState(
        Stamp("pad", 0, 0, 0),
        "right",
        np.zeros(3),
        IDENTITY,
        "operator",
        buttons=frozenset(names),
        joystick=np.array(list(stick)),
    )


# --- scale knob -------------------------------------------------------------------------------------


def test_scale_steps_once_per_press_edge() -> None:
    knob = ScaleKnob(1.0, step_factor=2.0, up_button="b", down_button="a")
    assert knob.update(_buttons("b"))
    assert not knob.update(_buttons("b"))  # held, no repeat
    assert not knob.update(_buttons())
    assert knob.update(_buttons("b"))
    assert knob.scale == pytest.approx(4.0)
    assert knob.update(_buttons("a"))
    assert knob.scale == pytest.approx(2.0)
    assert knob.version == 3


def test_scale_is_clamped_to_its_range() -> None:
    knob = ScaleKnob(0.002, minimum=0.001, maximum=100.0, step_factor=10.0)
    assert knob.step(-1)
    assert knob.scale == pytest.approx(0.001)
    assert not knob.step(-1)
    assert knob.set(1e6)
    assert knob.scale == pytest.approx(100.0)
    assert not knob.set(float("nan"))


def test_scale_bus_commands() -> None:
    knob = ScaleKnob(1.0, step_factor=2.0)
    assert knob.command("up")
    assert knob.scale == pytest.approx(2.0)
    assert knob.command(" 0.005 ")
    assert knob.scale == pytest.approx(0.005)
    with pytest.raises(ValueError, match="'up', 'down' or a number"):
        knob.command("faster")
    assert knob.state() == {"scale": 0.005, "min": 0.001, "max": 100.0, "step_factor": 2.0}


# --- fixtures ---------------------------------------------------------------------------------------

MOTION = np.array([0.03, -0.04, 0.05])


def test_axis_fixture_removes_motion_across_the_axis() -> None:
    dp, dq = Fixture("diag", "axis", (1.0, 1.0, 0.0)).constrain(MOTION, TURN)
    axis = np.array([1.0, 1.0, 0.0]) / np.sqrt(2)
    np.testing.assert_allclose(dp, (MOTION @ axis) * axis, atol=1e-15)
    np.testing.assert_allclose(np.cross(dp, axis), 0.0, atol=1e-15)
    np.testing.assert_array_equal(dq, TURN)


def test_plane_fixture_removes_motion_along_the_normal() -> None:
    dp, _ = Fixture("table", "plane", (0.0, 0.0, 2.0)).constrain(MOTION, TURN)
    np.testing.assert_allclose(dp, [0.03, -0.04, 0.0], atol=1e-15)


def test_orientation_fixture_removes_rotation_only() -> None:
    dp, dq = Fixture("level", "orientation").constrain(MOTION, TURN)
    np.testing.assert_array_equal(dp, MOTION)
    np.testing.assert_array_equal(dq, IDENTITY)


def test_free_fixture_changes_nothing() -> None:
    dp, dq = FREE.constrain(MOTION, TURN)
    np.testing.assert_array_equal(dp, MOTION)
    np.testing.assert_array_equal(dq, TURN)


def test_fixture_set_cycles_on_press_and_selects_by_command() -> None:
    fixtures = FixtureSet(
        [FREE, Fixture("x", "axis", (1.0, 0.0, 0.0)), Fixture("level", "orientation")],
        cycle_button="thumbstick",
    )
    assert fixtures.update(_buttons("thumbstick"))
    assert not fixtures.update(_buttons("thumbstick"))
    assert fixtures.active.name == "x"
    assert fixtures.command("level")
    assert fixtures.active.name == "level"
    assert fixtures.command("next")
    assert fixtures.active.name == "free"
    with pytest.raises(ValueError, match="Available: free, x, level"):
        fixtures.command("sideways")
    fixtures.select("x")
    assert fixtures.state() == {
        "name": "x",
        "kind": "axis",
        "axis": [1.0, 0.0, 0.0],
        "keep_orientation": False,
        "frame": "base",
        "options": ["free", "x", "level"],
    }


# --- base drive -------------------------------------------------------------------------------------


def _drive() -> BaseDrive:
    return BaseDrive(
        forward_button="b", backward_button="a", max_linear_m_s=0.4, max_angular_rad_s=1.0, deadzone=0.2
    )


@pytest.mark.parametrize(("held", "vx"), [(("b",), 0.4), (("a",), -0.4), (("a", "b"), 0.0), ((), 0.0)])
def test_buttons_drive_forward_and_backward_at_the_limited_speed(held: tuple[str, ...], vx: float) -> None:
    command = _drive()(_buttons(*held))
    assert command is not None
    assert (command.vx, command.vy, command.wz) == (vx, 0.0, 0.0)


@pytest.mark.parametrize(("stick_x", "wz"), [(1.0, -1.0), (-1.0, 1.0), (0.6, -0.5), (0.15, 0.0)])
def test_thumbstick_x_turns_with_a_dead_zone(stick_x: float, wz: float) -> None:
    command = _drive()(_buttons(stick=(stick_x, 0.9)))
    assert command is not None
    assert command.wz == pytest.approx(wz)
    assert command.vx == 0.0


def test_base_drive_ignores_samples_without_buttons() -> None:
    assert _drive()(Pose(Stamp("m", 0, 0, 0), np.zeros(3), IDENTITY, "operator")) is None


def test_base_drive_stop_is_zero_and_expiry_follows_the_timeout() -> None:
    drive = BaseDrive(forward_button="b", backward_button="a", input_timeout_s=0.25)
    stop = drive.stop(123)
    assert (stop.vx, stop.vy, stop.wz) == (0.0, 0.0, 0.0)
    assert stop.stamp.capture_ns == 123
    assert not drive.expired(0, 250_000_000)
    assert drive.expired(0, 250_000_001)


# --- configs: one-line errors -----------------------------------------------------------------------


@pytest.mark.parametrize(
    ("raw", "message"),
    [
        ({"type": "arm_pose", "mode": "relative"}, "mode 'relative' needs clutch_button"),
        ({"type": "arm_pose", "clutch_button": "grip"}, "clutch_button needs mode: relative"),
        ({"type": "arm_pose", "scale": {}}, "scale applies to relative motion"),
        (
            {"type": "arm_pose", "mode": "relative", "clutch_button": "a", "scale": {"initial": 500}},
            "need min <= initial <= max",
        ),
        (
            {"type": "arm_pose", "fixtures": {"options": [{"name": "x", "kind": "axis"}]}},
            "kind 'axis' needs a non-zero axis",
        ),
        (
            {
                "type": "arm_pose",
                "fixtures": {"options": [{"name": "f", "kind": "free"}, {"name": "f", "kind": "free"}]},
            },
            "fixture names must be unique",
        ),
        ({"type": "base_drive", "forward_button": "a"}, "forward_button and backward_button must differ"),
        ({"type": "base_drive", "max_linear_m_s": 0}, "max_linear_m_s"),
    ],
)
def test_config_errors_are_one_line(raw: dict[str, object], message: str) -> None:
    with pytest.raises(ValueError, match=message) as info:
        RETARGETERS.parse_config(raw, "retargeter")
    assert "\n" not in str(info.value)


def test_absolute_pose_config_converts_to_arm_pose() -> None:
    cfg = RETARGETERS.parse_config({"type": "absolute_pose", "ik_substeps": 2}, "retargeter")
    arm = cfg.as_arm_pose()
    assert (arm.type, arm.mode, arm.ik_substeps, arm.filter) == ("arm_pose", "absolute", 2, None)


def test_fixture_command_selects_by_kind() -> None:
    from telerig.retarget.fixtures import Fixture, FixtureSet

    fixtures = FixtureSet(
        [Fixture("free", "free"), Fixture("table", "plane", (0, 0, 1)), Fixture("o", "orientation")]
    )
    assert fixtures.command("kind:orientation")
    assert fixtures.active.name == "o"
    assert fixtures.command("kind:plane")
    assert fixtures.active.name == "table"
    with pytest.raises(
        ValueError, match=r"no fixture of kind 'axis'. Available: free \(free\), table \(plane\)"
    ):
        fixtures.command("kind:axis")
