"""Robot hosts: one robot with its control loop, its own devices and cameras in a child process.

With ``runtime.isolation: processes`` a station runs each robot in a child process so robots
never compete for one interpreter lock: a rig of six simulated robots in one process spends its
time waiting for the GIL (MQTT client threads, physics threads, control loops), not computing.
The child builds its nodes with the same :class:`~telerig.runtime.nodes.StationNodes` code as a
single-process station and talks to the others over the broker as before; the station keeps the
broker, recorder, session and storage and drives the child's per-episode steps over a socket pair
with typed requests (:class:`HostRequest`: one small frozen dataclass per step, each with its one
handler, :meth:`HostRequest.run`, executed in the child).

The child is a fresh interpreter (``python -m telerig.runtime.robot_host``: no threads or locks
inherited, and unlike ``multiprocessing``'s spawn it never re-imports the caller's main script)
talking over a socket pair, and dies with its parent (``PR_SET_PDEATHSIG``). A fault under
``halt_all`` is published on ``telerig/v1/<rig>/safety/halt`` and every host halts its robots on it.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import signal
import socket
import subprocess
import sys
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Generic, TypeVar, cast

import numpy as np
import numpy.typing as npt

from telerig import errors, thread_names
from telerig.config.schema import RigConfig
from telerig.errors import DeviceError, RobotError, TelerigError
from telerig.robots.base import JointLimits
from telerig.runtime.camera_node import CameraEpisode
from telerig.runtime.process_settings import control_process, settle_heap
from telerig.runtime.realtime import set_realtime_priority
from telerig.runtime.robot_record import robot_joints_record
from telerig.store.manifest_extra import RobotJointsRecord

if TYPE_CHECKING:
    from telerig.bus.mqtt import MqttBus
    from telerig.runtime.control_node import ControlNode
    from telerig.runtime.nodes import StationNodes

__all__ = [
    "BeginCameras",
    "ControlStats",
    "EndCameras",
    "Estop",
    "Estopped",
    "Fault",
    "GoHome",
    "HostInfo",
    "HostPlan",
    "HostRequest",
    "LatencyNs",
    "Limits",
    "Prepare",
    "ReplayDevices",
    "RobotHost",
    "SafetyCounts",
    "StageRows",
    "StartDevices",
    "Stats",
    "StopDevices",
    "plan_hosts",
]

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class HostPlan:
    """What one child process runs: a robot, the devices bound only to it, and its cameras."""

    robot: str
    devices: tuple[str, ...]
    cameras: tuple[str, ...]


@dataclass(frozen=True, slots=True)
class HostInfo:
    """What a child reports once its nodes run.

    Attributes:
        bound_topics: The robot's bound parts and the device topics feeding them (``joints``, ...).
        has_home: The robot has a home configuration to drive to.
        robot_joints: The driver's joints, limits, gripper and standing height, for the manifest
            (``None`` until the child reported).
        sensed_streams: The measurement streams beyond ``joint_state`` its control node publishes
            every tick (:attr:`ControlNode.sensed_streams`).
    """

    bound_topics: dict[str, str | None]
    has_home: bool
    robot_joints: RobotJointsRecord | None = None
    sensed_streams: tuple[str, ...] = ()


@dataclass(frozen=True, slots=True)
class ControlStats:
    """A hosted robot's control counters and simulated physics timing (for benchmarks and manifests).

    ``rejected`` counts input samples the control node's gate dropped, per reason; ``tick_faults``
    the control ticks that raised (each a ``driver_fault`` e-stop); ``alive`` whether its control
    thread runs.
    """

    inputs_skipped: int
    applied: int
    ik_flagged: int
    safety_events: dict[str, int]
    physics_realtime_factor: float | None
    physics_overruns: int | None
    pid: int
    rejected: dict[str, int]
    tick_faults: int
    alive: bool


T = TypeVar("T")


class _Hosted:
    """The child's side of one request: its nodes and the robot's control node."""

    def __init__(self, nodes: StationNodes, robot: str) -> None:
        self.nodes = nodes
        self.control: ControlNode = nodes.controls[robot]


class HostRequest(Generic[T]):
    """A request of the station to a robot host, answered with a ``T``; :meth:`run` is its handler."""

    __slots__ = ()
    #: Name in messages and logs.
    name: ClassVar[str]

    def run(self, hosted: _Hosted) -> T:
        raise NotImplementedError


@dataclass(frozen=True, slots=True)
class Prepare(HostRequest[None]):
    """Before an episode: reset latency statistics and the simulated scene's objects."""

    name: ClassVar[str] = "prepare"

    def run(self, hosted: _Hosted) -> None:
        hosted.nodes.prepare()


