"""Robot hosts: one robot with its control loop, its own devices and cameras in a child process.

With ``runtime.isolation: processes`` a station runs each robot in a child process so robots
never compete for one interpreter lock: a rig of six simulated robots in one process spends its
time waiting for the GIL (MQTT client threads, physics threads, control loops), not computing.
The child builds its nodes with the same :class:`~telerig.runtime.rig.RigRuntime` code as a
single-process station and talks to the others over the broker as before; the station keeps the
broker, recorder, session and storage and drives the child's per-episode steps over a socket pair.

The child is a fresh interpreter (``python -m telerig.runtime.robot_host``: no threads or locks
inherited, and unlike ``multiprocessing``'s spawn it never re-imports the caller's main script)
talking over a socket pair, and dies with its parent (``PR_SET_PDEATHSIG``). A fault under
``halt_all`` is published on ``telerig/v1/<rig>/safety/halt`` and every host halts its robots on it.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import signal
import socket
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from telerig.bus.topics import Topic
from telerig.cameras.encoder import EncodeResult
from telerig.config.schema import RigConfig
from telerig.errors import RobotError
from telerig.robots.base import JointLimits
from telerig.runtime.realtime import keep_heap, release_heap, set_realtime_priority
from telerig.safety.commands import HaltListener
from telerig.safety.filters import SafetyEvent

__all__ = ["HALT", "HostPlan", "RobotHost", "halt_publisher", "listen_for_halts", "plan_hosts"]

log = logging.getLogger(__name__)

#: Stream (on the ``safety`` node) where a ``halt_all`` fault reaches every process of the rig.
HALT = "halt"


@dataclass(frozen=True, slots=True)
class HostPlan:
    """What one child process runs: a robot, the devices bound only to it, and its cameras."""

    robot: str
    devices: tuple[str, ...]
    cameras: tuple[str, ...]


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
        #: What the child reported when ready: ``bound_topics``, ``has_home``.
        self.info: dict[str, Any] = {}

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
        self.info = self._reply(conn)

    def call(self, op: str, *args: Any, timeout_s: float = 60.0) -> Any:
        """Run ``op`` in the child and return its result.

        Raises:
            RobotError: the child raised (its message), died, or did not answer in time.
        """
        conn = self._require()
        try:
            conn.send((op, args))
            if not conn.poll(timeout_s):
                raise RobotError(f"robot {self.plan.robot!r}: {op} did not answer within {timeout_s:g} s")
        except (BrokenPipeError, EOFError, OSError):
            raise RobotError(f"robot {self.plan.robot!r}: its process died; see the log above") from None
        return self._reply(conn)

    def close(self, timeout_s: float = 15.0) -> None:
        """Stop the child's nodes (robots hold, then stop) and the process. Idempotent."""
        conn, process = self._conn, self._process
        self._conn = None
        if conn is not None:
            with contextlib.suppress(BrokenPipeError, EOFError, OSError):
                conn.send(("close", ()))
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
        self.call("begin_cameras", {name: str(path) for name, path in paths.items()})

    def end_cameras(self) -> dict[str, EncodeResult]:
        results: dict[str, EncodeResult] = self.call("end_cameras")
        return results

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
            raise RobotError(f"robot {self.plan.robot!r}: {value}")
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
    sys.setswitchinterval(0.001)  # as the station does: a woken control thread waits at most 1 ms
    keep_heap()  # as the station does: no heap trimming inside a control tick
    logging.basicConfig(level=logging.WARNING, format=f"{plan.robot}: %(message)s", stream=sys.stderr)
    from telerig.runtime.rig import RigRuntime

    try:
        config = RigConfig.model_validate_json(config_json)
        if config.runtime.realtime_priority is not None:
            set_realtime_priority(config.runtime.realtime_priority, f"robot {plan.robot}")
        runtime = RigRuntime(config, data_root=Path(data_root), station=station, broker_url=broker_url)
        runtime.open_nodes(broker_url, robots=(plan.robot,), devices=plan.devices, cameras=plan.cameras)
        release_heap()  # the expensive first heap trim now, not inside a control tick
    except Exception as exc:
        conn.send(("error", str(exc) or type(exc).__name__))
        return
    try:
        control = runtime.controls[plan.robot]
        conn.send(("ok", {"bound_topics": control.bound_topics, "has_home": control.has_home}))
        _serve(conn, runtime, plan.robot)
    finally:
        runtime.close()


