"""The public names of telerig.robots.ur are pinned."""

from __future__ import annotations

from telerig.robots import ur

PUBLIC = {
    "ROBOTIQ_PORT", "UR_JOINT_NAMES", "UR_MODELS", "ClockMapper", "FakeURController", "RobotiqSocket",
    "ServoProgram", "URRobot", "URStats", "URStatus", "stop_program", "ur_limits",
}  # fmt: skip


def test_public_names_are_pinned_and_resolve() -> None:
    assert set(ur.__all__) == PUBLIC
    for name in ur.__all__:
        assert getattr(ur, name) is not None
