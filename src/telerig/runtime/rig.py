"""Rig runtime: builds every node of one station of a rig from its config and records episodes.

All nodes of the station run in one process, each with its own bus client, talking
through the broker exactly as separate processes would. The rig's first station
coordinates the session (and runs the embedded broker); every other station follows
it from its own host (:meth:`RigRuntime.follow_episode`), records its own nodes into
its own data root under the coordinator's episode ids, with times in the
coordinator's clock.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import queue
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from pydantic import JsonValue

from telerig.bus.base import Message
from telerig.bus.broker import MosquittoBroker
from telerig.bus.mqtt import MqttBus
from telerig.bus.topics import Topic, qos_for
from telerig.cameras.capture import Camera
from telerig.cameras.config import MujocoCameraConfig
from telerig.cameras.encoder import EncodeResult
from telerig.cameras.mujoco_camera import FrameCallback, MujocoCamera
from telerig.config.schema import (
    CameraConfig,
    DeviceConfig,
    EmbeddedBrokerConfig,
    EpisodeControlConfig,
    NodeConfig,
    RigConfig,
    RobotConfig,
    SessionCommand,
)
from telerig.devices.validate import SampleValidator
from telerig.errors import BusError, ConfigError, RecordingError, SessionError, TelerigError, WireError
from telerig.ir import wire
from telerig.ir.types import ControllerState, now_ns
from telerig.record.recorder import Recorder
from telerig.retarget.binding import BindContext
from telerig.robots.base import RobotDriver
from telerig.robots.sim.arm import MujocoArm, arm_kinematics_of
from telerig.robots.sim.gripper import MujocoGripper
from telerig.runtime import streams
from telerig.runtime.camera_node import CameraFactory, CameraNode
from telerig.runtime.control_node import (
    AidBinding,
    BaseBinding,
    ControlNode,
    DeadmanBinding,
    GripperBinding,
    JointsBinding,
)
from telerig.runtime.device_node import DeviceNode
from telerig.runtime.episode_control import EpisodeController
from telerig.runtime.metrics import LatencySummary, LatencyTracker, StreamSummary
from telerig.runtime.realtime import keep_heap, release_heap
from telerig.runtime.robot_host import RobotHost, halt_publisher, listen_for_halts, plan_hosts
from telerig.runtime.session import Coordinator, SessionState, SessionStatus, StationAgent
from telerig.safety import (
    ConfigurationGuard,
    Deadman,
    RobotSafetyConfig,
    SafetyAlerts,
    SafetyChain,
    SafetySupervisor,
    arm_guard,
)
from telerig.safety.commands import SafetyCommandListener
from telerig.store.episodes import EpisodeManifest, EpisodeStore
from telerig.store.fingerprint import MANIFEST_KEY, check_compatible, rig_fingerprint
from telerig.store.index import EpisodeIndex
from telerig.store.remote import RemoteConfig, open_store
from telerig.store.upload import EpisodeUploader, RateLimiter, UploadQueue, UploadResult

__all__ = ["EpisodeResult", "ProgressCallback", "RigRuntime"]

log = logging.getLogger(__name__)

#: Called with (seconds elapsed, seconds total) while an episode runs; total is ``inf`` while a
#: following station records until the coordinator stops the episode.
ProgressCallback = Callable[[float, float], None]

_OnStation = TypeVar("_OnStation", bound=NodeConfig)


@dataclass(frozen=True, slots=True)
class EpisodeResult:
    """What one recorded episode produced.

    Attributes:
        status: ``complete`` (committed) or ``incomplete`` (discarded by the operator).
        command: The operator's session command that ended the episode early, if any.
    """

    episode_id: str
    status: str
    path: Path
    duration_s: float
    streams: list[StreamSummary]
    latency: LatencySummary
    camera_frames: dict[str, int] = field(default_factory=dict)
    command: SessionCommand | None = None


class RigRuntime:
    """Owns the broker, bus clients, robots, devices, cameras, control nodes and the recorder.

    Use as a context manager; ``close()`` is idempotent and always leaves the
    robots stopped and no child process behind.

    Args:
        config: The validated rig.
        data_root: Where episodes go; the rig's ``recording.data_root`` when None.
        switch_interval_s: Python's GIL switch interval while the rig runs [s], restored on
            close; None leaves it alone. The default 5 ms lets a busy thread (recorder,
            encoder feed) delay a woken control thread by up to 5 ms; 1 ms bounds that.
        station: Which station of the rig this process runs; the first (the coordinator) when None.
        broker_url: Broker to use instead of the rig's; a station other than the first needs it
            when the rig embeds its broker (the coordinator's host runs it).

    Raises:
        ConfigError: ``station`` is not in the rig, or a following station has no broker to reach.
    """

    def __init__(
        self,
        config: RigConfig,
        *,
        data_root: Path | None = None,
        switch_interval_s: float | None = 0.001,
        station: str | None = None,
        broker_url: str | None = None,
    ) -> None:
        stations = [s.id for s in config.stations]
        self.station_id = stations[0] if station is None else station
        if self.station_id not in stations:
            raise ConfigError(
                f"station {station!r} is not in rig {config.name!r}. Valid: {', '.join(stations)}"
            )
        #: Whether this station runs the session coordinator (the rig's first station does).
        self.coordinating = self.station_id == stations[0]
        if not self.coordinating and broker_url is None and isinstance(config.broker, EmbeddedBrokerConfig):
            raise ConfigError(
                f"station {self.station_id!r} follows {stations[0]!r}, which runs the rig's embedded broker: "
                "give its address with --broker mqtt://HOST:PORT"
            )
        self._broker_url = broker_url
        self.config = config
        self._switch_interval_s = switch_interval_s
        self._saved_switch_interval: float | None = None
        self.store = EpisodeStore(data_root or config.recording.data_root)
        self.robots: dict[str, RobotDriver] = {}
        self.devices: dict[str, DeviceNode] = {}
        self.controls: dict[str, ControlNode] = {}
        self.cameras: dict[str, CameraNode] = {}
        self._recorder: Recorder | None = None
        self._broker: MosquittoBroker | None = None
        self._buses: list[MqttBus] = []
        self._commands: queue.SimpleQueue[SessionCommand] = queue.SimpleQueue()
        self.index: EpisodeIndex | None = None
        self.coordinator: Coordinator | None = None
        self.station: StationAgent | None = None
        self._session_started = threading.Event()
        self._outcome: str | None = None
        self._watchdog_stop = threading.Event()
        self._broker_outages: list[tuple[int, int]] = []  # (down_ns, up_ns) of embedded broker restarts
        self._episode_running = False
        self.uploads: UploadQueue | None = None
        #: Robots running in child processes (``runtime.isolation: processes``), by robot id.
        self.hosts: dict[str, RobotHost] = {}
        #: This process's bus for node-level messages (safety alerts and halts); set by :meth:`open_nodes`.
        self.node_bus: MqttBus | None = None
        #: The fault reactions and halt policy over this station's robots (created by :meth:`open`).
        self.supervisor: SafetySupervisor | None = None
        #: The broker this station's nodes use, once open (the embedded one's port is chosen then).
        self.broker_url: str | None = None
        #: Applies operator e-stop/reset commands from the bus to this process's robots.
        self.safety_commands: SafetyCommandListener | None = None
        self._fingerprint = rig_fingerprint(config)
        self._closed = False

    def __enter__(self) -> RigRuntime:
        try:
            self.open()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def recorder(self) -> Recorder:
        if self._recorder is None:
            raise RuntimeError("open() the runtime first")
        return self._recorder

    def open(self) -> None:
        """Start the broker (if embedded), connect robots, start control nodes and the recorder."""
        cfg = self.config
        self._check_supported()
        # Refuse to silently mix episodes of an incompatible rig into one data root.
        check_compatible(self.store, self._fingerprint)
        self._open_storage()
        keep_heap()  # control loops and the recorder share this process: no heap trimming mid-tick
        if self._switch_interval_s is not None:
            self._saved_switch_interval = sys.getswitchinterval()
            sys.setswitchinterval(self._switch_interval_s)
        url = self.broker_url = self._start_broker()
        plans = plan_hosts(cfg, self.station_id) if cfg.runtime.isolation == "processes" else []
        for plan in plans:  # children start in parallel with the station's own nodes
            host = RobotHost(cfg, plan, url, station=self.station_id, data_root=self.store.root)
            self.hosts[plan.robot] = host
            host.start()
        hosted = {p.robot for p in plans} | {d for p in plans for d in p.devices}
        hosted |= {c for p in plans for c in p.cameras}
        self.open_nodes(
            url,
            robots=[r.id for r in self._local(cfg.robots) if r.id not in hosted],
            devices=[d.id for d in self._local(cfg.devices) if d.id not in hosted],
            cameras=[c.id for c in self._local(cfg.cameras) if c.id not in hosted],
        )
        for host in self.hosts.values():
            host.wait_ready()
        recorder_node = "recorder" if self.coordinating else f"recorder-{self.station_id}"
        self._recorder = Recorder(
            cfg.name,
            self._bus(url, recorder_node),
            self._expected_rates(),
            node=recorder_node,
            skip_nodes=self._remote_nodes(),
            to_session_ns=None if self.coordinating else self._to_session_ns,
        )
        if cfg.episode_control is not None and self.coordinating:
            self._listen_for_commands(cfg.episode_control)
        self._start_session()
        release_heap()  # the expensive first heap trim now, not inside a control tick

    def open_nodes(
        self, url: str, *, robots: Sequence[str], devices: Sequence[str], cameras: Sequence[str]
    ) -> None:
        """Build and start the named robots (with their control nodes), devices and cameras.

        :meth:`open` calls it for the station's own nodes; a robot host process calls it alone
        for its robot (see :mod:`telerig.runtime.robot_host`).
        """
        cfg = self.config
        for robot_cfg in (r for r in cfg.robots if r.id in robots):
            robot = robot_cfg.build()
            self.robots[robot_cfg.id] = robot
            robot.connect()
        for device_cfg in (d for d in cfg.devices if d.id in devices):
            self.devices[device_cfg.id] = DeviceNode(
                cfg.name,
                device_cfg.build(),
                self._bus(url, f"dev-{device_cfg.id}"),
                validator=SampleValidator.from_config(cfg.validation),
            )
        node = (self.robots and "-".join(sorted(self.robots))) or self.station_id
        self.node_bus = self._bus(url, f"safety-{node}")
        isolated = cfg.runtime.isolation == "processes"
        self.supervisor = SafetySupervisor(
            cfg.safety.policy,
            alerts=SafetyAlerts(self.node_bus, cfg.name, node=f"safety-{node}" if isolated else "safety"),
            on_halt_all=halt_publisher(self.node_bus, cfg.name) if isolated else None,
        )
        if isolated:
            listen_for_halts(self, cfg.name)
        self.safety_commands = SafetyCommandListener(self.node_bus, cfg.name, self.supervisor)
        for robot_cfg in (r for r in cfg.robots if r.id in robots):
            self.controls[robot_cfg.id] = self._build_control(robot_cfg, url)
        for camera_cfg in (c for c in cfg.cameras if c.id in cameras):
            camera = CameraNode(
                cfg.name, camera_cfg, self._camera_factory(camera_cfg), self._bus(url, f"cam-{camera_cfg.id}")
            )
            self.cameras[camera_cfg.id] = camera
            camera.start()  # before control starts: a simulated camera creates its GL context now
        for control in self.controls.values():
            control.start()

    def prepare_nodes(self) -> None:
        """Before an episode: reset the latency statistics and the simulated scenes' objects."""
        for control in self.controls.values():
            control.latency.reset()
        for robot in self.robots.values():
            if isinstance(robot, MujocoArm | MujocoGripper):
                robot.reset_objects()

    def close(self) -> None:
        """Stop devices and control, stop robots, disconnect, stop the broker. Idempotent."""
        if self._closed:
            return
        self._closed = True
        self._watchdog_stop.set()
        for host in self.hosts.values():
            _quietly(host.close)
        for device in self.devices.values():
            _quietly(device.stop)
        for camera in self.cameras.values():
            _quietly(camera.stop)
        for node in self.controls.values():
            _quietly(node.stop)
        for robot in self.robots.values():
            _quietly(robot.close)
        if self.station is not None:
            _quietly(self.station.close)
        if self.coordinator is not None:
            _quietly(self.coordinator.close)
        if self._recorder is not None:
            _quietly(self._recorder.close)
        if self.uploads is not None:
            _quietly(self.uploads.close)
        if self.index is not None:
            _quietly(self.index.close)
        for bus in self._buses:
            _quietly(bus.close)
        if self._broker is not None:
            _quietly(self._broker.stop)
        if self._saved_switch_interval is not None:
            sys.setswitchinterval(self._saved_switch_interval)

    def _local(self, components: Sequence[_OnStation]) -> list[_OnStation]:
        """The components of ``components`` that run on this station."""
        return [c for c in components if c.station == self.station_id]

    def _remote_nodes(self) -> set[str]:
        """Bus node names of the components other stations run (they record those themselves)."""
        cfg = self.config
        components: list[DeviceConfig | RobotConfig | CameraConfig] = [
            *cfg.devices,
            *cfg.robots,
            *cfg.cameras,
        ]
        return {c.id for c in components if c.station != self.station_id}

    def _to_session_ns(self, local_ns: int) -> int:
        """This station's clock → the coordinator's, by the current estimate [ns]."""
        station = self.station
        if station is None or not station.sync.sync.synced:
            return local_ns
        return station.sync.sync.to_coordinator(local_ns)

    def _start_session(self) -> None:
        """The first station coordinates the session (state machine, global start time, clock server);
        every station follows it (clock sync, start at the broadcast time)."""
        cfg = self.config
        bus = self.recorder.bus
        if self.coordinating:
            self.coordinator = Coordinator(
                bus,
                cfg.name,
                lead_s=cfg.recording.start_lead_s,
                task=cfg.recording.task,
                operator=cfg.recording.operator,
                on_status=[self._on_session_status],
            ).start()
        started = self._session_started
        self.station = StationAgent(
            bus,
            cfg.name,
            self.station_id,
            on_start=lambda status, report: started.set(),
            on_status=None if self.coordinating else self._on_session_status,
        ).start()
        if not self.station.sync.wait_synced(5.0):
            raise BusError("no clock-sync reply from the session coordinator within 5 s; is it running?")

    def _on_session_status(self, status: SessionStatus) -> None:
        """Commands from the CLI or web UI (on the coordinator's command topic) end the running episode."""
        if status.outcome is not None and self._episode_running:
            self._outcome = status.outcome  # "mark success/failure" from a UI, the CLI or a button
        if not self._episode_running or status.state is not SessionState.STOPPED:
            return
        if status.reason == "restart":
            self._commands.put(SessionCommand.RESTART_EPISODE)
        elif status.discarded:
            self._commands.put(SessionCommand.STOP_COLLECTION)
        else:
            self._commands.put(SessionCommand.END_SESSION)

    def _open_storage(self) -> None:
        """Open the episode index and, when the rig names object storage, the upload queue."""
        storage = self.config.storage
        self.index = EpisodeIndex.open(storage.index or self.store.root)
        if storage.remote is None or storage.upload == "off":
            return
        remote = open_store(RemoteConfig(url=storage.remote, endpoint_url=storage.endpoint_url))
        limiter = RateLimiter(storage.bandwidth_mb_s * 1e6) if storage.bandwidth_mb_s else None
        uploader = EpisodeUploader(remote, self.store.root / ".uploads", limiter=limiter)
        index = self.index

        def uploaded(result: UploadResult) -> None:
            index.set_location(result.episode_id, result.url)

        self.uploads = UploadQueue(self.store.root, uploader, on_uploaded=uploaded)
        self.uploads.start()

    def _listen_for_commands(self, config: EpisodeControlConfig) -> None:
        """Turn controller button presses into session commands (seed 000: A end, B next, X redo, Y stop)."""
        controller = EpisodeController(config)

        def on_message(message: Message) -> None:
            if not message.topic.endswith("_controller"):
                return
            try:
                sample = wire.decode(message.payload)
            except WireError:
                return  # the control node and recorder count malformed messages
            if isinstance(sample, ControllerState):
                command = controller.update(sample)
                if command is not None:
                    log.info("operator command: %s", command)
                    self._commands.put(command)

        self.recorder.bus.subscribe(Topic.pattern(self.config.name, config.device or "+"), on_message)

    def go_home(self, *, timeout_s: float = 15.0) -> bool:
        """Drive every arm to its home configuration through its safety chain (safe repositioning)."""
        here = all(node.go_home(timeout_s=timeout_s) for node in self.controls.values() if node.has_home)
        hosted = [
            bool(h.call("go_home", timeout_s, timeout_s=timeout_s + 10.0))
            for h in self.hosts.values()
            if h.info.get("has_home")
        ]
        return here and all(hosted)

    def _check_supported(self) -> None:
        for i, camera in enumerate(self.config.cameras):
            if not isinstance(camera, MujocoCameraConfig) and type(camera).build is CameraConfig.build:
                raise ConfigError(f"cameras[{i}].type: {camera.type!r} has no builder in this runtime")

    def _camera_factory(self, config: CameraConfig) -> CameraFactory:
        if not isinstance(config, MujocoCameraConfig):
            return config.build
        robot = self.robots[config.robot]
        if not isinstance(robot, MujocoArm | MujocoGripper):
            raise ConfigError(
                f"camera {config.id!r}: robot {config.robot!r} is not simulated; use a real camera type"
            )

        def make(on_frame: FrameCallback) -> Camera:
            return MujocoCamera(
                config.id,
                config.camera,
                robot.locked,
                on_frame=on_frame,
                width=config.width,
                height=config.height,
                fps=config.fps,
                geom_groups=robot.scene.visual_groups,
            )

        return make

    def _start_broker(self) -> str:
        broker = self.config.broker
        if self._broker_url is not None:
            return self._broker_url
        if isinstance(broker, EmbeddedBrokerConfig):
            self._broker = MosquittoBroker(port=broker.port, max_queued_messages=broker.max_queued_messages)
            self._broker.start()
            threading.Thread(target=self._watch_broker, name="broker-watchdog", daemon=True).start()
            return self._broker.url
        return broker.url

    def _watch_broker(self, period_s: float = 0.25) -> None:
        """Restart the embedded broker if it dies; the clients reconnect, the outage is recorded and alerted.

        Recording is local, so the episode goes on; the bus streams have a gap for the outage.
        """
        broker = self._broker
        while broker is not None and not self._watchdog_stop.wait(period_s):
            if broker.running or self._closed:
                continue
            down_ns = now_ns()
            log.warning("embedded broker died; restarting it on the same port")
            try:
                broker.restart()
            except TelerigError as exc:
                log.error("embedded broker could not be restarted: %s", exc)
                continue
            # When it first accepted a connection: the watchdog may get the CPU back later than the
            # clients that reconnected at once.
            up_ns = broker.listening_since_ns
            self._broker_outages.append((down_ns, up_ns))
            alert = {
                "code": "broker_restarted",
                "severity": "warning",
                "reason": "the embedded MQTT broker process died and was restarted",
                "suggested_action": "check the broker log and the machine's memory; bus streams have a gap",
                "active": False,
                "down_ns": down_ns,
                "up_ns": up_ns,
            }
            if self._recorder is not None:
                qos, retain = qos_for("alerts")
                topic = str(Topic(self.config.name, "broker", "alerts"))
                self._recorder.bus.publish(topic, json.dumps(alert).encode(), qos=qos, retain=retain)

    def _bus(self, url: str, node: str) -> MqttBus:
        bus = MqttBus(url, client_id=f"{self.config.name}-{node}")
        self._buses.append(bus)
        return bus.connect()

    def _build_control(self, robot_cfg: RobotConfig, url: str) -> ControlNode:
        """The robot's control node: every binding's retargeter config binds its parts, then the chain."""
        cfg = self.config
        robot = self.robots[robot_cfg.id]
        joints: JointsBinding | None = None
        gripper: GripperBinding | None = None
        base: BaseBinding | None = None
        aids: list[AidBinding] = []
        devices = tuple(d.id for d in cfg.devices)
        for binding in (b for b in cfg.bindings if b.robot == robot_cfg.id):
            context = BindContext(
                cfg.name, robot_cfg.id, robot, binding.target, binding.device, binding.part, devices
            )
            bound = binding.retargeter.bind(context)
            for part, taken in (("joints", joints), ("gripper", gripper), ("base", base)):
                if getattr(bound, part) is not None and taken is not None:
                    raise ConfigError(
                        f"{context.where}: robot {robot_cfg.id!r} already has its {part} bound to "
                        f"{taken.topic}; bind one device stream per robot part"
                    )
            if bound.joints is not None:
                joints = JointsBinding(context.topic, bound.joints)
            if bound.gripper is not None:
                if not robot.has_gripper:
                    raise ConfigError(
                        f"{context.where}: robot {robot_cfg.id!r} has no gripper for "
                        f"{binding.retargeter.type!r} to drive; remove the binding or configure the "
                        "robot's gripper"
                    )
                gripper = GripperBinding(context.topic, bound.gripper)
            if bound.base is not None:
                base = BaseBinding(context.topic, bound.base)
            aids.extend(AidBinding(topic, aid) for topic, aid in bound.aids)
        rate = _control_rate(robot_cfg)
        s = cfg.safety
        robot_safety = s.robots.get(robot_cfg.id, RobotSafetyConfig())
        deadman: DeadmanBinding | None = None
        if robot_safety.deadman is not None:
            d = robot_safety.deadman
            device, part = d.stream.split("/", 1)
            deadman = DeadmanBinding(
                str(Topic(cfg.name, device, part)), d.button, d.threshold, Deadman(d.signal_timeout_ms / 1e3)
            )
        chain = SafetyChain.default(
            robot.limits,
            velocity_fraction=s.velocity_scale,
            ramp_initial_fraction=s.start_velocity_fraction,
            ramp_duration_s=s.start_ramp_s,
            hold_timeout_s=s.hold_timeout_ms / 1e3,
            stop_timeout_s=s.watchdog_timeout_ms / 1e3,
            period_s=1.0 / rate,
            source_id=f"{robot_cfg.id}/safety",
            guard=self._guard(robot_cfg, robot, robot_safety),
            deadman=None if deadman is None else deadman.deadman,
            measured_tolerance=s.measured_tolerance_rad,
        )
        assert self.supervisor is not None
        bus = self._bus(url, f"ctl-{robot_cfg.id}")
        home = robot.scene.home if isinstance(robot, MujocoArm) else None
        return ControlNode(
            cfg.name,
            robot,
            self.supervisor.add(robot_cfg.id, robot, chain),
            bus,
            control_rate_hz=rate,
            joints=joints,
            gripper=gripper,
            home=home,
            aids=aids,
            base=base,
            deadman=deadman,
        )

    @staticmethod
    def _guard(
        robot_cfg: RobotConfig, robot: RobotDriver, config: RobotSafetyConfig
    ) -> ConfigurationGuard | None:
        """Workspace bounds and self-collision checks of an arm, on its kinematic model; None when off."""
        if config.workspace is None and not config.self_collision:
            return None
        kinematics = arm_kinematics_of(robot)
        if kinematics is None:
            raise ConfigError(
                f"safety.robots.{robot_cfg.id}: workspace and self_collision need an arm's kinematic "
                f"model; robot type {robot_cfg.type!r} has none yet (remove them or use a mujoco_arm)"
            )
        return arm_guard(kinematics, config)

    def _expected_rates(self) -> dict[str, float]:
        cfg = self.config
        rates: dict[str, float] = {}
        devices = {d.id: d for d in self._local(cfg.devices)}
        for binding in cfg.bindings:
            if (device := devices.get(binding.device)) is not None:
                topic = str(Topic(cfg.name, binding.device, binding.part))
                rates[topic] = float(getattr(device, "rate_hz", 0.0))
        input_rates = dict(rates)
        for robot_cfg in self._local(cfg.robots):
            rate = _control_rate(robot_cfg)

            def expect(stream: str, hz: float, robot: str = robot_cfg.id) -> None:
                rates[str(Topic(cfg.name, robot, stream))] = hz

            expect(streams.JOINT_SENT, rate)  # the loop ticks at the control rate, input or not
            expect(streams.JOINT_STATE, rate)
            if robot_cfg.id in self.controls:
                bound = self.controls[robot_cfg.id].bound_topics
            elif robot_cfg.id in self.hosts:
                bound = self.hosts[robot_cfg.id].info["bound_topics"]
            else:
                bound = {}
            # Retargeting runs per fresh input sample: the device's rate, at most the control rate.
            for part, requested_and_sent in (
                ("joints", (streams.JOINT_REQUESTED,)),
                ("gripper", (streams.GRIPPER_REQUESTED, streams.GRIPPER_SENT)),
                ("base", (streams.BASE_REQUESTED, streams.BASE_SENT)),
            ):
                source = bound.get(part)
                if source is None:
                    continue
                hz = min(rate, input_rates.get(source, 0.0) or rate) if part != "base" else rate
                for stream in requested_and_sent:
                    expect(stream, hz)
        for camera_cfg in self._local(cfg.cameras):
            rates[str(Topic(cfg.name, camera_cfg.id, streams.CAMERA_FRAMES))] = camera_cfg.fps
        return rates

    def run_episode(
        self, duration_s: float | None = None, *, progress: ProgressCallback | None = None
    ) -> EpisodeResult:
        """Record one episode: reset the scene objects, start devices and cameras, run, commit.

        The episode runs for ``duration_s`` or until the operator issues a session command
        (``episode_control`` in the rig): end-session and reset-and-next commit it (the latter
        then drives the arms home), restart and stop discard it to the incomplete partition.
        On any exception (Ctrl-C included) the devices stop, the robots hold, and the episode
        moves to the incomplete partition with the reason; earlier episodes are never touched.
        """
        cfg = self.config
        duration = duration_s if duration_s is not None else cfg.recording.episode_duration_s
        coordinator, station = self.coordinator, self.station
        if station is None:
            raise RuntimeError("open() the runtime first")
        if coordinator is None:
            raise RuntimeError(f"station {self.station_id!r} follows the session: use follow_episode()")
        self._prepare_episode()
        while not self._commands.empty():  # presses between episodes do not end the next one
            self._commands.get_nowait()
        self._session_started.clear()
        armed = coordinator.arm(task=cfg.recording.task, operator=cfg.recording.operator)
        if not self._session_started.wait(cfg.recording.start_lead_s + 5.0):
            coordinator.discard("start did not arrive")
            raise RecordingError(
                f"episode {armed.episode_id}: the session start did not arrive on this station"
            )
        assert armed.episode_id is not None
        return self._record(armed.episode_id, cfg.recording.task, cfg.recording.operator, duration, progress)

    def follow_episode(
        self, *, timeout_s: float | None = None, progress: ProgressCallback | None = None
    ) -> EpisodeResult | None:
        """On a following station: record the next episode the coordinator starts, until it ends.

        Waits up to ``timeout_s`` (forever when None) for the start; returns None when none came.
        The episode is filed under the coordinator's episode id, task and operator; it commits
        when the coordinator stops it and goes to the incomplete partition when it is discarded
        or restarted there.
        """
        station = self.station
        if station is None:
            raise RuntimeError("open() the runtime first")
        if self.coordinating:
            raise RuntimeError(f"station {self.station_id!r} coordinates the session: use run_episode()")
        self._prepare_episode()
        if not self._session_started.wait(timeout_s):
            return None
        self._session_started.clear()
        status = station.status
        if status is None or status.episode_id is None:
            raise RecordingError("the session started without an episode id; is the coordinator current?")
        cfg = self.config
        return self._record(
            status.episode_id,
            status.task or cfg.recording.task,
            status.operator or cfg.recording.operator,
            None,
            progress,
        )

    def _prepare_episode(self) -> None:
        self.prepare_nodes()
        for host in self.hosts.values():
            host.call("prepare")
        if self.uploads is not None:
            self.uploads.pause()  # uploads never compete with a recording
        self._outcome = None

    def _record(
        self,
        episode_id: str,
        task: str,
        operator: str,
        duration_s: float | None,
        progress: ProgressCallback | None,
    ) -> EpisodeResult:
        """Record the started episode until ``duration_s`` passes or a session command ends it."""
        cfg = self.config
        recorder = self.recorder
        coordinator, station = self.coordinator, self.station
        assert station is not None
        draft = self.store.begin(
            rig=cfg.name,
            task=task,
            operator=operator,
            extra={MANIFEST_KEY: self._fingerprint.to_json(), "station": self.station_id},
            episode_id=episode_id,
        )
        self._episode_running = True
        try:
            recorder.start(draft.mcap_path)
            clock = station.clock_record()
            recorder.add_metadata("clock", {k: str(v) for k, v in clock.items()})
            with self._cameras_recording(draft.camera_path) as videos:
                for device in self.devices.values():
                    device.start()
                for host in self.hosts.values():
                    host.call("start_devices")
                try:
                    command = _wait(duration_s, progress, self._commands)
                finally:
                    for host in self.hosts.values():
                        host.call("stop_devices")
                    for device in self.devices.values():
                        device.stop()
            stream_stats = recorder.stop()
            latency = self._latency()
            extra: dict[str, JsonValue] = {
                "streams": [_json(s) for s in stream_stats],
                "cameras": {
                    name: {"file": f"cameras/{name}.mp4", "frames": v.frames, "dropped": v.dropped}
                    for name, v in videos.items()
                },
                "latency_ms": _json(latency),
                "safety_events": {
                    **{rid: dict(node.safety.counts) for rid, node in self.controls.items()},
                    **{rid: host.call("safety_counts") for rid, host in self.hosts.items()},
                },
                "robots": [str(getattr(r, "model", r.type)) for r in cfg.robots],
                "session_id": station.status.session_id if station.status is not None else None,
                "outcome": self._outcome,
                "broker_outages": [
                    {"down_ns": d, "up_ns": u} for d, u in self._broker_outages if d >= draft.start_ns
                ],
                "clock": dict(clock),
                "malformed_messages": dict(recorder.malformed),
                "health": recorder.health.summary(),
            }
            if videos:
                try:
                    extra["alignment"] = recorder.capture_times.report()
                except RecordingError as exc:  # e.g. no camera frame was recorded
                    extra["alignment"] = {"error": str(exc)}
            self._episode_running = False
            discard = command in (SessionCommand.RESTART_EPISODE, SessionCommand.STOP_COLLECTION)
            if coordinator is not None:
                _end_session_episode(coordinator, discard=discard)
            if discard:
                assert command is not None
                manifest = draft.abandon(f"discarded by the operator ({command.value})", extra)
            else:
                manifest = draft.commit(extra)
        except BaseException as exc:
            self._episode_running = False
            if coordinator is not None:
                _end_session_episode(coordinator, discard=True)
            _quietly(recorder.stop)
            reason = "interrupted by operator (Ctrl-C)" if isinstance(exc, KeyboardInterrupt) else str(exc)
            try:
                draft.abandon(reason or type(exc).__name__)
            except (OSError, RecordingError) as abandon_exc:
                raise RecordingError(
                    f"episode {draft.id} could not be closed ({abandon_exc}); free disk space, then run "
                    f"`telerig repair {draft.id}`"
                ) from exc
            if isinstance(exc, OSError):
                raise RecordingError(f"episode {draft.id} marked incomplete: {exc}") from exc
            raise
        directory = (
            self.store.root / ("incomplete" if manifest.status == "incomplete" else "episodes") / manifest.id
        )
        self._archive(manifest, directory)
        if command is SessionCommand.RESET_AND_NEXT:
            self.go_home()
        return EpisodeResult(
            manifest.id,
            manifest.status,
            directory,
            manifest.duration_s or 0.0,
            stream_stats,
            latency,
            {name: v.frames for name, v in videos.items()},
            command,
        )

    def _archive(self, manifest: EpisodeManifest, directory: Path) -> None:
        """Index the finished episode and queue committed ones for upload (after resuming uploads)."""
        if self.index is not None:
            self.index.upsert_episode(manifest, location=directory)
        if self.uploads is not None:
            if manifest.status == "complete":
                self.uploads.submit(directory, now=self.config.storage.upload == "now")
            self.uploads.resume()

    def _latency(self) -> LatencySummary:
        merged = LatencyTracker()
        for node in self.controls.values():
            for value in node.latency.values_ns():
                merged.add(int(value))
        for host in self.hosts.values():
            for value in host.call("latency_ns"):
                merged.add(int(value))
        return merged.summary()

    @contextlib.contextmanager
    def _cameras_recording(self, camera_path: Callable[[str], Path]) -> Iterator[dict[str, EncodeResult]]:
        """Record every camera for the duration of the block; the dict holds their results afterwards."""
        results: dict[str, EncodeResult] = {}
        try:
            for name, camera in self.cameras.items():
                camera.begin(camera_path(name))
            for host in self.hosts.values():
                host.begin_cameras({name: camera_path(name) for name in host.plan.cameras})
            yield results
        finally:
            for name, camera in self.cameras.items():
                result = camera.end()
                if result is not None:
                    results[name] = result
            for host in self.hosts.values():
                results.update(host.end_cameras())


def _end_session_episode(coordinator: Coordinator, *, discard: bool) -> None:
    """Move the session to stopped unless a command from elsewhere already did."""
    if coordinator.state is SessionState.STOPPED:
        return
    try:
        coordinator.discard() if discard else coordinator.stop()
    except SessionError as exc:
        log.warning("session: %s", exc)


def _control_rate(robot_cfg: RobotConfig) -> float:
    return float(getattr(robot_cfg, "control_rate_hz", 100.0))


def _wait(
    duration_s: float | None, progress: ProgressCallback | None, commands: queue.SimpleQueue[SessionCommand]
) -> SessionCommand | None:
    """Wait ``duration_s`` (None: no limit) or until a session command arrives; returns the command."""
    start = time.monotonic()
    total = math.inf if duration_s is None else duration_s
    while True:
        elapsed = time.monotonic() - start
        if progress is not None:
            progress(min(elapsed, total), total)
        if elapsed >= total:
            return None
        try:
            return commands.get(timeout=min(0.1, total - elapsed))
        except queue.Empty:
            continue


def _json(obj: Any) -> dict[str, JsonValue]:
    """A slotted stats dataclass as JSON values (NaN becomes null)."""
    out: dict[str, JsonValue] = {}
    for name in obj.__slots__:
        value = getattr(obj, name)
        out[name] = None if isinstance(value, float) and math.isnan(value) else value
    return out


def _quietly(fn: Callable[[], object]) -> None:
    try:
        fn()
    except TelerigError as exc:  # expected (disk full, lost connection): one line, no traceback
        log.warning("%s: %s", getattr(fn, "__qualname__", fn), exc)
    except Exception:
        log.exception("error during shutdown in %s", getattr(fn, "__qualname__", fn))
