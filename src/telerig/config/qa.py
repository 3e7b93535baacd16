"""Quality-gate thresholds of a rig file (``qa:``): what makes a recorded episode fit for training.

Data only; :mod:`telerig.qa` runs the gates with them. Every threshold is a value a person can
check against a plot of the episode: heights as a fraction of standing height, limits as a
fraction beyond the robot model's, forces in newtons, times in seconds or milliseconds.
"""

from __future__ import annotations

import typing
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

__all__ = ["GATES", "GateName", "QaThresholds", "ScoreWeights"]

#: The quality gates, in the order they run and are reported.
GateName = Literal[
    "fall",
    "self_collision",
    "joint_limits",
    "force_spike",
    "sync",
    "teleop_faults",
    "calibration_drift",
    "idle",
]
GATES: tuple[GateName, ...] = typing.get_args(GateName)


class ScoreWeights(BaseModel):
    """Weights of the episode quality score's components (:func:`telerig.qa.score.score`) [1].

    The score is ``sum(w_i * s_i) / sum(w_i)`` over the components that could be measured; a
    component without data (no success label, no task median, no recorded motion) gives its weight
    to the others. Only ratios matter. Defaults: the success label weighs most (a failed
    demonstration is the worst one to imitate); idle time, tracking error and smoothness equal;
    completion time least, since a careful operator may be slow on purpose.

    Attributes:
        smoothness: Path smoothness (normalized integrated squared jerk of the sent joint commands).
        completion_time: Duration relative to the task's median duration.
        idle: Fraction of frames without motion (the idle gate's definition).
        tracking: IK residual, or |sent - measured| joint error where no residual is recorded.
        success: The operator's success / failure label.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    smoothness: Annotated[float, Field(ge=0, le=1000)] = 0.2
    completion_time: Annotated[float, Field(ge=0, le=1000)] = 0.15
    idle: Annotated[float, Field(ge=0, le=1000)] = 0.2
    tracking: Annotated[float, Field(ge=0, le=1000)] = 0.2
    success: Annotated[float, Field(ge=0, le=1000)] = 0.25

    @model_validator(mode="after")
    def _some_weight(self) -> ScoreWeights:
        if self.smoothness + self.completion_time + self.idle + self.tracking + self.success <= 0:
            raise ValueError("score weights are all 0; give at least one component a weight > 0")
        return self


class QaThresholds(BaseModel):
    """Thresholds of the quality gates run on every committed episode (issue 13 defaults).

    Attributes:
        after_commit: Run the gates (and the score) in the station's background after each
            commit; ``telerig qa`` runs them on demand either way.
        while_recording: What the gate process does while an episode records. ``idle`` (the
            default): it runs under ``SCHED_IDLE`` throughout, on CPU time nothing else of the
            host wants, so a station recording back to back keeps its verdicts coming.
            ``pause``: it is stopped (``SIGSTOP``) until the episode ends; no interference at
            all, but a station that records back to back checks nothing (the hour-long soak of
            2026-11-27: 0 verdicts after 128 episodes). Off Linux both run it at its niceness.
        gates: The gates that run; a gate left out is not evaluated (no verdict). Default: all.
        fall_height_fraction: Fall: the pelvis (humanoid) or base (mobile robot) is lower than this
            fraction of its standing height [1].
        joint_limit_margin: Joint limits: a measured position beyond a position limit by more than
            this fraction of the joint's range, or a measured speed above ``(1 + margin)`` times
            its velocity limit, fails [1].
        force_spike_n: Force spike: largest allowed |force| at the wrist F/T sensor [N]. 150 N is
            the default stop force of a UR e-Series safety system and the ISO/TS 15066
            quasi-static contact limit for a hand; a UR5e lifting its rated 5 kg with a 0.9 kg
            Robotiq gripper reads about 58 N, so only a crash or a pinch gets there.
        torque_spike_nm: Force spike: largest allowed |torque| at the wrist F/T sensor [N m]. 20 N m
            is twice the static moment of a 5 kg payload held 0.2 m off the flange (9.8 N m),
            below the 28 N m a UR5e wrist motor gives.
        max_missing_fraction: Sync: a stream that lost more than this fraction of its expected
            samples fails [1].
        max_gap_ms: Sync: a stream with a gap between two samples longer than this fails [ms]; a
            stream too slow for it (under 30 Hz at 50 ms) fails on a gap over 1.5 sample periods.
        alignment_tolerance_ms: Sync: a camera frame whose nearest sample of a stream is farther
            than this and than the stream's own median sample interval misses that stream [ms]
            (a 100 Hz stream is up to 5 ms from a frame by its rate alone); ``None`` uses the
            tolerance of the recorder's alignment report. The gate fails when a stream misses
            more than ``max_missing_fraction`` of the frames.
        residual_flag_s: Teleoperation faults: the IK residual flagged (target out of reach or
            ill-conditioned) without a break for longer than this fails [s]. A brief flag (a
            target crossing the workspace edge) is normal; half a second means the robot did not
            follow the operator.
        drift_rad: Calibration drift: largest allowed persistent offset between sent and measured
            joint position [rad]: the median of (sent - measured) over the frames where that
            joint is still (speed below ``idle_velocity_rad_s``), so tracking lag during motion
            does not count. 0.05 rad (2.9 deg, 2.5 cm at a 0.5 m reach) is the safety chain's
            measured-position tolerance; a 17 deg (0.30 rad) offset fails six times over, a UR5e
            servo holding still in simulation sits within 0.01 rad.
        idle_velocity_rad_s: Idle: a frame is idle when every joint moves slower than this
            [rad/s] (or [m/s] for a prismatic joint) and no gripper moves faster than
            ``idle_gripper_per_s``. 0.05 rad/s is 2.5 cm/s at a 0.5 m reach: slower than a careful
            approach, faster than a hand held still drifts.
        idle_gripper_per_s: Idle: a gripper command changing faster than this fraction of its full
            stroke per second is motion [1/s].
        idle_max_fraction: Idle: an episode with more idle time than this fraction fails [1]. 0.6
            lets an episode of 10 s spend 2 s getting ready, 2 s at the end and 2 s in pauses.
        idle_min_pause_s: Idle: an idle stretch inside the episode shorter than this is not a pause
            exports trim (a grasp settling) [s]; heads and tails are trimmable at any length.
        collision_rate_hz: Self-collision: the rate the recorded joint states are replayed at
            through the collision model [Hz]. 50 Hz (20 ms) is above the 10-30 Hz bandwidth of
            teleoperated motion, so a contact lasting one control-relevant interval is seen.
        score_weights: Weights of the quality score's components (:class:`ScoreWeights`).
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    after_commit: bool = True
    while_recording: Literal["idle", "pause"] = "idle"
    gates: tuple[GateName, ...] = GATES
    fall_height_fraction: Annotated[float, Field(gt=0, lt=1)] = 0.5
    joint_limit_margin: Annotated[float, Field(ge=0, le=1)] = 0.05
    force_spike_n: Annotated[float, Field(gt=0, le=100_000)] = 150.0
    torque_spike_nm: Annotated[float, Field(gt=0, le=10_000)] = 20.0
    max_missing_fraction: Annotated[float, Field(ge=0, le=1)] = 0.02
    max_gap_ms: Annotated[float, Field(gt=0, le=60_000)] = 50.0
    alignment_tolerance_ms: Annotated[float, Field(gt=0, le=60_000)] | None = None
    residual_flag_s: Annotated[float, Field(ge=0, le=3600)] = 0.5
    drift_rad: Annotated[float, Field(gt=0, le=3.15)] = 0.05
    idle_velocity_rad_s: Annotated[float, Field(gt=0, le=100)] = 0.05
    idle_gripper_per_s: Annotated[float, Field(gt=0, le=100)] = 0.1
    idle_max_fraction: Annotated[float, Field(ge=0, le=1)] = 0.6
    idle_min_pause_s: Annotated[float, Field(ge=0, le=3600)] = 1.0
    collision_rate_hz: Annotated[float, Field(gt=0, le=10_000)] = 50.0
    score_weights: ScoreWeights = Field(default_factory=ScoreWeights)

    @field_validator("gates")
    @classmethod
    def _no_repeats(cls, value: tuple[GateName, ...]) -> tuple[GateName, ...]:
        repeated = sorted({g for g in value if value.count(g) > 1})
        if repeated:
            raise ValueError(f"gate(s) listed twice: {', '.join(repeated)}")
        return value
