"""The ``extra`` section of an episode manifest, typed: written by the runtime, read by the index,
repair and exports through one model, so a field cannot be written under one key and read under
another (issue 11: the index read the fingerprint as a string under a key nobody wrote).

Unknown keys are kept (``extra="allow"``): stages add their own (``repair``, ``quality``...), and a
newer writer's fields survive an older reader.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, JsonValue, ValidationError, model_validator

from telerig.errors import RecordingError
from telerig.store.episodes import EpisodeManifest

__all__ = [
    "CameraRecord",
    "EpisodeExtra",
    "FingerprintRecord",
    "OutageRecord",
    "RobotJointsRecord",
    "SafetyEventRecord",
]


class FingerprintRecord(BaseModel):
    """The rig fingerprint (:class:`~telerig.store.fingerprint.RigFingerprint`): its ``digest``
    (16 hex chars) and the ``components`` it hashes."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    digest: str = Field(min_length=1, max_length=200)
    components: dict[str, str] = Field(default_factory=dict)


class CameraRecord(BaseModel):
    """One camera's video: ``file`` relative to the episode, ``frames`` written, ``dropped`` (refused
    by the encoder's full queue), and the camera's configured ``width`` x ``height`` [px], ``fps``
    [Hz] and ``codec`` (``h264``, ``av1``); and what the camera itself counted while the episode
    recorded: ``skipped`` (frames lost before the encoder: deadlines a simulated camera woke too late
    for or snapshots its renderer fell behind on, frames a device dropped), ``late`` (captured or
    delivered late) and ``callback_errors``. Each is ``None`` in episodes recorded before it was."""

    model_config = ConfigDict(frozen=True, extra="allow")

    file: str
    frames: int = 0
    dropped: int = 0
    width: int | None = Field(default=None, gt=0)
    height: int | None = Field(default=None, gt=0)
    fps: float | None = Field(default=None, gt=0)
    codec: str | None = None
    skipped: int | None = Field(default=None, ge=0)
    late: int | None = Field(default=None, ge=0)
    callback_errors: int | None = Field(default=None, ge=0)


class RobotJointsRecord(BaseModel):
    """One robot's commanded joints and limits as its driver reported them (what exports and gates
    read: joint order, normalization bounds, limit checks).

    Attributes:
        type: The driver's config ``type``, e.g. ``mujoco_arm``, ``ur_rtde``.
        model: The robot model it names (``ur5e_robotiq85``, ``g1``...), or ``None``.
        joints: Joint names in driver order (the order of every joint stream). Length n.
        lower: Lower position limits [rad] (or [m] for a prismatic joint); ``None`` where the joint
            is unbounded (e.g. a mobile base's x, y, yaw: JSON has no infinity). Length n.
        upper: Upper position limits, same units; ``None`` where unbounded. Length n.
        velocity: Speed limits [rad/s] or [m/s]. Length n.
        acceleration: Acceleration limits [rad/s^2] or [m/s^2]. Length n.
        gripper: Whether the robot has a gripper (its opening is the ``gripper_state`` stream).
        standing_height_m: Reference height [m] of a humanoid's pelvis or a mobile base above the
            floor when standing (the fall gate's reference); ``None`` for fixed robots.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    type: str
    model: str | None = None
    joints: list[str]
    lower: list[float | None]
    upper: list[float | None]
    velocity: list[float]
    acceleration: list[float]
    gripper: bool = False
    standing_height_m: float | None = Field(default=None, gt=0)

    @model_validator(mode="after")
    def _one_value_per_joint(self) -> RobotJointsRecord:
        n = len(self.joints)
        for name in ("lower", "upper", "velocity", "acceleration"):
            if len(getattr(self, name)) != n:
                raise ValueError(f"{name} has {len(getattr(self, name))} values for {n} joints")
        return self


class OutageRecord(BaseModel):
    """A restart of the embedded broker: down and back up, common clock [ns]."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    down_ns: int
    up_ns: int


