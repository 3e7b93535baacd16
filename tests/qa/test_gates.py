"""Each quality gate passes on a clean synthetic episode and fails on one with its defect."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from telerig.config.qa import GATES, QaThresholds
from telerig.qa import GateVerdict, QaReport, evaluate
from telerig.qa.timing import END_SLACK_S, gap_limit_ms, sample_interval_ms
from telerig.store.manifest_extra import SafetyEventRecord

DEFAULT = QaThresholds()


def _verdict(path: Path, gate: str, thresholds: QaThresholds = DEFAULT) -> GateVerdict:
    verdict = evaluate(path, thresholds.model_copy(update={"gates": (gate,)})).verdict(gate)
    assert verdict is not None
    return verdict


@pytest.fixture(scope="module")
def clean_report(clean_episode: Path) -> QaReport:
    return evaluate(clean_episode, DEFAULT)


@pytest.mark.parametrize(
    "gate", ["self_collision", "joint_limits", "sync", "teleop_faults", "calibration_drift", "idle"]
)
def test_clean_episode_passes(clean_report: QaReport, gate: str) -> None:
    verdict = clean_report.verdict(gate)
    assert verdict is not None
    assert verdict.passed is True, verdict


def test_clean_episode_report_passes_with_fall_and_force_not_applicable(clean_report: QaReport) -> None:
    assert clean_report.passed, clean_report.reasons
    assert [v.gate for v in clean_report.verdicts] == list(GATES)
    fall, force = clean_report.verdict("fall"), clean_report.verdict("force_spike")
    assert fall is not None
    assert fall.passed is None
    assert "nothing can fall" in fall.detail
    assert force is not None
    assert force.passed is None
    assert "no force/torque recorded" in force.detail


def test_report_json_round_trip(clean_report: QaReport) -> None:
    assert QaReport.from_json(clean_report.to_json()) == clean_report


# --- calibration drift ---------------------------------------------------------------------------


def test_drift_17_degree_offset_fails(synthetic: Any) -> None:
    offset = (0.0, 0.0, math.radians(17), 0.0, 0.0, 0.0)
    v = _verdict(synthetic.make(offset=offset), "calibration_drift")
    assert v.passed is False
    assert v.value == pytest.approx(math.radians(17), abs=1e-3)
    assert "elbow_joint" in v.detail
    assert "-17.0 deg" in v.detail


def test_drift_ignores_tracking_lag_of_100_ms(synthetic: Any) -> None:
    v = _verdict(synthetic.make(lag_s=0.1), "calibration_drift")
    assert v.passed is True
    assert v.value is not None
    assert v.value < 1e-3


def test_drift_not_judged_without_a_still_half_second(synthetic: Any) -> None:
    def always_moving(t: np.ndarray) -> np.ndarray:
        out: np.ndarray = synthetic.home + 0.2 * np.sin(2 * np.pi * t / 2.0)[:, None]
        return out

    v = _verdict(synthetic.make(sent=always_moving, offset=(0.3,) * 6), "calibration_drift")
    assert v.passed is None
    assert "tracking lag" in v.detail


# --- joint limits --------------------------------------------------------------------------------


def test_joint_at_1_1x_velocity_limit_fails(synthetic: Any) -> None:
    # The way back (0.5 rad in 1 s) peaks at 0.785 rad/s on shoulder pan; scaled to 1.1x the limit.
    peak = 0.5 * math.pi / 2 / 1.0
    v = _verdict(synthetic.make(speed_scale=1.1 * math.pi / peak), "joint_limits")
    assert v.passed is False
    assert v.value == pytest.approx(0.1, abs=0.01)
    assert "shoulder_pan_joint at 1.10x its velocity limit" in v.detail
    assert v.events
    assert 2.9 < v.events[0] < 3.2


def test_joint_at_1_04x_velocity_limit_passes(synthetic: Any) -> None:
    peak = 0.5 * math.pi / 2 / 1.0
    v = _verdict(synthetic.make(speed_scale=1.04 * math.pi / peak), "joint_limits")
    assert v.passed is True


def test_joint_beyond_position_limit_fails(synthetic: Any) -> None:
    def past_elbow_limit(t: np.ndarray) -> np.ndarray:
        q = np.tile(synthetic.home, (t.size, 1))
        target = math.pi + 0.4  # 0.4 rad past the limit: 6.4 % of the elbow's 2 pi range
        q[:, 2] += synthetic.ramp(t, 0.5, 3.0) * (target - q[0, 2])
        return q

    v = _verdict(synthetic.make(sent=past_elbow_limit, lag_s=0.0), "joint_limits")
    assert v.passed is False
    assert "elbow_joint" in v.detail
    assert "beyond its upper limit" in v.detail


def test_joint_limits_fall_back_to_the_model_named_in_the_fingerprint(synthetic: Any) -> None:
    peak = 0.5 * math.pi / 2 / 1.0
    v = _verdict(synthetic.make(speed_scale=1.1 * math.pi / peak, robot_joints=False), "joint_limits")
    assert v.passed is False
    assert "1.10x" in v.detail


# --- self-collision ------------------------------------------------------------------------------


def test_arm_folded_into_itself_fails(synthetic: Any) -> None:
    v = _verdict(synthetic.make(sent=synthetic.fold_and_back, lag_s=0.0), "self_collision")
    assert v.passed is False
    assert "upper_arm_link" in v.detail
    assert "penetrate" in v.detail
    assert v.value is not None
    assert v.value > 0.01
    assert v.events
    assert 0.5 < v.events[0] < 1.5


def test_self_collision_not_applicable_for_unknown_model(synthetic: Any) -> None:
    v = _verdict(
        synthetic.make(robot_type="ur_rtde", model="ur3_unknown", robot_joints=False), "self_collision"
    )
    assert v.passed is None
    assert "has no collision geometry" in v.detail


# --- sync ----------------------------------------------------------------------------------------


def test_60_ms_gap_fails_sync(synthetic: Any) -> None:
    v = _verdict(synthetic.make(state_gaps=[(2.0, 2.05)]), "sync")
    assert v.passed is False
    assert "arm0/joint_state paused 60 ms at t=1.99 s" in v.detail
    assert len(v.events) == 1
    assert v.events[0] == pytest.approx(1.991, abs=1e-3)


def test_a_15_hz_camera_is_not_a_gap_every_frame_but_a_missing_frame_is(synthetic: Any) -> None:
    # The pick_place rig's camera runs at 15 Hz: 67 ms between frames is its cadence, not a pause
    # over the 50 ms limit (every demonstration was rejected for it). A slow stream fails on a gap
    # over 1.5 of its periods, so one missing sample fails.
    assert gap_limit_ms(50.0, 15.0) == pytest.approx(100.0)
    assert gap_limit_ms(50.0, 100.0) == gap_limit_ms(50.0, 30.0) == 50.0
    v = _verdict(synthetic.make(camera_hz=15.0), "sync")
    assert v.passed is True, v.detail
    v = _verdict(synthetic.make(rate_hz=15.0, state_gaps=[(1.99, 2.01)]), "sync")  # the 2.0 s sample
    assert v.passed is False
    assert "arm0/joint_state paused 133 ms" in v.detail
    assert "limit 100 ms" in v.detail


def test_a_stream_that_stops_before_the_episode_ends_fails_sync(synthetic: Any) -> None:
    # Gaps and rates are measured between samples, so a stream that stopped mid-episode (a source
    # that died, or a station that fell behind its streams and closed the episode before it had
    # received their tail) looked complete. The time after its last sample is checked now.
    seconds = 4.0
    v = _verdict(synthetic.make(seconds=seconds, state_gaps=[(2.5, seconds)]), "sync")
    assert v.passed is False
    assert (
        "arm0/joint_state stopped 1.51 s before the episode's end (last sample at t=2.49 of 4.00 s)"
        in v.detail
    )
    assert v.value == pytest.approx(1.51 / 4.0, abs=0.01)
    assert any(abs(e - 2.49) < 0.01 for e in v.events)
    # The stop sequence's last tenths of a second are not a stream stopping.
    slack = END_SLACK_S - 0.2
    v = _verdict(synthetic.make(seconds=seconds, state_gaps=[(seconds - slack, seconds)]), "sync")
    assert "stopped" not in v.detail


def test_a_camera_gap_says_what_the_camera_counted(synthetic: Any) -> None:
    # A frame gap names the camera's own counters of the episode (the render fell behind, or the
    # camera thread woke late), which the manifest records per camera since issue 18.
    counted = {"cameras": {"scene": {"file": "cameras/scene.mp4", "frames": 88, "skipped": 2, "late": 1}}}
    v = _verdict(synthetic.make(frame_gaps=[(1.0, 1.07)], extra=counted), "sync")
    assert v.passed is False
    assert (
        "scene/frames paused 133 ms at t=0.97 s (limit 50 ms; 1 gap(s)) (the camera skipped 2 frames, 1 late)"
        in v.detail
    )
    # Recorded before cameras counted: the same line, without the counts.
    v = _verdict(synthetic.make(frame_gaps=[(1.0, 1.07)]), "sync")
    assert "scene/frames paused 133 ms" in v.detail
    assert "the camera" not in v.detail


def test_messages_of_one_tick_are_one_sample_for_the_alignment_distance() -> None:
    # pick_place publishes the cube's and the zone's pose each 100 Hz tick on object_pose: a frame
    # is up to 5 ms from a sample by the tick rate, so the gate's distance is 10 ms, not 5 (13 % of
    # every demonstration's frames "missed" object_pose).
    ticks = np.arange(100) * 10_000_000
    pairs = np.sort(np.concatenate([ticks, ticks + 20_000]))  # two poses 20 us apart per tick
    assert sample_interval_ms(pairs) == pytest.approx(10.0, abs=0.05)
    assert sample_interval_ms(ticks) == pytest.approx(10.0)
    assert sample_interval_ms(np.array([5, 5, 5])) == 0.0


def test_slow_camera_fails_sync_on_lost_frames(synthetic: Any) -> None:
    path = synthetic.make(camera_hz=30.0)
    thresholds = DEFAULT.model_copy(update={"max_gap_ms": 1000.0})
    # The recorder expected 30 Hz; a camera that delivers 15 loses half of its frames.
    import json

    manifest = json.loads((path / "manifest.json").read_text())
    for s in manifest["extra"]["streams"]:
        if s["name"].endswith("/frames"):
            s["measured_hz"] = 15.0
    (path / "manifest.json").write_text(json.dumps(manifest))
    v = _verdict(path, "sync", thresholds)
    assert v.passed is False
    assert "scene/frames lost 50.0 %" in v.detail


def test_holes_shorter_than_the_gap_limit_fail_sync_on_missed_frames(synthetic: Any) -> None:
    # 40 ms between samples every 200 ms: no gap over 50 ms, but a tenth of the frames fall 10+ ms off.
    holes = [(0.095 + k * 0.2, 0.125 + k * 0.2) for k in range(19)]
    v = _verdict(synthetic.make(state_gaps=holes), "sync")
    assert v.passed is False
    assert "arm0/joint_state has no sample within 10 ms of" in v.detail
    assert "paused" not in v.detail


def test_residuals_only_while_input_arrives_pass_sync(synthetic: Any) -> None:
    # One typed residual per solved input sample: none while the operator's device sends nothing.
    # The residual is derived from the input stream like joint_command_requested, not judged itself.
    path = synthetic.make(residual_window=(0.0, 1.0))
    v = _verdict(path, "sync")
    assert v.passed is True, v.detail
    manifest = (path / "manifest.json").read_text()
    assert "arm0/residual" in manifest, "the recorder's alignment report lists it: the gate skips it"


def test_jitter_within_a_sample_interval_passes_sync(synthetic: Any) -> None:
    # Camera frames land mid-way between 100 Hz joint states: 5 ms, the rig's tolerance, plus 1 ms.
    v = _verdict(synthetic.make(), "sync", DEFAULT.model_copy(update={"alignment_tolerance_ms": 1.0}))
    assert v.passed is True


# --- teleoperation faults ------------------------------------------------------------------------


@pytest.mark.parametrize("old_json", [False, True], ids=["typed", "json_before_issue_18"])
def test_residual_flagged_for_a_second_fails(synthetic: Any, old_json: bool) -> None:
    v = _verdict(synthetic.make(residual_flagged=(1.0, 2.0), residual_json=old_json), "teleop_faults")
    assert v.passed is False
    assert v.value == pytest.approx(1.0, abs=0.02)
    assert v.events == (1.0,)


@pytest.mark.parametrize("old_json", [False, True], ids=["typed", "json_before_issue_18"])
def test_residual_flagged_briefly_passes(synthetic: Any, old_json: bool) -> None:
    v = _verdict(synthetic.make(residual_flagged=(1.0, 1.2), residual_json=old_json), "teleop_faults")
    assert v.passed is True
    assert v.value == pytest.approx(0.2, abs=0.02)


def test_estop_in_safety_log_fails(synthetic: Any) -> None:
    stop = SafetyEventRecord(
        t_ns=1_800_000_002_500_000_000, robot="arm0", code="operator_estop", reason="estop by op"
    )
    v = _verdict(synthetic.make(safety_log=[stop], status=[(0.0, "ok"), (2.5, "estopped")]), "teleop_faults")
    assert v.passed is False
    assert "operator_estop at t=2.50 s" in v.detail
    assert "estopped at t=2.50 s" in v.detail
    assert v.events == (2.5,)


def test_tick_fault_fails(synthetic: Any) -> None:
    assert _verdict(synthetic.make(tick_faults=3), "teleop_faults").passed is False


# --- idle ----------------------------------------------------------------------------------------


def test_still_episode_is_idle(synthetic: Any) -> None:
    report = evaluate(synthetic.make(sent=synthetic.still), DEFAULT.model_copy(update={"gates": ("idle",)}))
    assert report.idle_fraction == 1.0
    assert report.idle_segments == ((0.0, 4.0),)
    v = report.verdict("idle")
    assert v is not None
    assert v.passed is False


def test_idle_segments_are_head_pause_and_tail(clean_episode: Path) -> None:
    # reach_and_back, measured 30 ms late: still to 0.63 s, pause 1.83-2.63 s, still after 3.63 s.
    report = evaluate(clean_episode, DEFAULT.model_copy(update={"idle_min_pause_s": 0.5}))
    (head, pause, tail) = report.idle_segments
    assert head[0] == 0.0
    assert head[1] == pytest.approx(0.66, abs=0.06)
    assert pause[0] == pytest.approx(1.8, abs=0.06)
    assert pause[1] == pytest.approx(2.66, abs=0.06)
    assert tail[0] == pytest.approx(3.6, abs=0.06)
    assert tail[1] == 4.0
    assert report.idle_fraction == pytest.approx(0.45, abs=0.05)


def test_pause_shorter_than_the_minimum_is_not_a_segment(clean_report: QaReport) -> None:
    # The 0.8 s pause is below the 1 s default: only the head and tail are trimmable.
    assert [round(a) for a, _ in clean_report.idle_segments] == [0, 4]


# --- fall and force spike ------------------------------------------------------------------------


def test_humanoid_pelvis_below_half_height_fails(synthetic: Any) -> None:
    def falls(t: np.ndarray) -> np.ndarray:
        return np.where(t < 2.0, 0.795, 0.2)

    v = _verdict(synthetic.make(base_z=falls, robot_type="mujoco_humanoid", standing_height_m=0.795), "fall")
    assert v.passed is False
    assert v.value == pytest.approx(0.2 / 0.795)
    assert v.events == (2.0,)


def test_humanoid_standing_passes(synthetic: Any) -> None:
    v = _verdict(
        synthetic.make(
            base_z=lambda t: np.full(t.size, 0.79), robot_type="mujoco_humanoid", standing_height_m=0.795
        ),
        "fall",
    )
    assert v.passed is True


def test_humanoid_without_base_pose_is_not_applicable(synthetic: Any) -> None:
    v = _verdict(synthetic.make(robot_type="mujoco_humanoid", standing_height_m=0.795), "fall")
    assert v.passed is None
    assert "no base_pose stream" in v.detail


def test_force_spike_fails(synthetic: Any) -> None:
    def spike(t: np.ndarray) -> np.ndarray:
        f = np.tile([0.0, 0.0, -9.0], (t.size, 1))
        f[(t > 1.5) & (t < 1.6), 0] = 300.0
        return f

    v = _verdict(synthetic.make(force=spike), "force_spike")
    assert v.passed is False
    assert v.value is not None
    assert v.value > 300.0
    assert v.events
    assert v.events[0] == pytest.approx(1.51)


def test_gripper_weight_passes_force_gate(synthetic: Any) -> None:
    v = _verdict(synthetic.make(force=lambda t: np.tile([0.0, 0.0, -9.0], (t.size, 1))), "force_spike")
    assert v.passed is True
    assert v.value == pytest.approx(9.0)


def test_gate_list_limits_what_runs(synthetic: Any) -> None:
    report = evaluate(synthetic.make(), DEFAULT.model_copy(update={"gates": ("sync", "idle")}))
    assert [v.gate for v in report.verdicts] == ["sync", "idle"]


# --- a humanoid: the G1 model by name ------------------------------------------------------------


def _g1(synthetic: Any, **pose: float) -> Path:
    from telerig.robots.models.g1 import UPPER_BODY_JOINTS

    q = np.array([pose.get(j, 0.0) for j in UPPER_BODY_JOINTS])

    def sent(t: np.ndarray) -> np.ndarray:
        out: np.ndarray = np.outer(synthetic.ramp(t, 0.5, 1.5) - synthetic.ramp(t, 2.5, 3.5), q)
        return out

    return synthetic.make(  # type: ignore[no-any-return]
        sent=sent,
        joints=UPPER_BODY_JOINTS,
        robot_type="mujoco_humanoid",
        model="g1",
        robot_joints=False,
        base_z=lambda t: np.full(t.size, 0.79),
    )


def test_g1_reaching_out_passes_collision_limits_and_fall(synthetic: Any) -> None:
    report = evaluate(_g1(synthetic, right_shoulder_pitch_joint=-0.8, right_elbow_joint=-0.5), DEFAULT)
    for gate in ("self_collision", "joint_limits", "fall"):
        verdict = report.verdict(gate)
        assert verdict is not None
        assert verdict.passed is True, verdict


def test_g1_arm_swung_into_its_torso_fails(synthetic: Any) -> None:
    v = _verdict(_g1(synthetic, right_shoulder_roll_joint=1.5), "self_collision")
    assert v.passed is False
    assert "'torso_link' and 'right_shoulder_yaw_link'" in v.detail