@dataclass(frozen=True, slots=True)
class StartDevices(HostRequest[None]):
    name: ClassVar[str] = "start_devices"

    def run(self, hosted: _Hosted) -> None:
        hosted.nodes.start_devices()


@dataclass(frozen=True, slots=True)
class StopDevices(HostRequest[None]):
    name: ClassVar[str] = "stop_devices"

    def run(self, hosted: _Hosted) -> None:
        hosted.nodes.stop_devices()


@dataclass(frozen=True, slots=True)
class ReplayDevices(HostRequest[None]):
    """Swap the child's stopped devices for replays of a recorded episode: ``topics`` maps a device
    id to its stream's topic in the episode's MCAP at ``path``."""

    path: str
    topics: dict[str, str]
    name: ClassVar[str] = "replay_devices"

    def run(self, hosted: _Hosted) -> None:
        from telerig.devices.replay import ReplayDevice

        devices = hosted.nodes.devices
        unknown = sorted(set(self.topics) - set(devices))
        if unknown:
            raise DeviceError(f"device(s) {', '.join(unknown)} do not run here. Here: {', '.join(devices)}")
        for device_id, topic in self.topics.items():
            devices[device_id].swap(ReplayDevice(self.path, topic=topic, id=device_id))


@dataclass(frozen=True, slots=True)
class BeginCameras(HostRequest[None]):
    """Start recording every camera of the child into ``paths`` (camera id → MP4 path)."""

    paths: dict[str, str]
    name: ClassVar[str] = "begin_cameras"

    def run(self, hosted: _Hosted) -> None:
        for camera_id, camera in hosted.nodes.cameras.items():
            camera.begin(Path(self.paths[camera_id]))


@dataclass(frozen=True, slots=True)
class EndCameras(HostRequest[dict[str, CameraEpisode]]):
    name: ClassVar[str] = "end_cameras"

    def run(self, hosted: _Hosted) -> dict[str, CameraEpisode]:
        results = {camera_id: camera.end() for camera_id, camera in hosted.nodes.cameras.items()}
        return {camera_id: result for camera_id, result in results.items() if result is not None}


@dataclass(frozen=True, slots=True)
class LatencyNs(HostRequest[list[int]]):
    """The episode's input-to-actuation latencies [ns]."""

    name: ClassVar[str] = "latency_ns"

    def run(self, hosted: _Hosted) -> list[int]:
        return [int(v) for v in hosted.control.latency.values_ns()]


@dataclass(frozen=True, slots=True)
class StageRows(HostRequest[npt.NDArray[np.int64]]):
    """The stage stamps [ns] of the commands applied in the live window before ``now_ns`` [ns, wall
    clock], one row per command (:meth:`~telerig.runtime.metrics.LatencyWindow.rows` of the control
    node's ``live.stages``): the per-stage breakdown of a robot in a host, as a station reads its own."""

    name: ClassVar[str] = "stage_rows"
    now_ns: int

    def run(self, hosted: _Hosted) -> npt.NDArray[np.int64]:
        return hosted.control.live.stages.rows(self.now_ns)


@dataclass(frozen=True, slots=True)
class SafetyCounts(HostRequest[dict[str, int]]):
    """The robot's safety event counts since it started."""

    name: ClassVar[str] = "safety_counts"

    def run(self, hosted: _Hosted) -> dict[str, int]:
        return dict(hosted.control.safety.counts)


