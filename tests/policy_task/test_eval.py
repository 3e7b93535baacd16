"""`telerig eval`: the task rig with a policy bound in place of the scripted operator, rolled out on
held-out seeds through the real embedded broker, success judged from the scene."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from telerig.cli.main import main
from telerig.cli.task import policy_rig
from telerig.config import load_rig, parse_rig, shipped_rig_path
from telerig.errors import ConfigError
from telerig.runtime.task import EVAL_SEED_BASE

UR5E = (
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
)
SPEC = {"camera_keys": ["observation.images.scene"], "image_size": [24, 32], "fps": 10.0}


def test_policy_replaces_the_operator_on_the_task_robot() -> None:
    rig = policy_rig(load_rig("pick_place"), Path("/ckpt/policy.pt"), SPEC)
    assert [(d.id, d.type) for d in rig.devices] == [("policy", "policy")]
    assert {(b.device, b.part, b.target, b.retargeter.type) for b in rig.bindings} == {
        ("policy", "joints", "arm", "joint_passthrough"),
        ("policy", "joints", "gripper", "joint_gripper"),
    }
    camera = rig.cameras[0]
    observation = camera.observation
    assert observation is not None
    assert (observation.width, observation.height, observation.rate_hz) == (32, 24, 10.0)
    assert [getattr(r, "type", None) for r in rig.robots] == ["mujoco_pick_place"]
    # A rig that already binds a policy keeps its wiring and gets the checkpoint.
    again = policy_rig(rig, Path("/ckpt/other.pt"), SPEC)
    assert str(again.devices[0].checkpoint) == "/ckpt/other.pt"  # type: ignore[attr-defined]
    assert again.bindings == rig.bindings
    # telerig eval --execute-actions: the policy sends that many actions of each chunk.
    assert rig.devices[0].execute_actions == 1  # type: ignore[attr-defined]
    chunked = policy_rig(load_rig("pick_place"), Path("/ckpt/policy.pt"), SPEC, execute_actions=8)
    assert chunked.devices[0].execute_actions == 8  # type: ignore[attr-defined]
    assert policy_rig(rig, Path("/ckpt/p.pt"), SPEC, execute_actions=4).devices[0].execute_actions == 4  # type: ignore[attr-defined]


def test_policy_rig_errors_are_one_line() -> None:
    with pytest.raises(ConfigError, match="has no camera in rig") as info:
        policy_rig(load_rig("pick_place"), Path("x.pt"), {**SPEC, "camera_keys": ["observation.images.top"]})
    assert len(str(info.value).splitlines()) == 1
    with pytest.raises(ConfigError, match="no task robot"):
        policy_rig(load_rig("demo"), Path("x.pt"), SPEC)


@pytest.mark.parametrize("n", ["0", "-3"])
def test_execute_actions_below_one_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], n: str
) -> None:
    ckpt = tmp_path / "p.pt"
    ckpt.write_bytes(b"not read: the argument is checked first")
    assert main(["eval", "pick_place", "--policy", str(ckpt), "--execute-actions", n]) == 2
    err = capsys.readouterr().err.strip()
    assert err.splitlines() == [err]
    assert "--execute-actions must be >= 1" in err
    assert f"got {n}" in err


def _checkpoint(path: Path) -> Path:
    """A real, untrained bc checkpoint of the UR5e + gripper with the scene camera (child process:
    torch stays out of the test's control process)."""
    code = (
        "import sys; from telerig.policy.checkpoint import tiny_for_tests; "
        f"tiny_for_tests(sys.argv[1], state_names={(*UR5E, 'gripper')!r}, camera_keys=('scene',), "
        "image_size=(24, 32), fps=10.0)"
    )
    subprocess.run([sys.executable, "-c", code, str(path)], check=True, timeout=180)
    return path


@pytest.mark.slow
@pytest.mark.broker
@pytest.mark.sim
def test_eval_rolls_a_checkpoint_out_on_held_out_seeds(tmp_path: Path) -> None:
    data = yaml.safe_load(shipped_rig_path("pick_place").read_text())
    data["cameras"][0].update({"width": 160, "height": 120, "fps": 10, "preview": {"enabled": False}})
    ckpt = _checkpoint(tmp_path / "tiny.pt")
    # The rig with the policy already bound (as policy_rig binds it): eval only swaps the checkpoint,
    # so the test spares a third torch start for reading the checkpoint's spec.
    bound = policy_rig(parse_rig(data), tmp_path / "placeholder.pt", SPEC)
    rig = tmp_path / "pick_place_policy.yaml"
    rig.write_text(yaml.safe_dump(bound.model_dump(mode="json")))
    out = tmp_path / "eval.json"
    args = [
        "eval",
        str(rig),
        "--policy",
        str(ckpt),
        "--episodes",
        "1",
        "--duration",
        "3",
        "--gates-wait",
        "0",
    ]
    code = main([*args, "--data-root", str(tmp_path / "data"), "--json", str(out)])
    assert code == 0
    result = json.loads(out.read_text())
    assert result["seed"] == EVAL_SEED_BASE
    (run,) = result["runs"].values()
    (episode,) = run["episodes"]
    assert episode["seed"] == EVAL_SEED_BASE
    assert episode["success"] is False  # an untrained policy, 3 s: judged from the scene
    assert run["summary"]["episodes"] == 1
    assert run["summary"]["wilson95"][0] == 0.0
    manifest = json.loads(
        next((tmp_path / "data").rglob(f"{episode['episode_id']}/manifest.json")).read_text()
    )
    assert manifest["extra"]["task"]["seed"] == EVAL_SEED_BASE
    assert manifest["extra"]["outcome"] == "failure"


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--temporal-ensemble", "0"], "--temporal-ensemble must be a weight decay in"),
        (["--temporal-ensemble", "nan"], "--temporal-ensemble must be a weight decay in"),
        (["--temporal-ensemble", "0.01", "--execute-actions", "8"], "leave out --execute-actions"),
    ],
)
def test_temporal_ensemble_errors_are_one_line(
    extra: list[str], message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    ckpt = tmp_path / "p.pt"
    ckpt.write_bytes(b"x")
    code = main(["eval", "pick_place", "--policy", str(ckpt), "--episodes", "1", *extra])
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert message in err
    assert len(err.splitlines()) == 1


def test_temporal_ensemble_makes_the_policy_ask_every_tick() -> None:
    rig = policy_rig(load_rig("pick_place"), Path("/ckpt/p.pt"), SPEC, temporal_ensemble=0.01)
    (device,) = rig.devices
    assert (device.temporal_ensemble, device.execute_actions) == (0.01, 1)  # type: ignore[attr-defined]
    with pytest.raises(ConfigError, match="temporal_ensemble infers every tick"):
        policy_rig(rig, Path("/ckpt/p.pt"), SPEC, execute_actions=8)
