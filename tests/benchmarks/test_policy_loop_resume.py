"""benchmarks/policy_loop.py --resume: a finished size is reused only from a run with the same settings,
demonstrations and evaluation episodes; a damaged report is refused in one line."""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from types import ModuleType

import pytest

SCRIPT = Path(__file__).resolve().parents[2] / "benchmarks" / "policy_loop.py"
IDS = [f"ep-{i:02d}" for i in range(50)]


@pytest.fixture(scope="module")
def loop(load_benchmark: Callable[[str], ModuleType]) -> ModuleType:
    return load_benchmark("policy_loop")


def _args(loop: ModuleType, out: Path, **changes: object) -> argparse.Namespace:
    settings = {
        "rig": "pick_place",
        "policy": "bc",
        "steps": 6000,
        "shift_px": 2,
        "gripper_weight": 5.0,
        "trim_idle": True,
        "include_rejected": True,
        "train_on_failures": False,
        "temporal_ensemble": 0.01,
        "execute_actions": None,
    }
    assert set(settings) == set(loop.RESULT_SETTINGS)
    return argparse.Namespace(**{**settings, **changes}, resume=True, out=out)


def _earlier_run(loop: ModuleType, out: Path, **settings: object) -> None:
    done = loop.SizeResult(50, "aligned", IDS, 50, 69.0, 1237.0, 1138.0, 1.0, [0.93, 1.0], 14.3)
    failed = loop.SizeResult(10, "aligned", IDS[:10], 20, error="train: out of memory")
    parts = [
        loop.Part(name, [], seconds, 0)
        for name, seconds in (
            ("export aligned_50", 69.0),
            ("train aligned_50", 1237.0),
            ("eval aligned_50", 1138.0),
        )
    ]
    args = {k: v for k, v in vars(_args(loop, out, **settings)).items() if k != "out"}
    out.write_text(
        json.dumps(
            {"args": args, "results": [asdict(done), asdict(failed)], "parts": [asdict(p) for p in parts]}
        )
    )


def test_a_finished_size_is_reused_with_its_parts(loop: ModuleType, tmp_path: Path) -> None:
    out = tmp_path / "policy_loop.json"
    _earlier_run(loop, out)
    previous = loop._previous(_args(loop, out))
    reused = loop._reused(previous, IDS, 50, "aligned", 50)
    assert reused is not None
    result, parts = reused
    assert (result.success_rate, result.train_s) == (1.0, 1237.0)
    assert [p.name for p in parts] == [
        "export aligned_50 (reused)",
        "train aligned_50 (reused)",
        "eval aligned_50 (reused)",
    ]


def test_a_size_that_failed_or_differs_is_run_again(loop: ModuleType, tmp_path: Path) -> None:
    out = tmp_path / "policy_loop.json"
    _earlier_run(loop, out)
    previous = loop._previous(_args(loop, out))
    assert loop._reused(previous, IDS, 10, "aligned", 20) is None  # it failed
    assert loop._reused(previous, IDS, 50, "aligned", 20) is None  # fewer evaluation episodes
    assert loop._reused(previous, IDS[::-1], 50, "aligned", 50) is None  # other demonstrations
    assert loop._reused(previous, IDS, 50, "camera+100ms", 50) is None  # the shifted variant


@pytest.mark.parametrize(
    "change", [{"steps": 3000}, {"gripper_weight": 1.0}, {"trim_idle": False}, {"policy": "act-lite"}]
)
def test_other_settings_reuse_nothing(loop: ModuleType, tmp_path: Path, change: dict[str, object]) -> None:
    out = tmp_path / "policy_loop.json"
    _earlier_run(loop, out, **change)
    assert loop._previous(_args(loop, out)) == ([], [])


def test_without_resume_nothing_is_read(loop: ModuleType, tmp_path: Path) -> None:
    out = tmp_path / "policy_loop.json"
    out.write_text("not json")
    args = _args(loop, out)
    args.resume = False
    assert loop._previous(args) == ([], [])


@pytest.mark.parametrize(
    "text",
    [
        "not json",
        "[]",
        '{"args": {}, "results": [{"nope": 1}], "parts": []}',
        '{"args": "x", "results": [], "parts": []}',
        '{"args": {}, "results": [7], "parts": []}',
        '{"args": {}, "results": [], "parts": null}',
    ],
)
def test_a_damaged_report_is_refused_in_one_line(loop: ModuleType, tmp_path: Path, text: str) -> None:
    out = tmp_path / "policy_loop.json"
    out.write_text(text)
    with pytest.raises(SystemExit, match=r"--resume cannot read .*delete it or drop --resume") as err:
        loop._previous(_args(loop, out))
    assert "\n" not in str(err.value)
