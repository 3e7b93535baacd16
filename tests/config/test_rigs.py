"""Rig files: every shipped rig loads and builds; bad rigs fail with one line naming the fix."""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import pytest
import yaml

from telerig.cameras.capture import Camera
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


@pytest.mark.sim
@pytest.mark.parametrize("name", shipped_rigs())
def test_shipped_rig_builds_cameras_from_their_configs(name: str) -> None:
    rig = load_rig(name)
    robots = {robot_cfg.id: robot_cfg.build() for robot_cfg in rig.robots}
    try:
        for camera_cfg in rig.cameras:
            camera = camera_cfg.build(lambda image, frame: True, robots=robots)  # no I/O until start()
            assert isinstance(camera, Camera)
            assert camera.name == camera_cfg.id
    finally:
        for robot in robots.values():
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


# --- rig files that are not YAML text, and bindings the registry cannot drive (issue 11, finding 9) ---


def _one_line(info: pytest.ExceptionInfo[ConfigError]) -> str:
    message = str(info.value)
    assert "\n" not in message
    return message


def test_a_non_utf8_rig_file_names_the_line_and_the_fix(tmp_path: Path) -> None:
    path = tmp_path / "latin1.yaml"
    path.write_bytes("name: demo\n# caf\u00e9\n".encode("latin-1"))
    with pytest.raises(ConfigError) as info:
        load_rig(path)
    message = _one_line(info)
    assert message.startswith(f"{path}: line 2: not UTF-8 text (byte 0xe9)")
    assert "save the file as UTF-8" in message


def test_a_directory_given_as_rig_file_is_a_one_line_error(tmp_path: Path) -> None:
    folder = tmp_path / "rigs.yaml"
    folder.mkdir()
    with pytest.raises(ConfigError) as info:
        load_rig(folder)
    assert _one_line(info) == f"{folder}: is a directory; give the path of a rig file (.yaml) inside it"


def test_a_nul_byte_names_its_line(tmp_path: Path) -> None:
    path = tmp_path / "nul.yaml"
    path.write_bytes(b"name: demo\ndevices: []\nrobots: [\x00]\n")
    with pytest.raises(ConfigError) as info:
        load_rig(path)
    message = _one_line(info)
    assert message.startswith(f"{path}: line 3: invalid YAML: ")
    assert "#x0000" in message


@pytest.mark.parametrize(
    ("index", "target", "retargeter", "valid"),
    [
        (0, "tentacle", "absolute_pose", "arm"),
        (1, "arm", "trigger_gripper", "gripper"),
    ],
)
def test_a_binding_target_its_retargeter_cannot_drive_fails_the_check(
    demo: dict[str, Any], index: int, target: str, retargeter: str, valid: str
) -> None:
    demo["bindings"][index]["target"] = target
    if index == 1:  # two bindings may not drive one robot part; move the other one away
        demo["bindings"].pop(0)
        index = 0
    with pytest.raises(ConfigError) as info:
        parse_rig(demo, source="rig.yaml")
    message = _one_line(info)
    assert message.startswith(
        f"rig.yaml: bindings[{index}].target: retargeter {retargeter!r} cannot drive target {target!r}. "
        f"Valid: {valid}"
    )
    # ... and it names the retargeters that do drive a target, so the fix is one look away.
    assert "absolute_pose, arm_pose" in message
    assert "gripper: joint_gripper, pinch_gripper, trigger_gripper" in message


def test_every_registered_retargeter_declares_its_targets() -> None:
    from telerig.registry import RETARGETERS

    for name in RETARGETERS.names():
        assert RETARGETERS.get(name).targets, f"retargeter {name!r} declares no targets"