@dataclass(frozen=True, slots=True)
class Stats(HostRequest[ControlStats]):
    name: ClassVar[str] = "stats"

    def run(self, hosted: _Hosted) -> ControlStats:
        s = hosted.control.stats
        robot = hosted.control.robot
        physics_stats = getattr(robot, "stats", None)  # simulated robots time their physics
        physics = physics_stats() if callable(physics_stats) else None
        return ControlStats(
            inputs_skipped=s.inputs_skipped,
            applied=s.applied,
            ik_flagged=s.ik_flagged,
            safety_events=dict(s.safety_events),
            physics_realtime_factor=getattr(physics, "realtime_factor", None),
            physics_overruns=getattr(physics, "overruns", None),
            pid=os.getpid(),
            rejected=dict(s.rejected),
            tick_faults=s.tick_faults,
            alive=hosted.control.alive,
        )


@dataclass(frozen=True, slots=True)
class GoHome(HostRequest[bool]):
    """Drive the arm home through its safety chain within ``timeout_s`` [s] (opening the gripper
    with ``open_gripper``); whether it got there."""

    timeout_s: float
    open_gripper: bool = False
    name: ClassVar[str] = "go_home"

    def run(self, hosted: _Hosted) -> bool:
        return bool(hosted.control.go_home(timeout_s=self.timeout_s, open_gripper=self.open_gripper))


@dataclass(frozen=True, slots=True)
class Estop(HostRequest[None]):
    reason: str
    name: ClassVar[str] = "estop"

    def run(self, hosted: _Hosted) -> None:
        hosted.control.estop(self.reason)


@dataclass(frozen=True, slots=True)
class Fault(HostRequest[None]):
    """Report a hardware fault of the robot (e.g. from an external monitor): the rig's policy applies."""

    reason: str
    name: ClassVar[str] = "fault"

    def run(self, hosted: _Hosted) -> None:
        hosted.control.fault(self.reason)


@dataclass(frozen=True, slots=True)
class Estopped(HostRequest[bool]):
    name: ClassVar[str] = "estopped"

    def run(self, hosted: _Hosted) -> bool:
        return bool(hosted.control.safety.estopped)


@dataclass(frozen=True, slots=True)
class Limits(HostRequest[JointLimits]):
    name: ClassVar[str] = "limits"

    def run(self, hosted: _Hosted) -> JointLimits:
        limits: JointLimits = hosted.control.robot.limits
        return limits


def plan_hosts(config: RigConfig, station: str) -> list[HostPlan]:
    """One plan per robot of ``station``. A device bound to several robots stays with the station."""
    robots = [r.id for r in config.robots if r.station == station]
    plans = []
    for robot in robots:
        devices = tuple(
            d.id
            for d in config.devices
            if d.station == station and {b.robot for b in config.bindings if b.device == d.id} == {robot}
        )
        cameras = tuple(
            c.id for c in config.cameras if c.station == station and getattr(c, "robot", None) == robot
        )
        plans.append(HostPlan(robot, devices, cameras))
    return plans


