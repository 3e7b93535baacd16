"""Binding a rig: each retargeter config binds its parts; misuse is one line naming the binding."""

from __future__ import annotations

import pytest

from telerig.config import load_rig
from telerig.config.schema import RigConfig
from telerig.errors import ConfigError
from telerig.runtime.rig import RigRuntime

pytestmark = [pytest.mark.sim, pytest.mark.broker]


def _demo(**changes: object) -> RigConfig:
    raw = load_rig("demo").model_dump(mode="json", exclude_none=True)
    raw["cameras"] = []
    raw.update(changes)
    return RigConfig.model_validate(raw)


def test_a_retargeter_on_the_wrong_target_names_the_valid_ones() -> None:
    raw = load_rig("demo").model_dump(mode="json", exclude_none=True)
    grip = {**raw["bindings"][1], "target": "arm"}
    with pytest.raises(
        ConfigError, match=r"vr0.right_controller → arm0.arm: .*'trigger_gripper'.* Valid: gripper"
    ):
        RigRuntime(_demo(bindings=[grip])).open()
