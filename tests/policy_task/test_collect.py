"""`telerig collect` through the real embedded broker (Mosquitto): 2 short episodes of the task rig
record the seed, the drawn cube pose, the cube on <robot>/object_pose and the outcome judged from the
scene; bad seeds, rigs and checkpoints get one line."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from telerig.cli.main import main
from telerig.config import load_rig, shipped_rig_path
from telerig.ir.mcap_log import read_log
from telerig.ir.types import Pose
from telerig.robots.sim.pick_place import draw_cube


def _rig(tmp_path: Path) -> Path:
    """The shipped task rig without its camera (rendering is the slow part; the task needs none)."""
    data = yaml.safe_load(shipped_rig_path("pick_place").read_text())
    data["cameras"] = []
    path = tmp_path / "pick_place.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.slow
@pytest.mark.broker
@pytest.mark.sim
def test_collect_two_episodes_records_seed_pose_and_outcome(tmp_path: Path) -> None:
    root = tmp_path / "data"
    out = tmp_path / "collect.json"
    rig = _rig(tmp_path)
    args = ["collect", str(rig), "--episodes", "2", "--duration", "2.5", "--seed", "5", "--gates-wait", "0"]
    code = main([*args, "--data-root", str(root), "--json", str(out)])
    assert code == 0
    result = json.loads(out.read_text())
    assert [e["seed"] for e in result["episodes"]] == [5, 6]
    assert result["summary"]["episodes"] == 2
    spec = load_rig(str(rig)).robots[0].spec()  # type: ignore[attr-defined]
    for entry in result["episodes"]:
        manifest_path = next(root.rglob(f"{entry['episode_id']}/manifest.json"))
        manifest = json.loads(manifest_path.read_text())
        extra = manifest["extra"]
        task = extra["task"]
        draw = draw_cube(spec, task["seed"])
        assert task["robot"] == "arm0"
        assert np.allclose(task["cube"]["position_m"], draw.position, atol=1e-6)
        assert task["cube"]["yaw_rad"] == pytest.approx(draw.yaw, abs=1e-6)
        # 2.5 s is far too short to solve it: judged from the scene, never assumed.
        assert task["success"] is False
        assert extra["outcome"] == "failure"
        assert "outside the target zone" in task["reason"]
        assert task["checks"] > 10
        # The cube is observable in the recording at the drawn pose.
        cubes = [
            e.sample
            for e in read_log(
                manifest_path.parent / "episode.mcap", topics=["telerig/v1/pick_place/arm0/object_pose"]
            )
            if e.sample.stamp.source_id == "arm0/cube"
        ]
        assert len(cubes) > 50
        assert isinstance(cubes[0], Pose)
        assert np.allclose(cubes[0].position, draw.position, atol=3e-3)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["collect", "RIG", "--seed", "999999", "--episodes", "2"], "held out for `telerig eval`"),
        (["collect", "RIG", "--seed", "-4", "--episodes", "2"], "demonstrations use"),
        (["collect", "RIG", "--episodes", "0"], "--episodes must be >= 1"),
        (["collect", "demo", "--episodes", "1"], "has no task with a seed"),
        (["eval", "RIG", "--policy", "missing.pt", "--seed", "3"], "evaluation seeds are held out"),
        (["eval", "RIG", "--policy", "missing.pt"], "no such checkpoint file"),
        (["collect", "no-such-rig"], "no-such-rig"),
    ],
)
def test_bad_arguments_get_one_line(
    args: list[str], message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rig = str(_rig(tmp_path))
    code = main([rig if a == "RIG" else a for a in args] + ["--data-root", str(tmp_path / "d")])
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert message in " ".join(err.split())
    assert not (tmp_path / "d").exists()
