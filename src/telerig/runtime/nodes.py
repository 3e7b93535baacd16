"""Node building: a station's robots (each with its control node and safety chain), devices and cameras.

:class:`StationNodes` builds the nodes named from the rig's config, starts them, resets them
between episodes and stops them. A station's :class:`~telerig.runtime.rig.RigRuntime` uses one
for the nodes it runs itself; a robot host process (:mod:`telerig.runtime.robot_host`) uses one
for its robot alone.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from telerig import priority, thread_names
from telerig.bus.mqtt import MqttBus, rig_tls
from telerig.bus.topics import Topic
from telerig.cameras.capture import Camera
from telerig.cameras.mujoco_camera import FrameCallback
from telerig.config.schema import BindingConfig, CameraConfig, RigConfig, RobotConfig
from telerig.devices.base import on_change_streams
from telerig.devices.validate import FiniteCheck, MonotonicCheck, SampleValidator, StampCheck
from telerig.errors import ConfigError, TelerigError
from telerig.retarget.binding import BindContext
from telerig.robots.base import RobotDriver
from telerig.runtime.camera_node import CameraFactory, CameraNode
from telerig.runtime.control_node import (
    AidBinding,
    BaseBinding,
    ControlNode,
    DeadmanBinding,
    FeedBinding,
    GripperBinding,
    JointsBinding,
)
from telerig.runtime.device_node import DeviceNode
from telerig.runtime.halts import halt_publisher, listen_for_halts
from telerig.runtime.handover import Handover, Source, SourceKind
from telerig.safety import (
    ConfigurationGuard,
    Deadman,
    RobotSafetyConfig,
    SafetyAlerts,
    SafetyChain,
    SafetySupervisor,
)
from telerig.safety.commands import SafetyCommandListener
from telerig.safety.parts import BaseLimit, GripperLimit
from telerig.safety.settings import robot_guard

__all__ = ["StationNodes", "check_supported", "quietly"]

log = logging.getLogger(__name__)


@runtime_checkable
class _HomedScene(Protocol):
    """A simulated arm's scene: the arm's home configuration [rad]. Shape (n,)."""

    home: NDArray[np.float64]


@runtime_checkable
class _Policy(Protocol):
    """A device with a process of its own to load before and end after the session (a policy)."""

    def load(self) -> object: ...

    def close(self) -> None: ...


def _check_policy(config: RigConfig, device_id: str, device: _Policy) -> None:
    """Refuse a policy whose robot or cameras the rig does not give it (one line saying what to set)."""
    robots = {r.id for r in config.robots}
    robot = getattr(device, "robot", None)
    if robot not in robots:
        raise ConfigError(
            f"devices.{device_id}.robot: {robot!r} is not a robot of this rig. "
            f"Available: {', '.join(sorted(robots))}"
        )
    observed = {c.id: c for c in config.cameras}
    for camera in getattr(device, "observes_frames", ()):
        if camera not in observed:
            raise ConfigError(
                f"devices.{device_id}: the policy needs camera {camera!r}, which this rig does not have; "
                "map its camera keys with cameras: {key: camera id} "
                f"(cameras: {', '.join(sorted(observed)) or 'none'})"
            )
        if observed[camera].observation is None:
            raise ConfigError(
                f"cameras.{camera}: the policy {device_id!r} reads its frames; set observation: "
                "{width: W, height: H, rate_hz: R} on the camera"
            )


@runtime_checkable
class _Simulated(Protocol):
    """A simulated robot: task objects to put back between episodes."""

    @property
    def scene(self) -> object: ...

    def reset_objects(self) -> None: ...


def check_supported(config: RigConfig) -> None:
    """Refuse a rig with a camera this runtime cannot build (before anything starts).

    Raises:
        ConfigError: naming the camera.
    """
    for i, camera in enumerate(config.cameras):
        if type(camera).build is CameraConfig.build:
            raise ConfigError(f"cameras[{i}].type: {camera.type!r} has no builder in this runtime")


class StationNodes:
    """The robots, control nodes, devices and cameras one process runs, with their safety supervisor.

    Args:
        config: The validated rig.
        station: The station the nodes belong to (names the node bus when it runs no robot).
        buses: Every bus client made here is appended (the owner closes them after the nodes).
        login: The URL a client named ``node`` logs in with, from ``(url, node)``; ``url`` as given
            when ``None`` (see :meth:`~telerig.runtime.broker_supervisor.BrokerSupervisor.node_url`).
    """

    def __init__(
        self,
        config: RigConfig,
        station: str,
        buses: list[MqttBus],
        login: Callable[[str, str], str] | None = None,
    ) -> None:
        self.config = config
        self.station = station
        self._buses = buses
        self._login = login
        self.robots: dict[str, RobotDriver] = {}
        self.devices: dict[str, DeviceNode] = {}
        self.controls: dict[str, ControlNode] = {}
        self.cameras: dict[str, CameraNode] = {}
        #: This process's bus for node-level messages (safety alerts and halts); set by :meth:`open`.
        self.node_bus: MqttBus | None = None
        #: The fault reactions and halt policy over these robots; set by :meth:`open`.
        self.supervisor: SafetySupervisor | None = None
        #: Applies operator e-stop/reset commands from the bus to these robots.
        self.safety_commands: SafetyCommandListener | None = None
        self._closed = False
        #: Where operator calibrations launched over the bus save their profiles (the station's data
        #: root); set before :meth:`open`.
        self.profile_root: Path | None = None

    def bus(self, url: str, node: str) -> MqttBus:
        """A connected bus client named after ``node``."""
        url = url if self._login is None else self._login(url, node)
        bus = MqttBus(url, client_id=f"{self.config.name}-{node}", tls=rig_tls(self.config.broker))
        self._buses.append(bus)
        return bus.connect()

    def open(
        self, url: str, *, robots: Sequence[str], devices: Sequence[str], cameras: Sequence[str]
    ) -> None:
        """Build and start the named robots (with their control nodes), devices and cameras."""
        cfg = self.config
        # The rig's priorities for every thread and render process started from here on.
        priority.configure(cfg.runtime.priorities.priorities())
        for robot_cfg in (r for r in cfg.robots if r.id in robots):
            robot = robot_cfg.build()
            self.robots[robot_cfg.id] = robot
            robot.connect()
        for device_cfg in (d for d in cfg.devices if d.id in devices):
            device = device_cfg.build()
            policy = isinstance(device, _Policy)
            if isinstance(device, _Policy):
                device.load()  # the inference process loads the checkpoint now, not at episode start
                try:
                    _check_policy(cfg, device_cfg.id, device)
                except ConfigError:
                    device.close()
                    raise
            self.devices[device_cfg.id] = DeviceNode(
                cfg.name,
                device,
                self.bus(url, f"dev-{device_cfg.id}"),
                # A policy's joint targets are no hand motion: no gap or jump checks (a missed
                # deadline is the safety chain's business, and the first action after it is valid).
                validator=(
                    SampleValidator([FiniteCheck(), StampCheck(), MonotonicCheck()])
                    if policy
                    else SampleValidator.from_config(
                        cfg.validation, on_change_streams=on_change_streams(device)
                    )
                ),
                profile_root=self.profile_root,
            )
        self._open_supervisor(url)
        for camera_cfg in (c for c in cfg.cameras if c.id in cameras):
            self.cameras[camera_cfg.id] = CameraNode(
                cfg.name, camera_cfg, self._camera_factory(camera_cfg), self.bus(url, f"cam-{camera_cfg.id}")
            )
        # The cameras start while the control nodes are built: a simulated camera's render process
        # imports MuJoCo and creates its GL context (~1 s, as long as the rest of a warm start), and
        # a controller builds its IK. Control starts once every camera is up.
        with ThreadPoolExecutor(max(1, len(self.cameras)), thread_name_prefix="camera-start") as pool:
            starting = [pool.submit(camera.start) for camera in self.cameras.values()]
            for robot_cfg in (r for r in cfg.robots if r.id in robots):
                self.controls[robot_cfg.id] = self._build_control(robot_cfg, url)
            for started in starting:
                started.result()
        for control in self.controls.values():
            control.start()

    def _open_supervisor(self, url: str) -> None:
        cfg = self.config
        node = (self.robots and "-".join(sorted(self.robots))) or self.station
        self.node_bus = node_bus = self.bus(url, f"safety-{node}")
        isolated = cfg.runtime.isolation == "processes"
        self.supervisor = SafetySupervisor(
            cfg.safety.policy,
            alerts=SafetyAlerts(node_bus, cfg.name, node=f"safety-{node}" if isolated else "safety"),
            on_halt_all=halt_publisher(node_bus, cfg.name) if isolated else None,
        )
        if isolated:
            listen_for_halts(self, cfg.name)
        self.safety_commands = SafetyCommandListener(
            node_bus, cfg.name, self.supervisor, rig_robots=[r.id for r in cfg.robots]
        )

    def prepare(self) -> None:
        """Before an episode: reset the latency statistics and the simulated scenes' objects."""
        for control in self.controls.values():
            control.latency.reset()
            if control.handover is not None:
                control.handover.reset_counts()  # the manifest counts this episode's interventions
        for robot in self.robots.values():
            if isinstance(robot, _Simulated):
                robot.reset_objects()

    def start_devices(self) -> None:
        for device in self.devices.values():
            device.start()
        thread_names.name_all()  # the devices' threads, started just now

    def stop_devices(self) -> None:
        for device in self.devices.values():
            device.stop()

    def go_home(self, timeout_s: float, *, open_grippers: bool = False) -> bool:
        """Drive every arm with a home configuration there through its safety chain (and open its
        gripper with ``open_grippers``)."""
        return all(
            node.go_home(timeout_s=timeout_s, open_gripper=open_grippers)
            for node in self.controls.values()
            if node.has_home
        )

    def close(self) -> None:
        """Stop devices, cameras and control, then close the robots. Idempotent; never raises."""
        if self._closed:
            return
        self._closed = True
        for device in self.devices.values():
            quietly(device.stop)
            if isinstance(device.device, _Policy):
                quietly(device.device.close)  # ends its inference process
        for camera in self.cameras.values():
            quietly(camera.stop)
        for node in self.controls.values():
            quietly(node.stop)
        for robot in self.robots.values():
            quietly(robot.close)

    def _camera_factory(self, config: CameraConfig) -> CameraFactory:
        """The camera built from its config, with this process's robots (a scene camera renders one)."""

        def make(on_frame: FrameCallback) -> Camera:
            return config.build(on_frame, robots=self.robots)

        return make

    def _bindings(
        self, robot_cfg: RobotConfig, robot: RobotDriver
    ) -> tuple[
        JointsBinding | None,
        GripperBinding | None,
        BaseBinding | None,
        list[AidBinding | FeedBinding],
        Handover | None,
    ]:
        """Every binding's retargeter config binds its parts of the robot; several sources of the
        joints or gripper (or a policy) go through a handover."""
        cfg = self.config
        joints: JointsBinding | None = None
        gripper: GripperBinding | None = None
        base: BaseBinding | None = None
        aids: list[AidBinding | FeedBinding] = []
        devices = tuple(d.id for d in cfg.devices)
        drives = tuple((b.device, b.robot) for b in cfg.bindings)
        of_robot = [b for b in cfg.bindings if b.robot == robot_cfg.id]
        if needs_handover(cfg, of_robot):
            handover, base, aids = self._handover_bindings(robot_cfg, robot, of_robot)
            return None, None, base, aids, handover
        for binding in of_robot:
            context = BindContext(
                cfg.name, robot_cfg.id, robot, binding.target, binding.device, binding.part, devices, drives
            )
            bound = binding.retargeter.bind(context)
            for part, mine, taken in (
                ("joints", bound.joints, joints),
                ("gripper", bound.gripper, gripper),
                ("base", bound.base, base),
            ):
                if mine is not None and taken is not None:
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
            aids.extend(FeedBinding(topic, feed) for topic, feed in bound.feeds)
        return joints, gripper, base, aids, None

    def _handover_bindings(
        self, robot_cfg: RobotConfig, robot: RobotDriver, bindings: Sequence[BindingConfig]
    ) -> tuple[Handover, BaseBinding | None, list[AidBinding | FeedBinding]]:
        """The robot's sources of joints and gripper (one per device stream) under a handover."""
        cfg = self.config
        devices = tuple(d.id for d in cfg.devices)
        drives = tuple((b.device, b.robot) for b in cfg.bindings)
        kinds = {d.id: ("policy" if d.type == "policy" else "operator") for d in cfg.devices}
        sources: dict[str, Source] = {}
        base: BaseBinding | None = None
        aids: list[AidBinding | FeedBinding] = []
        lowest = min(b.priority for b in bindings)
        for binding in bindings:
            context = BindContext(
                cfg.name, robot_cfg.id, robot, binding.target, binding.device, binding.part, devices, drives
            )
            bound = binding.retargeter.bind(context)
            kind: SourceKind = "policy" if kinds[binding.device] == "policy" else "operator"
            source = sources.get(context.topic)
            if source is None:
                source = sources[context.topic] = Source(
                    context.topic, binding.device, kind, binding.priority
                )
            source.priority = max(source.priority, binding.priority)
            button = binding.takeover_button or getattr(binding.retargeter, "clutch_button", None)
            source.takeover_button = source.takeover_button or button
            if bound.joints is not None:
                if kind == "operator" and binding.priority > lowest and _absolute(binding):
                    raise ConfigError(
                        f"{context.where}: an operator who takes over must drive the arm in relative mode "
                        "(arm_pose with mode: relative and a clutch_button); absolute mode would pull the "
                        "arm to the hand at takeover"
                    )
                source.joints = bound.joints
            if bound.gripper is not None:
                if not robot.has_gripper:
                    raise ConfigError(
                        f"{context.where}: robot {robot_cfg.id!r} has no gripper for "
                        f"{binding.retargeter.type!r} to drive; remove the binding or configure the gripper"
                    )
                source.gripper = bound.gripper
            if bound.base is not None:
                base = BaseBinding(context.topic, bound.base)
            aids.extend(AidBinding(topic, aid) for topic, aid in bound.aids)
            aids.extend(FeedBinding(topic, feed) for topic, feed in bound.feeds)
        try:
            handover = Handover(
                [s for s in sources.values() if s.joints is not None or s.gripper is not None]
            )
        except ConfigError as exc:
            raise ConfigError(f"robot {robot_cfg.id!r}: {exc}") from None
        return handover, base, aids

    def _build_control(self, robot_cfg: RobotConfig, url: str) -> ControlNode:
        """The robot's control node: its bound parts, then its safety chain under the supervisor."""
        cfg = self.config
        robot = self.robots[robot_cfg.id]
        joints, gripper, base, aids, handover = self._bindings(robot_cfg, robot)
        rate = robot_cfg.control_rate()
        s = cfg.safety
        robot_safety = s.robots.get(robot_cfg.id, RobotSafetyConfig())
        deadman: DeadmanBinding | None = None
        if robot_safety.deadman is not None:
            d = robot_safety.deadman
            device, part = d.stream.split("/", 1)
            deadman = DeadmanBinding(
                str(Topic(cfg.name, device, part)), d.button, d.threshold, Deadman(d.signal_timeout_ms / 1e3)
            )
        chain = SafetyChain.from_config(
            robot.limits,
            s,
            rate_hz=rate,
            source_id=f"{robot_cfg.id}/safety",
            guard=_guard(robot_cfg, robot, robot_safety),
            deadman=None if deadman is None else deadman.deadman,
        )
        if self.supervisor is None:
            raise RuntimeError("the safety supervisor starts before the control nodes")
        bus = self.bus(url, f"ctl-{robot_cfg.id}")
        scene = robot.scene if isinstance(robot, _Simulated) else None
        home = scene.home if isinstance(scene, _HomedScene) else None
        return ControlNode(
            cfg.name,
            robot,
            self.supervisor.add(
                robot_cfg.id,
                robot,
                chain,
                gripper=GripperLimit.from_config(robot_safety.gripper),
                base=BaseLimit.from_config(robot_safety.base),
            ),
            bus,
            control_rate_hz=rate,
            joints=joints,
            gripper=gripper,
            home=home,
            aids=aids,
            base=base,
            deadman=deadman,
            latency_budgets=cfg.latency.budgets(),
            handover=handover,
        )