class SafetyEventRecord(BaseModel):
    """One safety event of the episode: a fault, an e-stop, a reset or a takeover.

    Attributes:
        t_ns: When it happened, common clock [ns].
        robot: The robot it concerns (``None``: the whole rig, e.g. a takeover of an input).
        code: What happened, e.g. ``driver_fault``, ``operator_estop``, ``reset``.
        reason: The one-line reason.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    t_ns: int
    robot: str | None = None
    code: str
    reason: str = ""


class EpisodeExtra(BaseModel):
    """What the runtime records about an episode beyond the manifest's own fields.

    Attributes:
        fingerprint: The rig fingerprint (what makes episodes of one dataset compatible).
        station: The station that recorded it.
        session_id: The session it belongs to.
        robots: The robot models of the rig.
        robot_joints: Robot id → its joints, limits, gripper and standing height, from its driver.
        outcome: The operator's success/failure mark.
        quality: A quality score in [0, 1], once scored.
        streams: Per-stream statistics (name, expected and measured rate, messages, drops, gaps).
        cameras: Camera id → its video.
        latency_ms: Input-to-actuation latency statistics [ms].
        safety_events: Robot → safety event code → count, within this episode only.
        safety_log: Every fault, e-stop, reset and takeover of this episode, in time order.
        input_rejected: Robot → reason → input samples its control node's gate rejected within this
            episode (non-finite, out of range, bad quaternion, future/stale stamp, out of order).
        tick_faults: Robot → control ticks that raised within this episode (each a ``driver_fault``).
        missing_streams: Bound device and robot streams that delivered nothing (topic → the
            address the device waited on, or ``""``); an episode with any is ``incomplete``.
        broker_outages: Restarts of the embedded broker during the episode.
        clock: The station's clock estimate.
        malformed_messages: Topic → messages dropped as malformed.
        samples_before_start: Samples that arrived during the episode but were captured more than a
            second before it started (the last episode's tail, reaching a station that receives its
            streams late), left out of its log.
        health: The health monitor's summary.
        alignment: The alignment-error report against the camera frames.
        priorities: Role (``control``, ``work``, ``render``) → the CPU priority its threads got in
            the station's process, e.g. ``SCHED_BATCH nice 10`` (:mod:`telerig.priority`).
        task: A randomized task's episode (:mod:`telerig.runtime.task`): robot, seed, what was drawn
            (cube pose, target zone), the scene's final check (``success``, ``reason``, values)
            and ``time_to_success_s``.
        instructions: The operator instructions of the episode (seed 002's metric, counted from its
            MCAP by :mod:`telerig.voice.instructions`; also its ``instructions.json``): ``total``,
            ``by_group``, ``rejected``, ``malformed`` and the reach planner's ``reaches``,
            ``reach_manual_instructions`` and ``reach_eta``.
    """

    model_config = ConfigDict(frozen=True, extra="allow")

    fingerprint: FingerprintRecord | None = None
    station: str | None = None
    session_id: str | None = None
    robots: list[str] = Field(default_factory=list)
    robot_joints: dict[str, RobotJointsRecord] = Field(default_factory=dict)
    outcome: Literal["success", "failure"] | None = None
    quality: float | None = Field(default=None, ge=0.0, le=1.0)
    streams: list[dict[str, JsonValue]] = Field(default_factory=list)
    cameras: dict[str, CameraRecord] = Field(default_factory=dict)
    latency_ms: dict[str, JsonValue] | None = None
    safety_events: dict[str, dict[str, int]] = Field(default_factory=dict)
    safety_log: list[SafetyEventRecord] = Field(default_factory=list)
    input_rejected: dict[str, dict[str, int]] = Field(default_factory=dict)
    tick_faults: dict[str, int] = Field(default_factory=dict)
    missing_streams: dict[str, str] = Field(default_factory=dict)
    broker_outages: list[OutageRecord] = Field(default_factory=list)
    clock: dict[str, JsonValue] = Field(default_factory=dict)
    malformed_messages: dict[str, int] = Field(default_factory=dict)
    samples_before_start: int = Field(default=0, ge=0)
    health: JsonValue = None
    alignment: JsonValue = None
    priorities: dict[str, str] = Field(default_factory=dict)
    task: dict[str, JsonValue] | None = None
    instructions: dict[str, JsonValue] | None = None

    @classmethod
    def of(cls, manifest: EpisodeManifest) -> EpisodeExtra:
        """The typed ``extra`` of ``manifest``.

        Raises:
            RecordingError: One line naming the episode and the field that does not fit.
        """
        try:
            return cls.model_validate(manifest.extra)
        except ValidationError as exc:
            first = exc.errors()[0]
            where = ".".join(str(p) for p in first["loc"]) or "extra"
            raise RecordingError(
                f"episode {manifest.id}: manifest extra.{where}: {first['msg']}; "
                "was it written by this version of telerig?"
            ) from None

    def to_json(self) -> dict[str, JsonValue]:
        """JSON values for :meth:`EpisodeDraft.commit` / ``abandon`` (the fields that were set)."""
        data: dict[str, JsonValue] = self.model_dump(mode="json", exclude_unset=True)
        return data