class _Steps:
    """The station's per-episode requests, run on the child's nodes."""

    def __init__(self, runtime: Any, robot: str) -> None:
        self._runtime = runtime
        self._control = runtime.controls[robot]

    def prepare(self) -> None:
        self._runtime.prepare_nodes()

    def start_devices(self) -> None:
        for device in self._runtime.devices.values():
            device.start()

    def stop_devices(self) -> None:
        for device in self._runtime.devices.values():
            device.stop()

    def begin_cameras(self, paths: dict[str, str]) -> None:
        for name, camera in self._runtime.cameras.items():
            camera.begin(Path(paths[name]))

    def end_cameras(self) -> dict[str, EncodeResult]:
        results = {name: camera.end() for name, camera in self._runtime.cameras.items()}
        return {name: result for name, result in results.items() if result is not None}

    def latency_ns(self) -> list[int]:
        return [int(v) for v in self._control.latency.values_ns()]

    def safety_counts(self) -> dict[str, int]:
        return dict(self._control.safety.counts)

    def stats(self) -> dict[str, Any]:
        """The control node's counters and the simulated physics' timing, for benchmarks."""
        s = self._control.stats
        robot = self._control.robot
        physics = robot.stats() if callable(getattr(robot, "stats", None)) else None
        return {
            "inputs_skipped": s.inputs_skipped,
            "applied": s.applied,
            "ik_flagged": s.ik_flagged,
            "safety_events": dict(s.safety_events),
            "physics_realtime_factor": getattr(physics, "realtime_factor", None),
            "physics_overruns": getattr(physics, "overruns", None),
            "pid": os.getpid(),
        }

    def go_home(self, timeout_s: float) -> bool:
        return bool(self._control.go_home(timeout_s=timeout_s))

    def estop(self, reason: str) -> None:
        self._control.estop(reason)

    def fault(self, reason: str) -> None:
        """Report a hardware fault of the robot (e.g. from an external monitor): the rig's policy applies."""
        self._control.fault(reason)

    def estopped(self) -> bool:
        return bool(self._control.safety.estopped)

    def limits(self) -> JointLimits:
        limits: JointLimits = self._control.robot.limits
        return limits


def _serve(conn: Connection, runtime: Any, robot: str) -> None:
    steps = _Steps(runtime, robot)
    while True:
        try:
            op, args = conn.recv()
        except (EOFError, OSError):
            return  # the station is gone
        if op == "close":
            runtime.close()
            conn.send(("ok", None))
            return
        step: Callable[..., Any] | None = getattr(steps, op, None) if not op.startswith("_") else None
        if step is None:
            conn.send(("error", f"unknown request {op!r}"))
            continue
        try:
            conn.send(("ok", step(*args)))
        except Exception as exc:
            log.exception("%s failed", op)
            conn.send(("error", f"{op}: {exc}"))


def listen_for_halts(runtime: Any, rig: str) -> HaltListener:
    """Halt this process's robots when another process's robot faults under ``halt_all``.

    Notices are validated (:class:`~telerig.safety.commands.HaltNotice`); a malformed one, or one
    naming a robot the rig does not have, is counted in the listener's ``rejected`` and dropped.
    """
    return HaltListener(
        runtime.node_bus,
        rig,
        own=set(runtime.robots),
        rig_robots=[r.id for r in runtime.config.robots],
        halt=runtime.supervisor.estop_all,
    )


def halt_publisher(bus: Any, rig: str) -> Callable[[str, SafetyEvent], None]:
    """The supervisor hook that tells every process of the rig to halt (``halt_all``)."""
    topic = str(Topic(rig, "safety", HALT))

    def publish(robot: str, event: SafetyEvent) -> None:
        doc = {"robot": robot, "code": event.code, "reason": event.reason}
        bus.publish(topic, json.dumps(doc).encode(), qos=1)

    return publish


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
    main()
