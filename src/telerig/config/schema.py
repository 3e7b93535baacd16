"""Rig file schema: pydantic models for broker, stations, devices, robots, cameras, bindings, safety.

Component sections (devices, robots, cameras, retargeters) are open: each entry
has a ``type`` that selects its config model from :mod:`telerig.registry`, so a
third-party package can add a device type without touching this file.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, ClassVar, Literal

from pydantic import BaseModel, ConfigDict, Field, SerializeAsAny, field_validator, model_validator

from telerig.config.export import ExportDefaults
from telerig.config.latency import LatencyConfig
from telerig.config.priorities import PriorityConfig
from telerig.config.process import ProcessSettings
from telerig.config.qa import QaThresholds
from telerig.config.safety import FaultPolicy, RobotSafetyConfig
from telerig.ir.types import Handedness

if TYPE_CHECKING:
    from telerig.cameras.capture import Camera
    from telerig.cameras.mujoco_camera import FrameCallback
    from telerig.devices.base import Device
    from telerig.retarget.binding import BindContext, Bound
    from telerig.robots.base import RobotDriver

__all__ = [
    "DEFAULT_BUTTONS",
    "EpisodeControlConfig",
    "SessionCommand",
    "ValidationConfig",
    "AlignmentConfig",
    "BindingConfig",
    "BrokerConfig",
    "BrokerTlsConfig",
    "CameraConfig",
    "ComponentConfig",
    "DeviceConfig",
    "EmbeddedBrokerConfig",
    "ExternalBrokerConfig",
    "NodeConfig",
    "ObservationConfig",
    "PreviewConfig",
    "RecordingConfig",
    "RetargeterConfig",
    "RigConfig",
    "RuntimeConfig",
    "RobotConfig",
    "SafetyConfig",
    "StationConfig",
    "StorageConfig",
]

Identifier = Annotated[str, Field(pattern=r"^[A-Za-z0-9_.\-]+$", min_length=1, max_length=64)]
Rate = Annotated[float, Field(gt=0, le=10_000)]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ComponentConfig(_Model):
    """Base of every config selected by ``type`` through the registry."""

    type: str


class NodeConfig(ComponentConfig):
    """Base of components that run on a station under an id."""

    id: Identifier
    station: Identifier = "station0"


class DeviceConfig(NodeConfig):
    """Base of input device configs."""

    def build(self) -> Device:
        """Construct the device (no I/O until ``start``)."""
        raise NotImplementedError(f"{type(self).__name__} must implement build()")


class RobotConfig(NodeConfig):
    """Base of robot driver configs."""

    def build(self) -> RobotDriver:
        """Construct the driver (no I/O until ``connect``)."""
        raise NotImplementedError(f"{type(self).__name__} must implement build()")

    def control_rate(self) -> float:
        """The rate the runtime's control loop ticks at for this robot [Hz]: 100 unless the config
        has a ``control_rate_hz`` setting (its subclass then returns that)."""
        return 100.0


class PreviewConfig(_Model):
    """Low-rate JPEG previews of a camera, published for the dashboard (the MP4 keeps every frame)."""

    enabled: bool = True
    max_width: Annotated[int, Field(ge=16, le=1920)] = 320
    max_height: Annotated[int, Field(ge=16, le=1080)] = 240
    rate_hz: Annotated[float, Field(gt=0, le=30)] = 2.0


class ObservationConfig(_Model):
    """Low-resolution raw RGB frames for a policy on the camera's ``observation`` stream.

    Frames are resized to exactly ``width`` x ``height`` [px] (the policy's input size; the aspect
    is not kept) and taken on a grid of ``1 / rate_hz`` in capture time [Hz].
    """

    width: Annotated[int, Field(ge=8, le=512)] = 96
    height: Annotated[int, Field(ge=8, le=512)] = 96
    rate_hz: Annotated[float, Field(gt=0, le=60)] = 30.0


class CameraConfig(NodeConfig):
    """Base of camera configs."""

    width: Annotated[int, Field(ge=16, le=7680)] = 640
    height: Annotated[int, Field(ge=16, le=4320)] = 480
    fps: Annotated[float, Field(gt=0, le=240)] = 30.0
    preview: PreviewConfig = Field(default_factory=PreviewConfig)
    #: Frames for a policy (``observation`` stream); none unless set.
    observation: ObservationConfig | None = None
    #: Video codec: H.264 (fast, everywhere) or AV1 (SVT-AV1; what LeRobot datasets use, ~3x smaller).
    codec: Literal["h264", "av1"] = "h264"

    def build(self, on_frame: FrameCallback, *, robots: Mapping[str, RobotDriver] | None = None) -> Camera:
        """Construct the camera delivering frames to ``on_frame`` (no I/O until ``start``).

        ``robots``: the robots built in this process, by rig id (a simulated robot's scene camera
        renders its physics); a camera of the world ignores them.
        """
        raise NotImplementedError(f"{type(self).__name__} has no builder")

    @model_validator(mode="after")
    def _even_size(self) -> CameraConfig:
        if self.width % 2 or self.height % 2:
            raise ValueError(
                f"width and height must be even for H.264 (yuv420p), got {self.width}x{self.height}"
            )
        return self


class RetargeterConfig(ComponentConfig):
    """Base of retargeter configs (how a device part drives a robot part)."""

    #: The robot parts (a binding's ``target``) it drives, e.g. ``("arm",)``: checked when the rig
    #: loads, so ``telerig rig check`` refuses a binding the runtime could not bind. Empty: not declared
    #: (a plug-in's ``bind`` then checks the target at run time).
    targets: ClassVar[tuple[str, ...]] = ()

    def bind(self, context: BindContext) -> Bound:
        """The control-loop parts this binding gives its robot (see :mod:`telerig.retarget.binding`).

        Raises:
            ConfigError: the binding's target or robot cannot be driven by this retargeter.
        """
        from telerig.errors import ConfigError

        raise ConfigError(f"{context.where}: retargeter {self.type!r} cannot be bound by this runtime")


class EmbeddedBrokerConfig(_Model):
    """telerig starts Mosquitto itself on 127.0.0.1 (a free port unless ``port`` is set)."""

    type: Literal["embedded"] = "embedded"
    port: Annotated[int, Field(ge=0, le=65535)] = 0
    max_queued_messages: Annotated[int, Field(ge=1)] = 1000
    #: Largest message the broker passes [bytes] (default: telerig.bus.broker's, which says why).
    message_size_limit: Annotated[int, Field(ge=1024)] = 2 * 1024 * 1024


class BrokerTlsConfig(_Model):
    """How clients check an external broker over TLS (``mqtts://``), as PEM files.

    Attributes:
        ca_file: CA certificate(s) the broker's certificate must chain to; ``None``: the system's.
        cert_file: Client certificate, for a broker that requires one.
        key_file: Private key of ``cert_file``.
    """

    ca_file: Path | None = None
    cert_file: Path | None = None
    key_file: Path | None = None

    @model_validator(mode="after")
    def _key_with_cert(self) -> BrokerTlsConfig:
        if (self.cert_file is None) != (self.key_file is None):
            raise ValueError("cert_file and key_file go together (a client certificate and its key)")
        return self


class ExternalBrokerConfig(_Model):
    """An existing broker (Mosquitto, EMQX), e.g. ``mqtt://user:secret@broker.lab:1883`` or
    ``mqtts://broker.lab:8883`` with ``tls: {ca_file: lab-ca.pem}``."""

    type: Literal["external"] = "external"
    url: Annotated[str, Field(pattern=r"^mqtts?://")]
    tls: BrokerTlsConfig | None = None

    @model_validator(mode="after")
    def _tls_needs_mqtts(self) -> ExternalBrokerConfig:
        if self.tls is not None and not self.url.startswith("mqtts://"):
            raise ValueError(f"tls is set but url {self.url.split('@')[-1]!r} is not mqtts://; use mqtts://")
        return self


BrokerConfig = Annotated[EmbeddedBrokerConfig | ExternalBrokerConfig, Field(discriminator="type")]


class StationConfig(_Model):
    """A host that runs devices, robots, cameras and a recorder."""

    id: Identifier
    host: str = "localhost"


class AlignmentConfig(_Model):
    """Maps the operator frame onto the robot base frame (absolute alignment).

    ``p_robot = rotation * (scale * (p_operator - operator_origin)) + robot_origin``;
    orientations are rotated by ``rotation``.
    """

    rotation: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    operator_origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    robot_origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    scale: Annotated[float, Field(gt=0, le=100)] = 1.0

    @field_validator("rotation")
    @classmethod
    def _unit_quaternion(cls, q: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
        norm = sum(c * c for c in q) ** 0.5
        if abs(norm - 1.0) > 1e-3:
            raise ValueError(f"rotation must be a unit quaternion (w, x, y, z); its norm is {norm:.4f}")
        return q


class BindingConfig(_Model):
    """Which device part drives which robot part, through which retargeter.

    Several bindings may drive one robot part when their ``priority`` differs (a policy and an
    operator who takes over, :mod:`telerig.runtime.handover`): the highest-priority source that is
    engaged drives it. A source with ``takeover_button`` is engaged while that button is held
    (e.g. the relative-mode clutch, ``grip``); one without it (a policy) while its samples are fresh.
    """

    device: Identifier
    part: Identifier
    robot: Identifier
    target: Identifier
    retargeter: SerializeAsAny[RetargeterConfig]
    priority: Annotated[int, Field(ge=0, le=100)] = 0
    takeover_button: Annotated[str, Field(pattern=r"^[a-z][a-z0-9_]*$")] | None = None

    @field_validator("retargeter", mode="before")
    @classmethod
    def _resolve_retargeter(cls, value: Any) -> Any:
        from telerig.registry import RETARGETERS

        return RETARGETERS.parse_config(value, "retargeter")


class SafetyConfig(_Model):
    """Safety settings: the chain's limits and timeouts for every robot, per-robot guards, the fault policy.

    ``policy``: on a hardware fault or joint-limit violation of one robot, ``halt_all`` e-stops every
    robot of the rig, ``pause_affected`` only that one. ``robots`` adds per-robot workspace bounds,
    self-collision checking and a deadman button (see :class:`telerig.config.safety.RobotSafetyConfig`).
    """

    start_velocity_fraction: Annotated[float, Field(gt=0, le=1)] = 0.1
    start_ramp_s: Annotated[float, Field(ge=0, le=60)] = 3.0
    #: Input older than this holds the robot at its last command; a control tick this late after the
    #: previous one (a starved loop) resumes from the measured position at the start of the ramp [ms].
    hold_timeout_ms: Annotated[float, Field(gt=0, le=10_000)] = 100.0
    #: Input older than this stops the robot (commands its measured position) [ms].
    watchdog_timeout_ms: Annotated[float, Field(gt=0, le=10_000)] = 250.0
    velocity_scale: Annotated[float, Field(gt=0, le=1)] = 1.0
    policy: FaultPolicy = "halt_all"
    #: A measured position this far beyond a joint limit is a fault (e-stop) [rad].
    measured_tolerance_rad: Annotated[float, Field(ge=0, le=0.5)] = 0.05
    robots: dict[Identifier, RobotSafetyConfig] = Field(default_factory=dict)

    @model_validator(mode="after")
    def _hold_before_watchdog(self) -> SafetyConfig:
        if self.hold_timeout_ms > self.watchdog_timeout_ms:
            raise ValueError(
                f"hold_timeout_ms ({self.hold_timeout_ms}) must not exceed watchdog_timeout_ms "
                f"({self.watchdog_timeout_ms})"
            )
        return self


class RecordingConfig(_Model):
    """Where and what to record."""

    data_root: Path = Path("telerig-data")
    task: str = "pick and place the cube"
    operator: Identifier = "scripted"
    episode_duration_s: Annotated[float, Field(gt=0, le=3600)] = 10.0
    #: Delay [s] between arming an episode and its start on every station (the coordinator broadcasts
    #: now + lead so acquisition, control and logging start together); 5 s suits several hosts.
    start_lead_s: Annotated[float, Field(ge=0, le=60)] = 0.5
    episodes: Annotated[int, Field(ge=1, le=10_000)] = 3


class ValidationConfig(BaseModel):
    """Thresholds of the default validator (see :meth:`SampleValidator.default`)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    workspace_radius_m: Annotated[float, Field(gt=0, le=1000)] = 5.0
    quaternion_tolerance: Annotated[float, Field(gt=0, lt=1)] = 0.01
    max_linear_m_s: Annotated[float, Field(gt=0)] = 10.0
    max_angular_rad_s: Annotated[float, Field(gt=0)] = 20.0
    min_confidence: Annotated[float, Field(ge=0, le=1)] = 0.5
    max_gap_factor: Annotated[float, Field(gt=1)] = 5.0
    min_gap_s: Annotated[float, Field(ge=0)] = 0.05
    expected_period_s: Annotated[float, Field(gt=0)] | None = None
    max_speed_m_s: Annotated[float, Field(gt=0)] = 10.0
    jump_tolerance_m: Annotated[float, Field(ge=0)] = 0.02


class SessionCommand(StrEnum):
    """What the operator asks the session to do.

    Attributes:
        END_SESSION: End the active recording session (the episode is kept).
        RESET_AND_NEXT: Reset the robot to a safe pose so the operator can reposition, then start
            the next recording.
        RESTART_EPISODE: Discard the current episode and record it again from the start.
        STOP_COLLECTION: Stop collecting: discard the current episode, keep the earlier ones.
        STOP_EPISODE: End the current episode and keep it; the session goes on with the next.
        DISCARD_EPISODE: End the current episode and discard it; the session goes on with the next.
    """

    END_SESSION = "end_session"
    RESET_AND_NEXT = "reset_and_next"
    RESTART_EPISODE = "restart_episode"
    STOP_COLLECTION = "stop_collection"
    STOP_EPISODE = "stop_episode"
    DISCARD_EPISODE = "discard_episode"


#: The seed's mapping (Quest / Pico layout: A, B on the right controller, X, Y on the left).
DEFAULT_BUTTONS: dict[str, SessionCommand] = {
    "a": SessionCommand.END_SESSION,
    "b": SessionCommand.RESET_AND_NEXT,
    "x": SessionCommand.RESTART_EPISODE,
    "y": SessionCommand.STOP_COLLECTION,
}

_BUTTON = re.compile(r"^[a-z][a-z0-9_]*$")


class EpisodeControlConfig(BaseModel):
    """Which controller buttons issue which session commands.

    Attributes:
        buttons: Button name (as in ``ControllerState.buttons``, e.g. ``"a"``, ``"menu"``) → command;
            names are lower-cased. Order matters only when several bound buttons go down in one
            sample: the first in this mapping wins.
        device: Only this device's controllers issue commands; ``None`` = any device of the rig.
        hand: Only controllers of this hand issue commands; ``None`` = either hand.
        debounce_s: Presses within this time [s] of the previous command are ignored.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    device: Identifier | None = None
    buttons: dict[str, SessionCommand] = Field(default_factory=lambda: dict(DEFAULT_BUTTONS))
    hand: Handedness | None = None
    debounce_s: Annotated[float, Field(ge=0, le=10)] = 0.5

    @field_validator("buttons", mode="before")
    @classmethod
    def _names(cls, value: object) -> object:
        if not isinstance(value, dict):
            return value
        out: dict[object, object] = {}
        for name, command in value.items():
            key = name.strip().lower() if isinstance(name, str) else name
            if not isinstance(key, str) or not _BUTTON.match(key):
                raise ValueError(
                    f"button name {name!r} must be a lowercase identifier like 'a', 'menu' or 'thumbstick'"
                )
            if key in out:
                raise ValueError(f"button {key!r} is bound twice; bind each button to one command")
            out[key] = command
        return out


class StorageConfig(_Model):
    """Where episodes are indexed and archived (they are always written to ``recording.data_root`` first).

    Attributes:
        index: Index database: ``postgresql://user:pass@host/db`` shared by stations, or ``None``
            for SQLite at ``<data_root>/index.sqlite``.
        remote: Object storage for committed episodes, e.g. ``s3://bucket/prefix`` (credentials and
            region from the standard AWS environment / files), or a directory; ``None`` keeps them local.
        endpoint_url: S3-compatible endpoint (MinIO, Ceph, ...); ``None`` for AWS.
        upload: ``deferred`` decides from episode size and station load whether to upload now or
            later (never competing with a recording), ``now`` uploads at once, ``off`` never.
        bandwidth_mb_s: Upload bandwidth cap [MB/s]; ``None`` for no cap.
    """

    index: str | None = None
    remote: str | None = None
    endpoint_url: str | None = None
    upload: Literal["deferred", "now", "off"] = "deferred"
    bandwidth_mb_s: Annotated[float, Field(gt=0)] | None = None


class RuntimeConfig(_Model):
    """How a station runs its nodes.

    ``processes``: each robot runs in a child process with its control loop, the devices bound
    only to it and its simulated cameras, so its control ticks never wait for the station's
    interpreter lock (Python's GIL), held by the recorder's MQTT thread, previews and uploads, nor
    for another robot's; they talk over the broker as before. The demo rig runs this way (its
    rig file says what it measured).
    ``threads``: every node in the station's process (the default): one process to debug, a robot
    whose randomized task the station resets, drivers a test reaches into.
    """

    isolation: Literal["threads", "processes"] = "threads"
    #: With ``processes``: run each robot process under the kernel's round-robin real-time policy
    #: (``SCHED_RR``) at this priority (1-99), so its control loop and physics are not delayed
    #: behind ordinary processes on a busy host. Needs root or CAP_SYS_NICE (or an ``rtprio`` limit
    #: in /etc/security/limits.conf); without it the robots run at normal priority with a warning.
    realtime_priority: Annotated[int, Field(ge=1, le=99)] | None = None
    #: The control loops above rendering, encoding, previews, health and uploads (on by default).
    priorities: PriorityConfig = Field(default_factory=PriorityConfig)
    #: Keep the station's idle CPUs polling instead of halting while the rig runs, as real-time
    #: hosts do (``idle=poll``): a CPU woken from a halt starts the control thread sent to it late,
    #: by up to tens of milliseconds in a virtual machine (:mod:`telerig.runtime.idle_poll`). The
    #: CPUs then read 100 % busy and draw full power; off by default.
    idle_poll: bool = False

    @model_validator(mode="after")
    def _priority_needs_processes(self) -> RuntimeConfig:
        if self.realtime_priority is not None and self.isolation != "processes":
            raise ValueError("realtime_priority applies to robot processes: set isolation: processes")
        return self


class RigConfig(_Model):
    """A whole rig: what runs where, and how it is wired."""

    name: Identifier
    broker: BrokerConfig = Field(default_factory=EmbeddedBrokerConfig)
    stations: list[StationConfig] = Field(default_factory=lambda: [StationConfig(id="station0")])
    # SerializeAsAny: model_dump writes each component's own fields (its type's), not just the base's.
    devices: list[SerializeAsAny[DeviceConfig]]
    robots: list[SerializeAsAny[RobotConfig]]
    cameras: list[SerializeAsAny[CameraConfig]] = Field(default_factory=list)
    bindings: list[BindingConfig]
    safety: SafetyConfig = Field(default_factory=SafetyConfig)
    recording: RecordingConfig = Field(default_factory=RecordingConfig)
    validation: ValidationConfig = Field(default_factory=ValidationConfig)
    episode_control: EpisodeControlConfig | None = None
    storage: StorageConfig = Field(default_factory=StorageConfig)
    runtime: RuntimeConfig = Field(default_factory=RuntimeConfig)
    #: Quality-gate thresholds (:mod:`telerig.qa`), run on every committed episode.
    qa: QaThresholds = Field(default_factory=QaThresholds)
    #: How ``telerig export --rig`` resamples this rig's episodes (its options override these).
    export: ExportDefaults = Field(default_factory=ExportDefaults)
    #: The annotation pipeline's stage settings (``telerig process --rig``; issue 15).
    process: ProcessSettings = Field(default_factory=ProcessSettings)
    #: p99 latency budgets per stage of the operator loop (issue 17), shown in the operator view.
    latency: LatencyConfig = Field(default_factory=LatencyConfig)

    @field_validator("devices", mode="before")
    @classmethod
    def _resolve_devices(cls, value: Any) -> Any:
        from telerig.registry import DEVICES

        return _resolve_list(value, DEVICES, "devices")

    @field_validator("robots", mode="before")
    @classmethod
    def _resolve_robots(cls, value: Any) -> Any:
        from telerig.registry import ROBOTS

        return _resolve_list(value, ROBOTS, "robots")

    @field_validator("cameras", mode="before")
    @classmethod
    def _resolve_cameras(cls, value: Any) -> Any:
        from telerig.registry import CAMERAS

        return _resolve_list(value, CAMERAS, "cameras")

    @model_validator(mode="after")
    def _cross_references(self) -> RigConfig:
        stations = _unique_ids("stations", [s.id for s in self.stations])
        devices = _unique_ids("devices", [d.id for d in self.devices])
        robots = _unique_ids("robots", [r.id for r in self.robots])
        _unique_ids("cameras", [c.id for c in self.cameras])
        sections: tuple[tuple[str, Sequence[NodeConfig]], ...] = (
            ("devices", self.devices),
            ("robots", self.robots),
            ("cameras", self.cameras),
        )
        for section, items in sections:
            for i, item in enumerate(items):
                _check_ref(f"{section}[{i}].station", item.station, stations)
        if self.episode_control is not None and self.episode_control.device is not None:
            _check_ref("episode_control.device", self.episode_control.device, devices)
        for i, camera in enumerate(self.cameras):
            robot = getattr(camera, "robot", None)
            if robot is not None:
                _check_ref(f"cameras[{i}].robot", robot, robots)
        seen: set[tuple[str, str, int]] = set()
        for robot_id, robot_safety in self.safety.robots.items():
            _check_ref(f"safety.robots.{robot_id}", robot_id, robots)
            if robot_safety.deadman is not None:
                device = robot_safety.deadman.stream.split("/", 1)[0]
                _check_ref(f"safety.robots.{robot_id}.deadman.stream", device, devices)
        for i, binding in enumerate(self.bindings):
            _check_ref(f"bindings[{i}].device", binding.device, devices)
            _check_ref(f"bindings[{i}].robot", binding.robot, robots)
            _check_target(f"bindings[{i}].target", binding)
            key = (binding.robot, binding.target, binding.priority)
            if key in seen:
                raise ValueError(
                    f"bindings[{i}]: robot {binding.robot!r} part {binding.target!r} is driven by two "
                    "bindings of the same priority; give each robot part one binding, or a higher "
                    "priority to the source that takes over"
                )
            seen.add(key)
        return self

    def with_isolation(
        self, isolation: Literal["threads", "processes"], realtime_priority: int | None = None
    ) -> RigConfig:
        """This rig with its robots run as ``isolation`` says (``runtime.isolation`` and
        ``runtime.realtime_priority``; the control priorities are kept), validated: a priority
        outside 1..99, or one with ``threads``, raises pydantic's ``ValidationError``."""
        return self.with_runtime(isolation=isolation, realtime_priority=realtime_priority)

    def with_runtime(self, **changes: Any) -> RigConfig:
        """This rig with the ``runtime`` fields in ``changes`` replaced, validated: an unknown field
        or a value out of range raises pydantic's ``ValidationError``. ``priorities`` given as a
        mapping updates the rig's priorities field by field, e.g.
        ``rig.with_runtime(idle_poll=True, priorities={"control_realtime": 11})``."""
        fields = self.runtime.model_dump()
        if isinstance(changes.get("priorities"), Mapping):
            changes["priorities"] = {**fields["priorities"], **changes["priorities"]}
        return self.model_copy(update={"runtime": RuntimeConfig.model_validate({**fields, **changes})})


def _resolve_list(value: Any, registry: Any, section: str) -> Any:
    if not isinstance(value, list):
        return value
    return [registry.parse_config(item, f"{section}[{i}]") for i, item in enumerate(value)]


def _unique_ids(section: str, ids: list[str]) -> set[str]:
    seen: set[str] = set()
    for item in ids:
        if item in seen:
            raise ValueError(f"{section}: id {item!r} is used twice; ids must be unique")
        seen.add(item)
    return seen


def _check_ref(field: str, value: str, valid: set[str]) -> None:
    if value not in valid:
        raise ValueError(
            f"{field}: {value!r} does not exist. Available: {', '.join(sorted(valid)) or 'none'}"
        )


def _check_target(field: str, binding: BindingConfig) -> None:
    valid = type(binding.retargeter).targets
    if not valid or binding.target in valid:
        return
    from telerig.registry import RETARGETERS

    by_target: dict[str, list[str]] = {}
    for name in RETARGETERS.names():
        for target in RETARGETERS.get(name).targets:
            by_target.setdefault(target, []).append(name)
    drivers = "; ".join(f"{target}: {', '.join(names)}" for target, names in sorted(by_target.items()))
    raise ValueError(
        f"{field}: retargeter {binding.retargeter.type!r} cannot drive target {binding.target!r}. "
        f"Valid: {', '.join(valid)} (targets and the retargeters that drive them: {drivers})"
    )