class RobotHost:
    """The station's handle on one child process (see the module docstring). Not thread-safe.

    Args:
        config: The rig.
        plan: What the child runs.
        broker_url: The broker every node connects to.
        station: The station the child belongs to.
        data_root: The station's data root (cameras write their MP4s into its episode drafts).
    """

    def __init__(
        self, config: RigConfig, plan: HostPlan, broker_url: str, *, station: str, data_root: Path
    ) -> None:
        self.plan = plan
        self._args = (
            config.model_dump_json(),
            plan.robot,
            plan.devices,
            plan.cameras,
            broker_url,
            station,
            str(data_root),
        )
        self._conn: Connection | None = None
        self._process: subprocess.Popen[bytes] | None = None
        #: What the child reported when ready (set by :meth:`wait_ready`).
        self.info = HostInfo(bound_topics={}, has_home=False)

    def start(self) -> None:
        """Spawn the child; returns at once (:meth:`wait_ready` waits for it)."""
        parent, child = socket.socketpair()
        with child:
            self._process = subprocess.Popen(
                [sys.executable, "-m", "telerig.runtime.robot_host", "--fd", str(child.fileno())],
                pass_fds=(child.fileno(),),
                stdin=subprocess.DEVNULL,
            )
        self._conn = Connection(parent.detach())
        self._conn.send(self._args)

    def wait_ready(self, timeout_s: float = 120.0) -> None:
        """Wait until the child has built and started its nodes.

        Raises:
            RobotError: the child failed to start (its one-line error) or did not answer in time.
        """
        conn = self._require()
        if not conn.poll(timeout_s):
            raise RobotError(f"robot {self.plan.robot!r}: its process did not start within {timeout_s:g} s")
        self.info = cast(HostInfo, self._reply(conn))

    def call(self, request: HostRequest[T], *, timeout_s: float = 60.0) -> T:
        """Run ``request`` in the child and return its answer.

        Raises:
            RobotError: the child raised (its message), died, or did not answer in time.
        """
        conn = self._require()
        name = getattr(request, "name", repr(request))
        try:
            conn.send(request)
            if not conn.poll(timeout_s):
                raise RobotError(f"robot {self.plan.robot!r}: {name} did not answer within {timeout_s:g} s")
        except (BrokenPipeError, EOFError, OSError):
            raise RobotError(f"robot {self.plan.robot!r}: its process died; see the log above") from None
        return cast(T, self._reply(conn))

    def close(self, timeout_s: float = 15.0) -> None:
        """Stop the child's nodes (robots hold, then stop) and the process. Idempotent."""
        conn, process = self._conn, self._process
        self._conn = None
        if conn is not None:
            with contextlib.suppress(BrokenPipeError, EOFError, OSError):
                conn.send(_CLOSE)
                if conn.poll(timeout_s):
                    conn.recv()
            conn.close()
        if process is not None:
            try:
                process.wait(timeout_s)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait(5.0)

    # -- per-episode steps --------------------------------------------------------------------

    def begin_cameras(self, paths: dict[str, Path]) -> None:
        self.call(BeginCameras({name: str(path) for name, path in paths.items()}))

    def end_cameras(self) -> dict[str, CameraEpisode]:
        return self.call(EndCameras())

    def _require(self) -> Connection:
        if self._conn is None:
            raise RobotError(f"robot {self.plan.robot!r}: its process is not running")
        return self._conn

    def _reply(self, conn: Connection) -> Any:
        try:
            status, value = conn.recv()
        except (EOFError, OSError):
            raise RobotError(f"robot {self.plan.robot!r}: its process died; see the log above") from None
        if status == "error":
            kind, message = value
            raise _error_class(kind)(f"robot {self.plan.robot!r}: {message}")
        return value


# -- child side ----------------------------------------------------------------------------------


def main(argv: list[str] | None = None) -> None:
    """Entry point of the child process: ``python -m telerig.runtime.robot_host --fd N``."""
    parser = argparse.ArgumentParser(description="a telerig robot host (started by a station)")
    parser.add_argument("--fd", type=int, required=True, help="the station's socket")
    args = parser.parse_args(argv)
    conn = Connection(args.fd)
    config_json, robot, devices, cameras, broker_url, station, data_root = conn.recv()
    _child_main(conn, config_json, HostPlan(robot, devices, cameras), broker_url, station, data_root)


