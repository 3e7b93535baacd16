"""A fake rosbridge server on 127.0.0.1: a simulated robot publishing joint states and following commands."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from types import TracebackType
from typing import Any, Literal

import numpy as np
from websockets.asyncio.server import Server, ServerConnection, serve
from websockets.exceptions import ConnectionClosed

from telerig.bus.peer_loop import PeerLoop
from telerig.errors import RobotError, WireError
from telerig.ir.types import FloatArray
from telerig.robots.rosbridge.protocol import (
    BOOL,
    JOINT_STATE,
    JOINT_TRAJECTORY,
    CommandType,
    canonical_type,
    decode,
    encode,
    joint_state,
    parse_command,
    publish,
    status,
)

__all__ = ["FakeRosbridge"]

_log = logging.getLogger(__name__)


class _Client:
    """What one connection advertised and subscribed to."""

    def __init__(self, ws: ServerConnection) -> None:
        self.ws = ws
        self.advertised: dict[str, str] = {}
        self.subscribed: dict[str, str] = {}


class FakeRosbridge:
    """rosbridge_server's protocol subset over a simulated robot (a dry-run peer for :class:`RosbridgeRobot`).

    Serves ``ws://127.0.0.1:<port>``; handles ``advertise``, ``unadvertise``, ``publish``,
    ``subscribe`` and ``unsubscribe``, answering bad requests with ``status`` errors as rosbridge
    does. The robot publishes ``sensor_msgs/JointState`` on ``state_topic`` at ``rate_hz`` to every
    subscriber (stamp = host time + ``clock_offset_ns``) and follows commands on ``command_topic``:
    a ``JointTrajectory`` point is reached after its ``time_from_start``, a ``Float64MultiArray``
    target at ``max_velocity``; speed is capped at ``max_velocity`` either way. ``True`` on
    ``estop_topic`` (``std_msgs/Bool``) stops it and ignores commands until ``False``.

    Faults for tests: ``omit_joint`` leaves a joint out of the states, ``paused`` stops them,
    :meth:`inject` sends raw text to every client, :meth:`drop_connections` closes them,
    :meth:`stop` kills the server.

    Args:
        joint_names: Robot joints. Length n.
        initial: Initial positions [rad]; zeros when None. Shape (n,).
        max_velocity: Joint speed limit [rad/s], scalar or shape (n,).
        rate_hz: JointState rate [Hz].
        port: TCP port (0 picks a free one; read :attr:`port` after :meth:`start`).
        state_topic, command_topic, command_type, estop_topic: Topics and the command type.
        clock_offset_ns: Robot ROS clock minus host clock [ns].
        extra_joints: Joints published at 0 rad but not commanded (a gripper, a second arm).
        null_fields: JointState fields (``"velocity"``, ``"effort"``, ``"position"``) published
            as JSON null for every joint: what rosbridge sends for the NaN that ROS 2's
            joint_state_broadcaster fills in for a joint without that state interface.
    """

    def __init__(
        self,
        joint_names: Sequence[str],
        *,
        initial: Sequence[float] | None = None,
        max_velocity: float | Sequence[float] = 1.0,
        rate_hz: float = 100.0,
        host: str = "127.0.0.1",
        port: int = 0,
        state_topic: str = "/joint_states",
        command_topic: str = "/joint_trajectory_controller/joint_trajectory",
        command_type: CommandType = "trajectory_msgs/JointTrajectory",
        estop_topic: str | None = "/telerig/estop",
        clock_offset_ns: int = 0,
        extra_joints: Sequence[str] = (),
        null_fields: Sequence[Literal["position", "velocity", "effort"]] = (),
    ) -> None:
        if not (math.isfinite(rate_hz) and 0 < rate_hz <= 1000):
            raise RobotError(f"rate_hz must be in (0, 1000], got {rate_hz}")
        self.joint_names = tuple(joint_names)
        n = len(self.joint_names)
        self.host = host
        self.port = port
        self.rate_hz = rate_hz
        self.state_topic = state_topic
        self.command_topic = command_topic
        self.command_type = command_type
        self.estop_topic = estop_topic
        self.clock_offset_ns = clock_offset_ns
        self.extra_joints = tuple(extra_joints)
        self.null_fields = tuple(null_fields)
        self.max_velocity = np.broadcast_to(np.asarray(max_velocity, dtype=np.float64), (n,)).copy()
        self.omit_joint: str | None = None
        self.paused = False

        self._lock = threading.Lock()  # guards the simulated robot
        self._q = np.zeros(n) if initial is None else np.array(initial, dtype=np.float64)
        self._qd = np.zeros(n)
        self._target: FloatArray | None = None
        self._speed = np.zeros(n)
        self._estopped = False
        self.received: deque[dict[str, Any]] = deque(maxlen=10_000)
        self.commands = 0
        self.malformed = 0
        self.connections = 0

        self._clients: dict[ServerConnection, _Client] = {}
        self._server: Server | None = None

        self._peer = PeerLoop(
            self._main, what="fake rosbridge", thread_name="telerig-fake-rosbridge", error=RobotError
        )

    # -- lifecycle ----------------------------------------------------------------------------

    @property
    def url(self) -> str:
        """WebSocket URL a client connects to (valid after :meth:`start`)."""
        return f"ws://{self.host}:{self.port}"

    def start(self) -> FakeRosbridge:
        """Serve from a background thread; returns once listening."""
        self._peer.start()
        return self

    def stop(self) -> None:
        """Kill the server and every connection. Idempotent; :meth:`start` serves again on the same port."""
        self._peer.stop()

    def __enter__(self) -> FakeRosbridge:
        return self.start()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()

    # -- inspection and faults ----------------------------------------------------------------

    @property
    def positions(self) -> FloatArray:
        """Current joint positions [rad]. Shape (n,)."""
        with self._lock:
            return self._q.copy()

    @property
    def estopped(self) -> bool:
        """Whether ``True`` was last published on the e-stop topic."""
        with self._lock:
            return self._estopped

    def inject(self, text: str) -> None:
        """Send raw text (e.g. malformed JSON) to every connected client."""
        self._call(
            lambda: [asyncio.ensure_future(self._send(c.ws, text)) for c in list(self._clients.values())]
        )

    def drop_connections(self) -> None:
        """Close every client connection; keep listening."""

        def abort() -> None:
            for client in list(self._clients.values()):
                client.ws.transport.abort()

        self._call(abort)

    # -- internals ----------------------------------------------------------------------------

    def _call(self, fn: Callable[[], object]) -> None:
        self._peer.call(fn)

    async def _main(self, ready: Callable[[], None], done: asyncio.Event) -> None:
        try:
            async with serve(
                self._handle, self.host, self.port, compression=None, ping_interval=None
            ) as server:
                self._server = server
                self.port = next(iter(server.sockets)).getsockname()[1]
                ticker = asyncio.create_task(self._tick())
                ready()
                await done.wait()
                ticker.cancel()
                for client in list(self._clients.values()):
                    client.ws.transport.abort()
        finally:
            self._server = None

    async def _tick(self) -> None:
        period = 1.0 / self.rate_hz
        next_t = time.monotonic()
        while True:
            next_t += period
            await asyncio.sleep(max(0.0, next_t - time.monotonic()))
            if time.monotonic() - next_t > 10 * period:
                next_t = time.monotonic()
            text = self._step(period)
            if self.paused:
                continue
            for client in list(self._clients.values()):
                if self.state_topic in client.subscribed:
                    await self._send(client.ws, text)

    def _step(self, dt: float) -> str:
        with self._lock:
            before = self._q.copy()
            if self._target is not None and not self._estopped:
                self._q = self._q + np.clip(self._target - self._q, -self._speed * dt, self._speed * dt)
            self._qd = (self._q - before) / dt
            keep = [i for i, j in enumerate(self.joint_names) if j != self.omit_joint]
            extra = len(self.extra_joints)
            msg = joint_state(
                [self.joint_names[i] for i in keep] + list(self.extra_joints),
                np.concatenate([self._q[keep], np.zeros(extra)]),
                np.concatenate([self._qd[keep], np.zeros(extra)]),
                np.zeros(len(keep) + extra),
                stamp_ns=time.time_ns() + self.clock_offset_ns,
            )
        for name in self.null_fields:
            msg[name] = [None] * len(msg["name"])
        return encode(publish(self.state_topic, msg))

    @staticmethod
    async def _send(ws: ServerConnection, text: str) -> None:
        with contextlib.suppress(ConnectionClosed):
            await ws.send(text)

    async def _handle(self, ws: ServerConnection) -> None:
        client = _Client(ws)
        self._clients[ws] = client
        self.connections += 1
        try:
            async for text in ws:
                reply = self._on_op(client, text)
                if reply is not None:
                    await self._send(ws, encode(reply))
        except ConnectionClosed:
            pass
        finally:
            self._clients.pop(ws, None)

    def _on_op(self, client: _Client, text: str | bytes) -> dict[str, Any] | None:
        try:
            op = decode(text)
        except WireError as exc:
            self.malformed += 1
            return status("error", str(exc))
        self.received.append(op)
        kind, topic, op_id = op["op"], op.get("topic"), op.get("id")
        if kind == "call_service":
            return self._on_call_service(op)
        if not isinstance(topic, str):
            return status("error", f"{kind}: missing 'topic'", op_id)
        if kind == "advertise":
            type_name = op.get("type")
            if not isinstance(type_name, str):
                return status("error", f"advertise {topic}: missing 'type'", op_id)
            client.advertised[topic] = canonical_type(type_name)
        elif kind == "unadvertise":
            client.advertised.pop(topic, None)
        elif kind == "subscribe":
            type_name = op.get("type", JOINT_STATE)
            if topic == self.state_topic and canonical_type(str(type_name)) != JOINT_STATE:
                return status("error", f"subscribe {topic}: type is {JOINT_STATE}, not {type_name}", op_id)
            client.subscribed[topic] = str(op_id)
        elif kind == "unsubscribe":
            client.subscribed.pop(topic, None)
        elif kind == "publish":
            # rosbridge takes the type of an existing topic when the client did not advertise it:
            # the robot subscribes to its command and e-stop topics.
            type_name = client.advertised.get(topic) or self._subscribed_types().get(topic)
            if type_name is None:
                return status(
                    "error", f"publish {topic}: topic not advertised and its type is unknown", op_id
                )
            return self._on_publish(topic, type_name, op.get("msg"))
        else:
            return status("error", f"unknown operation {kind!r}", op_id)
        return None

    def _subscribed_types(self) -> dict[str, str]:
        """Topics the simulated robot subscribes to, with their types."""
        types = {self.command_topic: canonical_type(self.command_type)}
        if self.estop_topic is not None:
            types[self.estop_topic] = BOOL
        return types

    def _on_call_service(self, op: dict[str, Any]) -> dict[str, Any]:
        """rosapi's topic list and clock (rosbridge's launch file starts rosapi); any other service
        gets rosbridge's failed ``service_response``."""
        service = op.get("service")
        values: Any
        if service == "/rosapi/topics":
            topics = {self.state_topic: JOINT_STATE, **self._subscribed_types()}
            values = {"topics": list(topics), "types": list(topics.values())}
            result = True
        elif service == "/rosapi/get_time":
            now = time.time_ns() + self.clock_offset_ns
            values = {"time": {"sec": now // 1_000_000_000, "nanosec": now % 1_000_000_000}}
            result = True
        else:
            values, result = f"Service {service} does not exist", False
        reply: dict[str, Any] = {
            "op": "service_response",
            "service": service,
            "values": values,
            "result": result,
        }
        if "id" in op:
            reply["id"] = op["id"]
        return reply

    def _on_publish(self, topic: str, type_name: str, msg: Any) -> dict[str, Any] | None:
        if topic == self.estop_topic:
            if type_name != BOOL or not isinstance(msg, dict) or not isinstance(msg.get("data"), bool):
                return status("error", f"publish {topic}: expected {BOOL}")
            with self._lock:
                self._estopped = msg["data"]
                self._target = None
            return None
        if topic != self.command_topic:
            return None  # a topic nobody here listens to
        try:
            target = parse_command(type_name, msg, self.joint_names)
        except WireError as exc:
            self.malformed += 1
            return status("error", f"publish {topic}: {exc}")
        horizon = 0.0
        if type_name == canonical_type(JOINT_TRAJECTORY):
            tfs = msg["points"][-1].get("time_from_start", {})
            if isinstance(tfs, dict):
                horizon = float(tfs.get("sec", 0)) + float(tfs.get("nanosec", 0)) * 1e-9
        with self._lock:
            if self._estopped:
                return None
            speed = np.abs(target - self._q) / horizon if horizon > 0 else self.max_velocity
            self._speed = np.minimum(speed, self.max_velocity)
            self._target = target
            self.commands += 1
        return None
