"""Offline humanoid retargeting: zero-phase low-pass, whole recordings from BVH and MCAP, flags, files."""

from __future__ import annotations

import importlib.util
import json
import math
from pathlib import Path

import numpy as np
import pytest

from telerig.devices.mocap.fake import sample_bvh_path
from telerig.errors import DependencyError, RecordingError
from telerig.ir import wire
from telerig.ir.mcap_log import McapLog
from telerig.ir.types import BodySkeleton, Stamp
from telerig.retarget.humanoid import KEYPOINTS, HumanoidIK
from telerig.retarget.offline import load_skeletons, lowpass, retarget_recording

pytestmark = pytest.mark.sim

_RATE = 100.0  # [Hz]
_PELVIS = np.array([0.0, 0.0, 0.795])  # the G1 URDF standing on straight legs


@pytest.fixture(scope="module")
def ik() -> HumanoidIK:
    return HumanoidIK()


def test_lowpass_does_not_shift_a_delayed_sine() -> None:
    t = np.arange(0.0, 10.0, 1.0 / _RATE)
    x = np.sin(2 * np.pi * 1.0 * (t - 0.13))  # 1 Hz, delayed by 130 ms
    y = lowpass(x, _RATE, cutoff_hz=5.0, order=4)
    middle = slice(200, -200)
    np.testing.assert_allclose(y[middle], x[middle], atol=2e-3)
    lags = np.arange(-20, 21)
    corr = [np.dot(np.roll(y, lag)[middle], x[middle]) for lag in lags]
    assert lags[int(np.argmax(corr))] == 0


def test_lowpass_attenuates_above_the_cutoff() -> None:
    t = np.arange(0.0, 10.0, 1.0 / _RATE)
    y = lowpass(np.sin(2 * np.pi * 20.0 * t), _RATE, cutoff_hz=5.0, order=4)
    assert np.max(np.abs(y[200:-200])) < 1e-3


def test_lowpass_refuses_a_cutoff_above_nyquist() -> None:
    with pytest.raises(ValueError, match="half the 8 Hz sample rate"):
        lowpass(np.zeros(50), 8.0, cutoff_hz=5.0)


def _skeleton(ik: HumanoidIK, q: np.ndarray, k: int, *, source: str = "mocap0/body") -> BodySkeleton:
    points = ik.points(q)
    rows = [points[name] for name in KEYPOINTS[:6]]
    rows += [_PELVIS + np.array([0.0, -0.1, 0.0]), _PELVIS + np.array([0.0, 0.1, 0.0])]
    positions = (np.array(rows) - _PELVIS) * 1.3
    t = 1_000_000_000 + round(k * 1e9 / _RATE)
    return BodySkeleton(
        Stamp(source, k, t, t), KEYPOINTS, positions, np.tile([1.0, 0, 0, 0], (8, 1)), "operator"
    )


def _write_episode(path: Path, skeletons: list[BodySkeleton]) -> None:
    with McapLog(path) as log:
        for s in skeletons:
            topic = f"telerig/v1/test/{s.stamp.source_id}"
            log.write(
                topic, wire.encode(s), log_time_ns=s.stamp.capture_ns, publish_time_ns=s.stamp.capture_ns
            )


def _motion(ik: HumanoidIK, n: int) -> list[np.ndarray]:
    """A slow wave of both arms (0.5 Hz), well inside the limits."""
    out = []
    for k in range(n):
        q = np.array(ik.home)
        phase = math.sin(2 * np.pi * 0.5 * k / _RATE)
        q[1:6] += 0.3 * phase
        q[6:11] -= 0.3 * phase
        out.append(np.clip(q, ik.lower, ik.upper))
    return out


def test_shipped_bvh_clip_retargets_without_flags(tmp_path: Path, ik: HumanoidIK) -> None:
    calls: list[tuple[int, int]] = []
    result = retarget_recording(
        sample_bvh_path(),
        tmp_path,
        ik=ik,
        plot=False,
        progress=lambda done, total: calls.append((done, total)),
    )
    assert result.summary.frames == 180
    assert result.summary.profile == "cmu"
    assert result.summary.flagged == 0
    assert result.summary.rate_hz == pytest.approx(60.0, rel=1e-3)
    assert np.all(result.q >= ik.lower)
    assert np.all(result.q <= ik.upper)
    assert calls[-1] == (180, 180)
    assert len(calls) == 180
    saved = np.load(tmp_path / "humanoid_retarget.npz")
    np.testing.assert_array_equal(saved["q"], result.q)
    np.testing.assert_array_equal(saved["t_ns"], result.t_ns)
    assert tuple(saved["joint_names"]) == ik.joint_names
    assert json.loads(str(saved["summary"]))["frames"] == 180


def test_episode_mcap_flags_the_frame_with_an_unreachable_hand(tmp_path: Path, ik: HumanoidIK) -> None:
    skeletons = [_skeleton(ik, q, k) for k, q in enumerate(_motion(ik, 300))]
    # Frames 150..199: the right hand folded back onto the shoulder (the elbow cannot bend that far).
    for k in range(150, 200):
        s = skeletons[k]
        positions = np.array(s.positions)
        positions[1] = positions[0] + np.array([0.35, 0.0, 0.0])
        positions[2] = positions[0] + np.array([0.04, 0.0, 0.0])
        skeletons[k] = BodySkeleton(s.stamp, s.joint_names, positions, s.orientations, s.frame_id)
    episode = tmp_path / "ep1"
    episode.mkdir()
    _write_episode(episode / "episode.mcap", skeletons)
    result = retarget_recording(episode, ik=ik)
    assert result.summary.frames == 300
    flagged = np.flatnonzero(result.flagged)
    assert set(range(160, 190)) <= set(flagged)
    # The filter smears the edges a little, and moving back at the speed limit takes about 0.3 s.
    assert set(flagged) <= set(range(140, 260))
    assert result.summary.max_wrist_error_m > 0.05
    assert np.max(result.wrist_errors[:120]) < 0.01  # the reachable motion tracks well
    assert np.max(result.wrist_errors[260:]) < 0.01  # and again once the hand is back in reach


def test_several_skeleton_streams_need_a_source_id(tmp_path: Path, ik: HumanoidIK) -> None:
    qs = _motion(ik, 20)
    path = tmp_path / "two.mcap"
    _write_episode(
        path, [_skeleton(ik, q, k, source=s) for k, q in enumerate(qs) for s in ("a/body", "b/body")]
    )
    with pytest.raises(RecordingError, match="a/body, b/body"):
        load_skeletons(path)
    assert len(load_skeletons(path, source_id="b/body")) == 20


def test_missing_recording_is_a_recording_error(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match="not found"):
        retarget_recording(tmp_path / "nope.bvh")


def test_plot_is_written_when_matplotlib_is_installed(tmp_path: Path, ik: HumanoidIK) -> None:
    if importlib.util.find_spec("matplotlib") is None:
        with pytest.raises(DependencyError, match="pip install matplotlib"):
            retarget_recording(sample_bvh_path(), tmp_path, ik=ik, plot=True)
    else:
        result = retarget_recording(sample_bvh_path(), tmp_path, ik=ik, plot=True)
        assert (tmp_path / "humanoid_retarget.png") in result.files
