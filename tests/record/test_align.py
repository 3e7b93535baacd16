"""Frame-centric alignment: policies, tolerance, slerp, and the report stored in the manifest."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from telerig.errors import RecordingError
from telerig.ir import wire
from telerig.ir.frames import quat_angle, quat_from_axis_angle
from telerig.ir.mcap_log import McapLog, read_log
from telerig.ir.types import CameraFrame, JointState, Pose, Sample, Stamp
from telerig.record.align import (
    CaptureTimes,
    StreamData,
    StreamPolicy,
    align,
    align_episode,
    alignment_report,
    slerp,
)

RIG = "telerig/v1/test"
FRAMES = f"{RIG}/wrist/frames"
SIDE = f"{RIG}/side/frames"
JOINTS = f"{RIG}/arm/joint_state"
POSE = f"{RIG}/vr0/head"
MS = 1_000_000
T0 = 1_700_000_000_000_000_000


def _stream(times_ms: list[float], values: list[float] | None = None) -> StreamData:
    t = np.array([T0 + round(x * MS) for x in times_ms], dtype=np.int64)
    v = np.array(values if values is not None else times_ms, dtype=np.float64)
    return StreamData("s", "Test", t, {"x": v})


def _frames(times_ms: list[float]) -> np.ndarray:
    return np.array([T0 + round(x * MS) for x in times_ms], dtype=np.int64)


def _write(path: Path, entries: list[tuple[str, Sample]]) -> None:
    with McapLog(path) as log:
        for topic, s in entries:
            c = s.stamp.capture_ns
            log.write(topic, wire.encode(s), log_time_ns=c + MS, publish_time_ns=c)


def _episode(path: Path, *, seconds: float = 1.0, gap_ms: tuple[float, float] | None = None) -> None:
    """A 30 fps wrist camera, a 15 fps side camera, joints at 100 Hz (offset 1 ms), a head pose at 50 Hz."""
    entries: list[tuple[str, Sample]] = []
    for i in range(round(seconds * 30)):
        t = T0 + round(i * 1e9 / 30)
        entries.append((FRAMES, CameraFrame(Stamp("wrist", i, t, t), "wrist", i, 64, 48)))
    for i in range(round(seconds * 15)):
        t = T0 + round(i * 1e9 / 15) + 2 * MS
        entries.append((SIDE, CameraFrame(Stamp("side", i, t, t), "side", i, 64, 48)))
    for i in range(round(seconds * 100)):
        t_ms = i * 10.0 + 1.0
        if gap_ms is not None and gap_ms[0] <= t_ms < gap_ms[1]:
            continue
        t = T0 + round(t_ms * MS)
        q = t_ms / 1000.0  # position ramps at 1 rad/s
        entries.append((JOINTS, JointState(Stamp("arm", i, t, t), ("j1", "j2"), (q, -q), (1.0, -1.0))))
    for i in range(round(seconds * 50)):
        t = T0 + i * 20 * MS
        angle = i * 20e-3  # 1 rad/s about z
        entries.append(
            (
                POSE,
                Pose(
                    Stamp("vr0/head", i, t, t),
                    (0.0, 0.0, angle),
                    quat_from_axis_angle(np.array([0, 0, 1.0]), angle),
                    "operator",
                ),
            )
        )
    entries.sort(key=lambda e: e[1].stamp.capture_ns)
    _write(path, entries)


# --- slerp ---------------------------------------------------------------------------------------


def test_slerp_endpoints_return_the_inputs() -> None:
    a = quat_from_axis_angle(np.array([1.0, 2.0, 3.0]), 0.4)
    b = quat_from_axis_angle(np.array([0.0, 1.0, 0.0]), 1.3)
    np.testing.assert_allclose(slerp(a, b, 0.0), a, atol=1e-12)
    np.testing.assert_allclose(slerp(a, b, 1.0), b, atol=1e-12)


def test_slerp_midpoint_is_half_the_rotation() -> None:
    z = np.array([0.0, 0.0, 1.0])
    mid = slerp(quat_from_axis_angle(z, 0.0), quat_from_axis_angle(z, math.pi / 2), 0.5)
    assert quat_angle(mid, quat_from_axis_angle(z, math.pi / 4)) == pytest.approx(0.0, abs=1e-9)


def test_slerp_takes_the_short_arc_when_signs_differ() -> None:
    z = np.array([0.0, 0.0, 1.0])
    a, b = quat_from_axis_angle(z, 0.2), -quat_from_axis_angle(z, 0.4)
    assert quat_angle(slerp(a, b, 0.5), quat_from_axis_angle(z, 0.3)) == pytest.approx(0.0, abs=1e-9)


def test_slerp_is_vectorized_and_unit_norm() -> None:
    rng = np.random.default_rng(0)
    a = rng.normal(size=(7, 5, 4))
    b = rng.normal(size=(7, 5, 4))
    a /= np.linalg.norm(a, axis=-1, keepdims=True)
    b /= np.linalg.norm(b, axis=-1, keepdims=True)
    out = slerp(a, b, rng.uniform(size=(7, 1)))
    assert out.shape == (7, 5, 4)
    np.testing.assert_allclose(np.linalg.norm(out, axis=-1), 1.0, atol=1e-12)


def test_slerp_of_equal_quaternions_is_that_quaternion() -> None:
    q = quat_from_axis_angle(np.array([1.0, 0.0, 0.0]), 0.7)
    np.testing.assert_allclose(slerp(q, q, 0.3), q, atol=1e-12)


# --- policies on arrays --------------------------------------------------------------------------


def test_nearest_picks_the_closest_sample_and_reports_its_distance() -> None:
    out = align({"s": _stream([0, 10, 20, 30])}, _frames([4, 6, 29]), tolerance_ms=5.0)["s"]
    np.testing.assert_array_equal(out.source_index, [0, 1, 3])
    np.testing.assert_array_equal(out.error_ns, [4 * MS, 4 * MS, 1 * MS])
    np.testing.assert_array_equal(out.fields["x"], [0.0, 10.0, 30.0])


def test_zoh_holds_the_last_sample_at_or_before_the_frame() -> None:
    out = align({"s": _stream([0, 10, 20])}, _frames([9, 10, 19.5]), policy="zoh", tolerance_ms=20.0)["s"]
    np.testing.assert_array_equal(out.fields["x"], [0.0, 10.0, 10.0])
    np.testing.assert_array_equal(out.error_ns, [9 * MS, 0, round(9.5 * MS)])


def test_zoh_frame_before_the_first_sample_has_no_sample() -> None:
    out = align({"s": _stream([10, 20])}, _frames([5, 15]), policy="zoh", tolerance_ms=50.0)["s"]
    assert out.valid.tolist() == [False, True]
    assert out.source_index[0] == -1
    assert (out.stats.no_sample, out.stats.valid) == (1, 1)


def test_linear_interpolates_between_the_bracketing_samples() -> None:
    out = align({"s": _stream([0, 10, 20], [0.0, 1.0, 3.0])}, _frames([2.5, 15]), policy="linear")["s"]
    np.testing.assert_allclose(out.fields["x"], [0.25, 2.0])
    np.testing.assert_array_equal(out.error_ns, [round(2.5 * MS), 5 * MS])


def test_linear_holds_the_end_sample_outside_the_recorded_span() -> None:
    out = align({"s": _stream([10, 20], [1.0, 2.0])}, _frames([8, 23]), policy="linear")["s"]
    np.testing.assert_allclose(out.fields["x"], [1.0, 2.0])


def test_linear_does_not_interpolate_discrete_fields() -> None:
    data = StreamData("s", "Test", _frames([0, 10]), {"i": np.array([4.0, 5.0])}, frozenset({"i"}))
    out = align({"s": data}, _frames([3, 7]), policy="linear")["s"]
    np.testing.assert_array_equal(out.fields["i"], [4.0, 5.0])


def test_frames_beyond_tolerance_are_masked_and_counted() -> None:
    out = align({"s": _stream([0, 10, 100])}, _frames([0, 50, 101]), tolerance_ms=5.0)["s"]
    assert out.valid.tolist() == [True, False, True]
    assert math.isnan(out.fields["x"][1])
    assert out.stats.beyond_tolerance == 1
    assert out.stats.max_ms == pytest.approx(40.0)


def test_error_percentiles_are_in_milliseconds() -> None:
    out = align({"s": _stream([0, 100, 200, 300])}, _frames([1, 102, 203, 304]), tolerance_ms=10.0)["s"]
    assert out.stats.p50_ms == pytest.approx(2.5)
    assert out.stats.max_ms == pytest.approx(4.0)
    assert out.stats.p99_ms == pytest.approx(np.percentile([1, 2, 3, 4], 99))


def test_an_empty_stream_is_missing_everywhere() -> None:
    data = StreamData("s", "Test", np.zeros(0, dtype=np.int64), {"x": np.zeros((0, 3))})
    out = align({"s": data}, _frames([0, 1]))["s"]
    assert not out.valid.any()
    assert out.fields["x"].shape == (2, 3)
    assert out.stats.no_sample == 2
    assert math.isnan(out.stats.p50_ms)


def test_per_stream_policy_overrides_by_stream_name() -> None:
    streams = {f"{RIG}/arm/joint_state": _stream([0, 10]), f"{RIG}/arm/other": _stream([0, 10])}
    out = align(streams, _frames([5]), policies={"joint_state": StreamPolicy("linear", 6.0)})
    assert (out[f"{RIG}/arm/joint_state"].policy, out[f"{RIG}/arm/joint_state"].tolerance_ms) == (
        "linear",
        6.0,
    )
    assert out[f"{RIG}/arm/other"].policy == "nearest"


def test_unknown_policy_names_the_available_ones() -> None:
    with pytest.raises(ValueError, match="Available: nearest, linear, zoh"):
        align({}, _frames([0]), policy="cubic")  # type: ignore[arg-type]


def test_unsorted_frames_are_rejected() -> None:
    with pytest.raises(ValueError, match="non-decreasing"):
        align({}, _frames([10, 0]))


# --- episodes ------------------------------------------------------------------------------------


def test_episode_fields_have_documented_shapes(tmp_path: Path) -> None:
    _episode(tmp_path / "ep.mcap")
    view = align_episode(tmp_path / "ep.mcap")
    assert view.anchor == SIDE  # first camera by topic
    view = align_episode(tmp_path / "ep.mcap", anchor="wrist")
    assert view.anchor == FRAMES
    assert view.frame_ns.shape == (30,)
    np.testing.assert_array_equal(view.frame_index, np.arange(30))
    joints = view.streams[JOINTS]
    assert joints.fields["positions"].shape == (30, 2)
    assert joints.fields["efforts"].shape == (30, 0)
    assert view.streams[POSE].fields["orientation"].shape == (30, 4)
    assert view.streams[SIDE].fields["frame_index"].shape == (30,)
    assert set(view.streams) == {JOINTS, POSE, SIDE}


def test_episode_linear_policy_reconstructs_the_signal_at_frame_times(tmp_path: Path) -> None:
    _episode(tmp_path / "ep.mcap")
    view = align_episode(tmp_path / "ep.mcap", anchor="wrist", policy="linear", topics=[JOINTS, POSE])
    t_s = (view.frame_ns - T0) / 1e9
    inside = t_s >= 0.001  # the first frame is before the first joint sample
    np.testing.assert_allclose(view.streams[JOINTS].fields["positions"][inside, 0], t_s[inside], atol=1e-9)
    pose = view.streams[POSE]
    z = np.array([0.0, 0.0, 1.0])
    for t, q in zip(t_s[:29], pose.fields["orientation"][:29], strict=True):
        assert quat_angle(q, quat_from_axis_angle(z, t)) == pytest.approx(0.0, abs=1e-6)


def test_episode_gap_masks_frames_of_that_stream_only(tmp_path: Path) -> None:
    _episode(tmp_path / "ep.mcap", gap_ms=(300.0, 500.0))
    tolerances = {"frames": StreamPolicy("nearest", 40.0), "head": StreamPolicy("nearest", 10.0)}
    view = align_episode(tmp_path / "ep.mcap", anchor="wrist", policies=tolerances)
    joints = view.streams[JOINTS]
    frame_ms = (view.frame_ns - T0) / 1e6
    expected_missing = (frame_ms > 291.0 + 5.0) & (frame_ms < 501.0 - 5.0)
    np.testing.assert_array_equal(~joints.valid, expected_missing)
    assert joints.stats.beyond_tolerance == int(expected_missing.sum())
    assert view.streams[POSE].valid.all()
    np.testing.assert_array_equal(view.valid, ~expected_missing)


def test_report_matches_the_aligned_view_and_is_json(tmp_path: Path) -> None:
    _episode(tmp_path / "ep.mcap")
    report: Any = alignment_report(tmp_path / "ep.mcap", anchor="wrist", policies={"head": "zoh"})
    view = align_episode(tmp_path / "ep.mcap", anchor="wrist", policies={"head": "zoh"})
    assert report == view.report()
    json.dumps(report, allow_nan=False)
    joints = report["streams"][JOINTS]
    assert joints["samples"] == 100
    assert joints["error_ms"]["max"] <= 5.0
    assert report["anchor"]["frames"] == 30
    assert report["anchor"]["fps"] == pytest.approx(30.0)


def test_capture_times_gathered_while_recording_give_the_file_report(tmp_path: Path) -> None:
    _episode(tmp_path / "ep.mcap")
    times = CaptureTimes()
    for entry in read_log(tmp_path / "ep.mcap"):
        times.add(entry.topic, entry.sample.stamp.capture_ns)
    assert times.report(policy="zoh") == alignment_report(tmp_path / "ep.mcap", policy="zoh")


def test_episode_without_cameras_says_how_to_anchor(tmp_path: Path) -> None:
    t = T0
    _write(tmp_path / "ep.mcap", [(JOINTS, JointState(Stamp("arm", 0, t, t), ("j1",), (0.0,), (0.0,)))])
    with pytest.raises(RecordingError, match="no camera frames topic"):
        alignment_report(tmp_path / "ep.mcap")


def test_unknown_anchor_names_the_cameras(tmp_path: Path) -> None:
    _episode(tmp_path / "ep.mcap")
    with pytest.raises(RecordingError, match="Available: side, wrist"):
        align_episode(tmp_path / "ep.mcap", anchor="top")