def needs_handover(config: RigConfig, bindings: Sequence[BindingConfig]) -> bool:
    """Whether a robot's bindings need a handover: a policy drives it, or several sources share a part."""
    policies = {d.id for d in config.devices if d.type == "policy"}
    return any(b.device in policies for b in bindings) or len({b.priority for b in bindings}) > 1


def _absolute(binding: BindingConfig) -> bool:
    """An arm retargeter that maps the hand's absolute pose (no clutch, no re-anchoring)."""
    retargeter = binding.retargeter
    return retargeter.type == "absolute_pose" or getattr(retargeter, "mode", None) == "absolute"


def _guard(
    robot_cfg: RobotConfig, robot: RobotDriver, config: RobotSafetyConfig
) -> ConfigurationGuard | None:
    """Workspace bounds and self-collision checks of an arm (simulated or real, by the model its
    config names), on its kinematic model; None when off."""
    return robot_guard(robot, config, where=f"safety.robots.{robot_cfg.id}")


def quietly(fn: Callable[[], object]) -> None:
    """Call ``fn`` during shutdown: an error is one log line, never raised."""
    try:
        fn()
    except TelerigError as exc:  # expected (disk full, lost connection): one line, no traceback
        log.warning("%s: %s", getattr(fn, "__qualname__", fn), exc)
    except Exception:
        log.exception("error during shutdown in %s", getattr(fn, "__qualname__", fn))
