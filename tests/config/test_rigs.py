"""Rig files: every shipped rig loads and builds; bad rigs fail with one line naming the fix."""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import pytest
import yaml

from telerig.config import load_rig, parse_rig, shipped_rig_path, shipped_rigs
from telerig.config.schema import RigConfig
from telerig.errors import ConfigError


@pytest.fixture
def demo() -> dict[str, Any]:
    data = yaml.safe_load(shipped_rig_path("demo").read_text())
    assert isinstance(data, dict)
    return data


def test_demo_rig_is_shipped() -> None:
    assert "demo" in shipped_rigs()


@pytest.mark.parametrize("name", shipped_rigs())
def test_shipped_rig_loads_and_builds_devices(name: str) -> None:
    rig = load_rig(name)
    assert rig.name
    for device in rig.devices:
        built = device.build()
        assert built.id == device.id


@pytest.mark.sim
@pytest.mark.parametrize("name", shipped_rigs())
def test_shipped_rig_builds_robots(name: str) -> None:
    rig = load_rig(name)
    for robot_cfg in rig.robots:
        robot = robot_cfg.build()
        try:
            assert len(robot.joint_names) > 0
        finally:
            robot.close()


@pytest.mark.parametrize(
    ("mutate", "expected"),
    [
        (
            lambda d: d["devices"][0].update(type="glove9"),
            "devices[0].type: unknown device type 'glove9'. Valid:",
        ),
        (lambda d: d["robots"][0].update(model="ur10"), "robots[0].model: Input should be 'ur5e_robotiq85'"),
        (lambda d: d["robots"][0].update(control_rate_hz=300), "whole multiple of control_rate_hz"),
        (lambda d: d["devices"][0].update(rate_hz=-1), "devices[0].rate_hz: Input should be greater than 0"),
        (
            lambda d: d["bindings"][0].update(robot="arm9"),
            "bindings[0].robot: 'arm9' does not exist. Available: arm0",
        ),
        (lambda d: d.update(colour="red"), "colour: unknown field. Valid fields: name, broker"),
        (lambda d: d["recording"].update(bad=1), "recording.bad: unknown field. Valid fields: data_root"),
        (
            lambda d: d["bindings"][0]["retargeter"].update(type="x"),
            "bindings[0].retargeter.type: unknown retargeter type 'x'. Valid: absolute_pose",
        ),
        (
            lambda d: d["cameras"][0].update(fps=1000),
            "cameras[0].fps: Input should be less than or equal to 240",
        ),
        (lambda d: d["cameras"][0].update(robot="nope"), "cameras[0].robot: 'nope' does not exist"),
        (lambda d: d["safety"].update(hold_timeout_ms=500), "must not exceed watchdog_timeout_ms"),
    ],
)
def test_bad_rig_fails_with_one_line_naming_the_field(
    demo: dict[str, Any], mutate: Any, expected: str
) -> None:
    data = copy.deepcopy(demo)
    mutate(data)
    with pytest.raises(ConfigError) as info:
        parse_rig(data, source="rig.yaml")
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith("rig.yaml: ")
    assert expected in message


def test_missing_rig_file_names_shipped_rigs(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"not found\. Shipped rigs: .*demo"):
        load_rig(tmp_path / "nope.yaml")


def test_invalid_yaml_names_the_line(tmp_path: Path) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text("name: x\ndevices: [\n")
    with pytest.raises(ConfigError, match=r"line \d+: invalid YAML"):
        load_rig(path)


def test_external_broker_url_is_accepted(demo: dict[str, Any]) -> None:
    demo["broker"] = {"type": "external", "url": "mqtt://user:secret@broker.lab:1883"}
    rig = parse_rig(demo)
    assert rig.broker.type == "external"


@pytest.mark.parametrize("name", shipped_rigs())
def test_a_dumped_rig_loads_back_unchanged(name: str) -> None:
    # Components are polymorphic: the dump must carry each one's own fields, not just the base's.
    rig = load_rig(name)
    assert RigConfig.model_validate(rig.model_dump(mode="json")) == rig
