"""Rig runtime: runs one station of a rig from its config and records episodes. Read this first.

A station is put together from rooms that each do one job:

* :class:`~telerig.runtime.broker_supervisor.BrokerSupervisor`: the embedded broker and its watchdog
  (with the control center's registered device logins of ``<data root>/broker/<rig>``);
* :class:`~telerig.runtime.storage.StationStorage`: episode store, index database, uploads;
* :class:`~telerig.runtime.nodes.StationNodes`: robots with their control nodes and safety
  chains, devices and cameras that run in this process;
* :class:`~telerig.runtime.robot_host.RobotHost`: a robot (with its own devices and cameras) in a
  child process when ``runtime.isolation: processes``, driven by typed requests;
* :class:`~telerig.runtime.station_session.StationSession`: the session coordinator (first
  station), the station agent and the operator's commands;
* :class:`~telerig.runtime.recording.EpisodeRecording`: one episode's draft, recorder, cameras
  and manifest.

All nodes talk through the broker exactly as separate processes would. The rig's first station
coordinates the session (and runs the embedded broker); every other station follows it from its
own host (:meth:`RigRuntime.follow_episode`), records its own nodes into its own data root under
the coordinator's episode ids, with times in the coordinator's clock. Process-wide settings (GIL
switch interval, C heap) are the entry points' business:
:func:`~telerig.runtime.process_settings.control_process`.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import TypeVar

from telerig import thread_names
from telerig.bus.acl import rig_access_policy
from telerig.bus.mqtt import MqttBus
from telerig.config.schema import (
    CameraConfig,
    DeviceConfig,
    EmbeddedBrokerConfig,
    NodeConfig,
    RigConfig,
    RobotConfig,
    SessionCommand,
)
from telerig.errors import ConfigError, RecordingError
from telerig.record.recorder import Recorder
from telerig.robots.base import RobotDriver
from telerig.runtime.broker_supervisor import BrokerSupervisor, station_logins
from telerig.runtime.camera_node import CameraNode
from telerig.runtime.control_node import ControlNode
from telerig.runtime.device_node import DeviceNode
from telerig.runtime.idle_poll import IdlePoll
from telerig.runtime.nodes import StationNodes, check_supported, quietly
from telerig.runtime.process_settings import settle_heap
from telerig.runtime.recording import EpisodeRecording, EpisodeResult, expected_rates
from telerig.runtime.robot_host import GoHome, Prepare, ReplayDevices, RobotHost, plan_hosts
from telerig.runtime.session import Coordinator, StationAgent
from telerig.runtime.station_session import ProgressCallback, StationSession
from telerig.runtime.storage import StationStorage
from telerig.runtime.streams import rig_nodes
from telerig.runtime.task import TaskEpisodes, task_robots
from telerig.safety import SafetySupervisor
from telerig.store.episodes import EpisodeStore
from telerig.store.fingerprint import rig_fingerprint
from telerig.store.index import EpisodeIndex
from telerig.store.upload import UploadQueue

__all__ = ["EpisodeResult", "ProgressCallback", "RigRuntime"]

log = logging.getLogger(__name__)

_OnStation = TypeVar("_OnStation", bound=NodeConfig)


class RigRuntime:
    """One station of a rig: broker, storage, nodes, robot hosts, session and recorder.

    Use as a context manager; ``close()`` is idempotent and always leaves the robots stopped and
    no child process behind.

    Args:
        config: The validated rig.
        data_root: Where episodes go; the rig's ``recording.data_root`` when None.
        station: Which station of the rig this process runs; the first (the coordinator) when None.
        broker_url: Broker to use instead of the rig's; a station other than the first needs it
            when the rig embeds its broker (the coordinator's host runs it).
        task_seed: Base seed of the rig's randomized task (episode ``k`` uses ``task_seed + k``);
            the task robot's own ``seed`` when None.

    Raises:
        ConfigError: ``station`` is not in the rig, or a following station has no broker to reach.
    """

    def __init__(
        self,
        config: RigConfig,
        *,
        data_root: Path | None = None,
        station: str | None = None,
        broker_url: str | None = None,
        task_seed: int | None = None,
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
        self.config = config
        self._buses: list[MqttBus] = []
        self.broker = BrokerSupervisor(
            config.name,
            config.broker,
            broker_url=broker_url,
            access=rig_access_policy(config),
            realtime_priority=config.runtime.realtime_priority,
            # The control center's registered devices (`telerig serve` on the same data root).
            registered_folder=Path(data_root or config.recording.data_root) / "broker" / config.name,
            reserved=station_logins(config, self.station_id),
        )
        self.storage = StationStorage(
            data_root or config.recording.data_root, config.storage, rig_fingerprint(config), qa=config.qa
        )
        self.nodes = StationNodes(config, self.station_id, self._buses, login=self.broker.node_url)
        self.nodes.profile_root = self.storage.store.root  # operator calibrations from the dashboard
        #: Robots running in child processes (``runtime.isolation: processes``), by robot id.
        self.hosts: dict[str, RobotHost] = {}
        self.session = StationSession(config, self.station_id, coordinating=self.coordinating)
        self._recorder: Recorder | None = None
        self._recording: EpisodeRecording | None = None
        self._task_seed = task_seed
        #: The station's randomized tasks (reset per episode, judged from the scene); set by open().
        self.tasks = TaskEpisodes({})
        #: Keeps the station's CPUs from halting while the rig is open (``runtime.idle_poll``).
        self.idle_poll = IdlePoll()
        self._closed = False

    # -- what the rooms hold, for callers and tests -------------------------------------------

    @property
    def store(self) -> EpisodeStore:
        return self.storage.store

    @property
    def index(self) -> EpisodeIndex | None:
        return self.storage.index

    @property
    def uploads(self) -> UploadQueue | None:
        return self.storage.uploads

    @property
    def broker_url(self) -> str | None:
        """The broker this station's nodes use, once open (the embedded one's port is chosen then)."""
        return self.broker.url

    @property
    def robots(self) -> dict[str, RobotDriver]:
        return self.nodes.robots

    @property
    def devices(self) -> dict[str, DeviceNode]:
        return self.nodes.devices

    @property
    def controls(self) -> dict[str, ControlNode]:
        return self.nodes.controls

    @property
    def cameras(self) -> dict[str, CameraNode]:
        return self.nodes.cameras

    @property
    def supervisor(self) -> SafetySupervisor | None:
        return self.nodes.supervisor

    @property
    def coordinator(self) -> Coordinator | None:
        return self.session.coordinator

    @property
    def station(self) -> StationAgent | None:
        return self.session.station

    @property
    def recorder(self) -> Recorder:
        if self._recorder is None:
            raise RuntimeError("open() the runtime first")
        return self._recorder

    # -- lifecycle ----------------------------------------------------------------------------

    def __enter__(self) -> RigRuntime:
        try:
            self.open()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def open(self) -> None:
        """Start the broker (if embedded), robots (here or in their processes), devices, cameras,
        control nodes, the recorder and the session."""
        cfg = self.config
        check_supported(cfg)
        if cfg.runtime.idle_poll:
            self.idle_poll.start()
        self.storage.open()
        url = self.broker.start()
        plans = plan_hosts(cfg, self.station_id) if cfg.runtime.isolation == "processes" else []
        for plan in plans:  # children start in parallel with the station's own nodes
            host_url = self.broker.host_url(url, plan.robot)
            host = RobotHost(cfg, plan, host_url, station=self.station_id, data_root=self.store.root)
            self.hosts[plan.robot] = host
            host.start()
        hosted = {p.robot for p in plans} | {d for p in plans for d in p.devices}
        hosted |= {c for p in plans for c in p.cameras}
        self.nodes.open(
            url,
            robots=[r.id for r in self._local(cfg.robots) if r.id not in hosted],
            devices=[d.id for d in self._local(cfg.devices) if d.id not in hosted],
            cameras=[c.id for c in self._local(cfg.cameras) if c.id not in hosted],
        )
        for host in self.hosts.values():
            host.wait_ready()
        hosted_tasks = sorted(set(task_robots(cfg)) & set(self.hosts))
        if hosted_tasks:
            raise ConfigError(
                f"robot(s) {', '.join(hosted_tasks)} run a randomized task, which needs the robot in the "
                "station's process: set runtime.isolation: threads"
            )
        self.tasks = TaskEpisodes(self.nodes.robots, seed=self._task_seed)
        node = "recorder" if self.coordinating else f"recorder-{self.station_id}"
        recorder = self._recorder = Recorder(
            cfg.name,
            self.nodes.bus(url, node),
            expected_rates(cfg, self.station_id, self.nodes, self.hosts),
            node=node,
            skip_nodes=self._remote_nodes(),
            nodes=rig_nodes(cfg),
            to_session_ns=None if self.coordinating else self.session.to_session_ns,
        )
        self.broker.publish_alerts_on(recorder.bus)
        self.session.start(recorder.bus)
        self._recording = EpisodeRecording(
            cfg,
            self.station_id,
            storage=self.storage,
            recorder=recorder,
            session=self.session,
            nodes=self.nodes,
            hosts=self.hosts,
            broker=self.broker,
            tasks=self.tasks,
        )
        thread_names.name_all()  # so the kernel's tools (top -H, perf, ftrace) tell its threads apart
        settle_heap()  # the first heap trim and a full collection now, not inside a control tick

    def close(self) -> None:
        """Stop robot hosts, devices, cameras and control, stop robots, the session, the recorder,
        storage, the bus clients and the broker. Idempotent."""
        if self._closed:
            return
        self._closed = True
        for host in self.hosts.values():
            quietly(host.close)
        self.nodes.close()
        quietly(self.session.close)
        if self._recorder is not None:
            quietly(self._recorder.close)
        quietly(self.storage.close)
        for bus in self._buses:
            quietly(bus.close)
        quietly(self.broker.close)
        self.idle_poll.close()

    # -- episodes -----------------------------------------------------------------------------

    def run_episode(
        self, duration_s: float | None = None, *, progress: ProgressCallback | None = None
    ) -> EpisodeResult:
        """Record one episode: reset the scene objects (a randomized task: the arm home and the
        objects at the next seed's poses), start devices and cameras, run, commit.

        The episode runs for ``duration_s`` or until the operator issues a session command
        (``episode_control`` in the rig): end-session and reset-and-next commit it (the latter
        then drives the arms home), restart and stop discard it to the incomplete partition.
        On any exception (Ctrl-C included) the devices stop, the robots hold, and the episode
        moves to the incomplete partition with the reason; earlier episodes are never touched.
        """
        cfg = self.config
        recording = self._require_open()
        coordinator = self.session.coordinator
        if coordinator is None:
            raise RuntimeError(f"station {self.station_id!r} follows the session: use follow_episode()")
        duration = duration_s if duration_s is not None else cfg.recording.episode_duration_s
        self._prepare_episode()
        self.session.started.clear()
        armed = coordinator.arm(task=cfg.recording.task, operator=cfg.recording.operator)
        if armed.episode_id is None or not self.session.started.wait(cfg.recording.start_lead_s + 5.0):
            coordinator.discard("start did not arrive")
            raise RecordingError(
                f"episode {armed.episode_id}: the session start did not arrive on this station"
            )
        result = recording.record(
            armed.episode_id, cfg.recording.task, cfg.recording.operator, duration, progress
        )
        if result.command is SessionCommand.RESET_AND_NEXT:
            self.go_home()
        return result

    def follow_episode(
        self, *, timeout_s: float | None = None, progress: ProgressCallback | None = None
    ) -> EpisodeResult | None:
        """On a following station: record the next episode the coordinator starts, until it ends.

        Waits up to ``timeout_s`` (forever when None) for the start; returns None when none came.
        The episode is filed under the coordinator's episode id, task and operator; it commits
        when the coordinator stops it and goes to the incomplete partition when it is discarded
        or restarted there.
        """
        recording = self._require_open()
        if self.coordinating:
            raise RuntimeError(f"station {self.station_id!r} coordinates the session: use run_episode()")
        self._prepare_episode()
        if not self.session.started.wait(timeout_s):
            return None
        self.session.started.clear()
        status = self.session.agent().status
        if status is None or status.episode_id is None:
            raise RecordingError("the session started without an episode id; is the coordinator current?")
        cfg = self.config
        task = status.task or cfg.recording.task
        return recording.record(
            status.episode_id, task, status.operator or cfg.recording.operator, None, progress
        )

    def go_home(self, *, timeout_s: float = 15.0, open_grippers: bool = False) -> bool:
        """Drive every arm to its home configuration through its safety chain (safe repositioning);
        with ``open_grippers`` each gripper opens on the way (a task's scene reset)."""
        here = self.nodes.go_home(timeout_s, open_grippers=open_grippers)
        hosted = [
            h.call(GoHome(timeout_s, open_grippers), timeout_s=timeout_s + 10.0)
            for h in self.hosts.values()
            if h.info.has_home
        ]
        return here and all(hosted)

    def replay_devices(self, episode: EpisodeResult) -> list[str]:
        """Swap every device that recorded a stream in ``episode`` (here or in a robot's process)
        for a replay of that stream, between episodes; returns the ids swapped."""
        from telerig.devices.replay import ReplayDevice

        path = episode.path / "episode.mcap"

        def recorded(device_id: str) -> str | None:
            marker = f"{self.config.name}/{device_id}/"
            return next((s.name for s in episode.streams if marker in s.name and s.messages), None)

        swapped = []
        for device_id, node in self.nodes.devices.items():
            if (topic := recorded(device_id)) is not None:
                node.swap(ReplayDevice(path, topic=topic, id=device_id))
                swapped.append(device_id)
        for host in self.hosts.values():
            topics = {d: t for d in host.plan.devices if (t := recorded(d)) is not None}
            if topics:
                host.call(ReplayDevices(str(path), topics))
                swapped += topics
        return swapped

    def _prepare_episode(self) -> None:
        # A task's scene reset: the arm home and its gripper open through its safety chain, then
        # the objects placed. Every episode starts from the same robot state, whatever the last
        # one ended holding (a policy that keeps the gripper as it found it never opens it).
        if self.tasks and not self.go_home(open_grippers=True):
            log.warning(
                "task reset: an arm did not reach home (or its gripper did not open) within 15 s; "
                "the episode starts anyway"
            )
        self.nodes.prepare()
        if self.tasks:
            self.tasks.begin()
        for host in self.hosts.values():
            host.call(Prepare())
        self.storage.pause_uploads()  # uploads never compete with a recording
        self.session.begin_episode()

    def _require_open(self) -> EpisodeRecording:
        if self._recording is None:
            raise RuntimeError("open() the runtime first")
        return self._recording

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