def _child_main(
    conn: Connection, config_json: str, plan: HostPlan, broker_url: str, station: str, data_root: str
) -> None:
    """Build the planned nodes, then serve the station's requests until it closes us."""
    _die_with_parent()
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C goes to the station, which closes us
    logging.basicConfig(level=logging.WARNING, format=f"{plan.robot}: %(message)s", stream=sys.stderr)
    from telerig.runtime.nodes import StationNodes

    buses: list[MqttBus] = []
    # An entry point like ``telerig run``: a woken control thread waits at most 1 ms, no heap trimming.
    with control_process():
        try:
            config = RigConfig.model_validate_json(config_json)
            if config.runtime.realtime_priority is not None:
                set_realtime_priority(config.runtime.realtime_priority, f"robot {plan.robot}")
            nodes = StationNodes(config, station, buses)
            nodes.profile_root = Path(data_root)  # operator calibrations of the devices it hosts
            try:
                nodes.open(broker_url, robots=(plan.robot,), devices=plan.devices, cameras=plan.cameras)
            except BaseException:
                _close(nodes, buses)
                raise
            thread_names.name_all()  # so the kernel's tools (top -H, perf, ftrace) tell its threads apart
            settle_heap()  # the first heap trim and a full collection now, not inside a control tick
        except Exception as exc:
            conn.send(_failed(exc))
            return
        try:
            control = nodes.controls[plan.robot]
            robot_cfg = next(r for r in config.robots if r.id == plan.robot)
            info = HostInfo(
                bound_topics=dict(control.bound_topics),
                has_home=control.has_home,
                robot_joints=robot_joints_record(robot_cfg, control.robot),
                sensed_streams=control.sensed_streams,
            )
            conn.send(("ok", info))
            _serve(conn, _Hosted(nodes, plan.robot))
        finally:
            _close(nodes, buses)


def _close(nodes: StationNodes, buses: list[MqttBus]) -> None:
    from telerig.runtime.nodes import quietly

    nodes.close()
    for bus in buses:
        quietly(bus.close)


class _Close:
    """The station closes the child (sent by :meth:`RobotHost.close`)."""


_CLOSE = _Close()


def _serve(conn: Connection, hosted: _Hosted) -> None:
    while True:
        try:
            request = conn.recv()
        except (EOFError, OSError):
            return  # the station is gone
        except Exception as exc:  # e.g. a request class this version does not have
            conn.send(_failed(RobotError(f"unreadable request ({exc})")))
            continue
        if isinstance(request, _Close):
            hosted.nodes.close()
            conn.send(("ok", None))
            return
        if not isinstance(request, HostRequest):
            conn.send(_failed(RobotError(f"unknown request {request!r}")))
            continue
        try:
            conn.send(("ok", request.run(hosted)))
        except Exception as exc:
            conn.send(_failed(exc, f"{request.name}: "))


def _failed(exc: Exception, context: str = "") -> tuple[str, tuple[str, str]]:
    """The reply for a request (or a start) that raised ``exc``: its telerig error class, so the
    station raises the same kind (a bad rig stays a ``ConfigError``), and its message. A telerig
    error's one line is the station's to say (a full disk); anything else is a bug, whose
    traceback is logged here, where it happened."""
    if not isinstance(exc, TelerigError):
        log.error("%sfailed", context or "start-up ", exc_info=exc)
    kind = type(exc).__name__ if isinstance(exc, TelerigError) else RobotError.__name__
    return "error", (kind, f"{context}{exc}" if str(exc) else f"{context}{type(exc).__name__}")


def _error_class(kind: str) -> type[TelerigError]:
    """The telerig error class named ``kind`` by the child; :class:`RobotError` for any other name."""
    cls = getattr(errors, kind, None)
    return cls if isinstance(cls, type) and issubclass(cls, TelerigError) else RobotError


def _die_with_parent() -> None:
    if sys.platform != "linux":  # pragma: no cover - Linux only
        return
    import ctypes

    libc = ctypes.CDLL(None, use_errno=True)
    pr_set_pdeathsig = 1
    libc.prctl(pr_set_pdeathsig, signal.SIGTERM)
    if os.getppid() == 1:  # the parent died before prctl took effect
        os._exit(1)


if __name__ == "__main__":
    # Run the imported module's main, not this ``__main__`` copy: the requests and replies crossing
    # the socket are pickled as ``telerig.runtime.robot_host`` classes.
    from telerig.runtime.robot_host import main as _main

    _main()
