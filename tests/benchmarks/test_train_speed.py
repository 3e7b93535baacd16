"""benchmarks/train_speed.py: its fallback defaults are TrainConfig's, and a 1-step run writes its JSON."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import pytest

from telerig.learn.train import TrainConfig

SCRIPT = Path(__file__).resolve().parents[2] / "benchmarks" / "train_speed.py"


def test_fallback_defaults_match_train_config(load_benchmark: Callable[[str], ModuleType]) -> None:
    module = load_benchmark("train_speed")
    assert module._defaults() == module._FALLBACK_DEFAULTS  # read from TrainConfig where importable
    for policy, fallback in module._FALLBACK_DEFAULTS.items():
        config = TrainConfig.for_policy(policy)
        assert (config.hidden, config.batch_size, config.steps, config.learning_rate) == (
            fallback["hidden"],
            fallback["batch_size"],
            fallback["steps"],
            fallback["lr"],
        )
        assert (config.chunk_size, config.layers, config.channels, config.keypoints) == (
            fallback["chunk_size"],
            fallback["layers"],
            fallback["channels"],
            fallback["keypoints"],
        )


@pytest.mark.slow
def test_one_step_run_writes_the_table_and_json(tmp_path: Path) -> None:
    out = tmp_path / "speed.json"
    cmd = [
        sys.executable,
        str(SCRIPT),
        "--cores",
        "1",
        "--steps",
        "1",
        "--image-width",
        "32",
        "--json",
        str(out),
    ]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "steps/s" in done.stdout
    result = json.loads(out.read_text())
    assert [r["policy"] for r in result["rows"]] == ["bc", "act_lite"]
    assert all(r["steps_per_s"] > 0 for r in result["rows"])
    assert result["reference_gflops"] > 0
