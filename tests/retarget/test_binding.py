"""Binding a rig: each retargeter config binds its parts; misuse is one line naming the binding."""

from __future__ import annotations

from typing import cast

import pytest

from telerig.config import load_rig, parse_rig
from telerig.config.schema import RigConfig
from telerig.errors import ConfigError
from telerig.retarget.binding import BindContext
from telerig.retarget.config import AbsolutePoseConfig
from telerig.robots.base import RobotDriver

pytestmark = [pytest.mark.sim, pytest.mark.broker]


def _demo(**changes: object) -> RigConfig:
    raw = load_rig("demo").model_dump(mode="json", exclude_none=True)
    raw["cameras"] = []
    raw.update(changes)
    return RigConfig.model_validate(raw)


def test_a_retargeter_on_the_wrong_target_names_the_valid_ones() -> None:
    # Refused when the rig loads (telerig rig check), not first when the runtime binds it.
    raw = load_rig("demo").model_dump(mode="json", exclude_none=True)
    raw["bindings"] = [{**raw["bindings"][1], "target": "arm"}]
    with pytest.raises(
        ConfigError,
        match=r"bindings\[0\]\.target: retargeter 'trigger_gripper' cannot drive target 'arm'\. "
        r"Valid: gripper",
    ):
        parse_rig(raw)


def test_binding_a_wrong_target_names_the_retargeter_of_the_rig_file() -> None:
    # absolute_pose binds through arm_pose: the error still names the retargeter the file names.
    context = BindContext(
        "r", "arm0", cast(RobotDriver, None), "tentacle", "vr0", "right_controller", ("vr0",)
    )
    with pytest.raises(ConfigError, match=r"retargeter 'absolute_pose' cannot drive target 'tentacle'"):
        AbsolutePoseConfig().bind(context)
