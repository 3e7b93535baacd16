"""``telerig retarget humanoid``: the shipped BVH clip → npz (+ plot), a one-line summary, exit codes."""

from __future__ import annotations

import argparse
import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

from telerig.cli.retarget import add_arguments
from telerig.devices.mocap.fake import sample_bvh_path
from telerig.errors import TelerigError
from telerig.robots.models.g1 import UPPER_BODY_JOINTS

pytestmark = pytest.mark.sim


def _run(*argv: str) -> int:
    parser = argparse.ArgumentParser(prog="telerig")
    add_arguments(parser.add_subparsers())
    args = parser.parse_args(["retarget", "humanoid", *argv])
    code: int = args.handler(args)
    return code


def test_shipped_clip_writes_the_trajectory_and_prints_a_summary(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert _run(str(sample_bvh_path()), "-o", str(tmp_path)) == 0
    out = capsys.readouterr().out
    summary = next(line for line in out.splitlines() if line.startswith("retargeted"))
    assert "retargeted 180 frames" in summary
    assert "profile cmu, 5 Hz low-pass (order 4)" in summary
    assert "0 flagged" in summary
    assert "max wrist error" in summary
    with np.load(tmp_path / "humanoid_retarget.npz") as npz:
        assert tuple(npz["joint_names"]) == UPPER_BODY_JOINTS
        assert npz["q"].shape == (180, len(UPPER_BODY_JOINTS))
        assert not npz["flagged"].any()
        assert json.loads(str(npz["summary"]))["cutoff_hz"] == 5.0
    if importlib.util.find_spec("matplotlib") is None:
        assert "no plot written: matplotlib is not installed" in out
    else:
        assert (tmp_path / "humanoid_retarget.png").stat().st_size > 0


def test_flagged_frames_exit_2_only_with_fail_on_flagged(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    tight = [str(sample_bvh_path()), "-o", str(tmp_path), "--no-filter", "--threshold", "0.001"]
    assert _run(*tight) == 0
    assert "no filter" in capsys.readouterr().out
    assert _run(*tight, "--fail-on-flagged") == 2


def test_a_cutoff_above_nyquist_is_one_line(tmp_path: Path) -> None:
    with pytest.raises(TelerigError, match=r"reach\.bvh: cutoff_hz must be in \(0, 30") as info:
        _run(str(sample_bvh_path()), "-o", str(tmp_path), "--cutoff", "40")
    assert "\n" not in str(info.value)


def test_a_wrong_profile_names_the_missing_joints(tmp_path: Path) -> None:
    with pytest.raises(TelerigError, match=r"lacks joints .* \(profile 'motive'") as info:
        _run(str(sample_bvh_path()), "-o", str(tmp_path), "--profile", "motive")
    assert "\n" not in str(info.value)


def test_a_missing_recording_is_one_line(tmp_path: Path) -> None:
    with pytest.raises(TelerigError, match=r"recording not found: .*nope\.bvh$"):
        _run(str(tmp_path / "nope.bvh"), "-o", str(tmp_path))


def test_cutoff_and_no_filter_are_exclusive(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        _run(str(sample_bvh_path()), "--cutoff", "4", "--no-filter")
    assert info.value.code == 2
    assert "not allowed with argument" in capsys.readouterr().err
