"""A fake Dobot CR controller on 127.0.0.1: dashboard, motion and 8 ms feedback ports with a simulated arm."""

from __future__ import annotations

import asyncio
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from types import TracebackType
from typing import Literal

import numpy as np

from telerig.bus.peer_loop import PeerLoop
from telerig.errors import RobotError, WireError
from telerig.ir.types import FloatArray
from telerig.robots.dobot.driver import CR5_LIMITS
from telerig.robots.dobot.protocol import (
    Command,
    RobotMode,
    encode_feedback,
    format_reply,
    parse_command,
    split_commands,
)

__all__ = ["FakeDobot"]

_log = logging.getLogger(__name__)

_MOTION = frozenset(("servoj", "jointmovj"))


class FakeDobot:
    """A simulated CR arm behind the controller's three TCP/IP ports (a dry-run peer for :class:`DobotRobot`).

    Dashboard commands: ``EnableRobot``, ``DisableRobot``, ``ClearError``, ``ResetRobot``,
    ``Stop``, ``EmergencyStop`` (``()``/``(1)`` press, ``(0)`` release), ``RobotMode``,
    ``GetAngle``, ``SpeedFactor``, ``ToolDOExecute``/``ToolDO``. Motion commands ``ServoJ`` (joint
    targets [deg], optional ``t=`` [s], default 0.1) and ``JointMovJ`` are taken on the motion port,
    and on the dashboard port too with ``protocol="v4"``. Replies follow the controller:
    -10000 unknown command, -20000 wrong parameter count, -3000n parameter n not a number,
    -4000n parameter n out of range, -1 refused in the current mode (not enabled, e-stop).

    The arm moves each joint toward its target at ``|target - q| / t``, capped at the joint speed
    limit x ``SpeedFactor`` %. Every ``period_s`` each feedback client receives a 1440-byte packet
    whose ``TimeStamp`` is host time + ``clock_offset_ms``.

    Faults for tests: :meth:`inject_feedback` writes raw bytes into the feedback stream,
    :meth:`inject_reply` raw text into the motion replies, ``feedback_paused`` stops the packets,
    :meth:`drop_connections` closes every client connection, :meth:`stop` kills the controller.

    Args:
        host: Listening address.
        dashboard_port, motion_port, feedback_port: Ports (0 picks free ones; read the attributes
            of the same name after :meth:`start`).
        protocol: ``"v3"`` (motion port only) or ``"v4"`` (motion on the dashboard port as well;
            ``EmergencyStop(0)`` needed before ``ClearError``).
        initial_deg: Initial joint positions [deg]. Shape (6,).
        lower_deg, upper_deg: Joint ranges [deg]; CR5 by default. Shape (6,).
        max_speed_deg_s: Joint speed limit at 100 % [deg/s].
        period_s: Feedback and simulation period [s] (0.008 on the controller).
        clock_offset_ms: Controller clock minus host clock [ms].
    """

    def __init__(
        self,
        *,
        host: str = "127.0.0.1",
        dashboard_port: int = 29999,
        motion_port: int = 30003,
        feedback_port: int = 30004,
        protocol: Literal["v3", "v4"] = "v3",
        initial_deg: Sequence[float] = (0.0, 0.0, 90.0, 0.0, -90.0, 0.0),
        lower_deg: Sequence[float] | None = None,
        upper_deg: Sequence[float] | None = None,
        max_speed_deg_s: float = 180.0,
        period_s: float = 0.008,
        clock_offset_ms: int = 0,
    ) -> None:
        if not (math.isfinite(period_s) and 0.001 <= period_s <= 1.0):
            raise RobotError(f"period_s must be in [0.001, 1] s, got {period_s}")
        self.host = host
        self.protocol = protocol
        self.dashboard_port = dashboard_port
        self.motion_port = motion_port
        self.feedback_port = feedback_port
        self.period_s = period_s
        self.clock_offset_ms = clock_offset_ms
        self.max_speed_deg_s = max_speed_deg_s
        self.lower_deg = np.degrees(CR5_LIMITS.lower) if lower_deg is None else np.array(lower_deg, float)
        self.upper_deg = np.degrees(CR5_LIMITS.upper) if upper_deg is None else np.array(upper_deg, float)
        self.feedback_paused = False

        self._lock = threading.Lock()  # guards the simulated robot below
        self._q = np.array(initial_deg, dtype=np.float64)
        if self._q.shape != (6,):
            raise RobotError(f"initial_deg must have 6 values, got {self._q.shape}")
        self._qd = np.zeros(6)
        self._target: FloatArray | None = None
        self._speed = np.zeros(6)  # per-joint speed toward the target [deg/s]
        self._mode = RobotMode.DISABLED
        self._estop_pressed = False
        self._speed_factor = 100
        self.tool_do: dict[int, int] = {}
        self.commands: deque[str] = deque(maxlen=10_000)
        self.estop_count = 0
        self.servo_count = 0

        self._servers: list[asyncio.Server] = []
        self._writers: set[asyncio.StreamWriter] = set()
        self._feedback_writers: set[asyncio.StreamWriter] = set()
        self._motion_writers: set[asyncio.StreamWriter] = set()

        self._peer = PeerLoop(
            self._main, what="fake Dobot", thread_name="telerig-fake-dobot", error=RobotError
        )

    # -- lifecycle ----------------------------------------------------------------------------

    def start(self) -> FakeDobot:
        """Listen on the three ports from a background thread; returns once listening."""
        self._peer.start()
        return self

    def stop(self) -> None:
        """Kill the controller: abort every connection and stop listening. Idempotent."""
        self._peer.stop()

    def __enter__(self) -> FakeDobot:
        return self.start()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()

    # -- inspection and faults ----------------------------------------------------------------

    @property
    def q_deg(self) -> FloatArray:
        """Current joint positions [deg]. Shape (6,)."""
        with self._lock:
            return self._q.copy()

    @property
    def mode(self) -> RobotMode:
        """Current robot mode."""
        with self._lock:
            return self._mode

    @property
    def speed_factor(self) -> int:
        """Global speed ratio [%]."""
        with self._lock:
            return self._speed_factor

    def inject_feedback(self, data: bytes) -> None:
        """Write raw bytes into every feedback stream (e.g. a truncated or corrupt packet)."""
        self._call(lambda: self._broadcast(self._feedback_writers, data))

    def inject_reply(self, text: str) -> None:
        """Write raw text into every motion-port reply stream."""
        self._call(lambda: self._broadcast(self._motion_writers, text.encode("ascii", errors="replace")))

    def drop_connections(self) -> None:
        """Abort every client connection; keep listening."""
        self._call(self._abort_all)

    # -- internals ----------------------------------------------------------------------------

    def _call(self, fn: Callable[[], object]) -> None:
        self._peer.call(fn)

    @staticmethod
    def _broadcast(writers: set[asyncio.StreamWriter], data: bytes) -> None:
        for w in list(writers):
            if not w.is_closing():
                w.write(data)

    def _abort_all(self) -> None:
        for w in list(self._writers):
            w.transport.abort()
        self._writers.clear()
        self._feedback_writers.clear()
        self._motion_writers.clear()

    async def _main(self, ready: Callable[[], None], done: asyncio.Event) -> None:
        specs = (
            ("dashboard_port", self._serve_dashboard),
            ("motion_port", self._serve_motion),
            ("feedback_port", self._serve_feedback),
        )
        try:
            for attr, handler in specs:
                server = await asyncio.start_server(handler, self.host, getattr(self, attr))
                self._servers.append(server)
                setattr(self, attr, server.sockets[0].getsockname()[1])
            ticker = asyncio.create_task(self._tick())
            ready()
            await done.wait()
            ticker.cancel()
        finally:
            for server in self._servers:
                server.close()
            self._abort_all()
            for server in self._servers:
                await server.wait_closed()
            self._servers.clear()

    async def _tick(self) -> None:
        period = self.period_s
        next_t = time.monotonic()
        while True:
            next_t += period
            await asyncio.sleep(max(0.0, next_t - time.monotonic()))
            if time.monotonic() - next_t > 10 * period:
                next_t = time.monotonic()  # fell far behind (loaded machine): do not burst
            packet = self._step(period)
            if not self.feedback_paused:
                for w in list(self._feedback_writers):
                    if w.is_closing() or w.transport.get_write_buffer_size() > 1 << 20:
                        self._feedback_writers.discard(w)
                        w.transport.abort()  # a client that stopped reading
                    else:
                        w.write(packet)

    def _step(self, dt: float) -> bytes:
        with self._lock:
            q_before = self._q.copy()
            if self._target is not None and self._mode in (RobotMode.ENABLE, RobotMode.RUNNING):
                step = np.clip(self._target - self._q, -self._speed * dt, self._speed * dt)
                self._q = self._q + step
                moving = bool(np.any(np.abs(self._target - self._q) > 1e-9))
                self._mode = RobotMode.RUNNING if moving else RobotMode.ENABLE
                if not moving:
                    self._target = None
            self._qd = (self._q - q_before) / dt
            return encode_feedback(
                robot_mode=int(self._mode),
                timestamp_ms=time.time_ns() // 1_000_000 + self.clock_offset_ms,
                q_actual=self._q,
                qd_actual=self._qd,
                q_target=self._q if self._target is None else self._target,
                velocity_ratio=self._speed_factor,
            )

    async def _serve_feedback(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self._writers.add(writer)
        self._feedback_writers.add(writer)
        try:
            while await reader.read(4096):
                pass  # the feedback port ignores what clients send
        except OSError:
            pass
        finally:
            self._forget(writer)

    async def _serve_dashboard(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        await self._serve_text(reader, writer, dashboard=True)

    async def _serve_motion(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self._motion_writers.add(writer)
        await self._serve_text(reader, writer, dashboard=False)

    async def _serve_text(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, *, dashboard: bool
    ) -> None:
        self._writers.add(writer)
        buf = ""
        try:
            while data := await reader.read(65536):
                commands, buf = split_commands(buf + data.decode("ascii", errors="replace"))
                for text in commands:
                    self.commands.append(text)
                    writer.write(self._handle(text, dashboard=dashboard).encode("ascii"))
        except OSError:
            pass
        finally:
            self._forget(writer)

    def _forget(self, writer: asyncio.StreamWriter) -> None:
        for group in (self._writers, self._feedback_writers, self._motion_writers):
            group.discard(writer)
        writer.transport.abort()

    def _handle(self, text: str, *, dashboard: bool) -> str:
        try:
            cmd = parse_command(text)
        except WireError:
            return format_reply(-10000, (), text)
        name = cmd.name.lower()
        if name in _MOTION and (not dashboard or self.protocol == "v4"):
            return self._motion_command(cmd)
        if dashboard and name not in _MOTION:
            return self._dashboard_command(cmd)
        return format_reply(-10000, (), cmd.text)

    def _dashboard_command(self, cmd: Command) -> str:
        name, n = cmd.name.lower(), len(cmd.args)
        with self._lock:
            if name == "enablerobot":
                if n not in (0, 1, 4):
                    return format_reply(-20000, (), cmd.text)
                if self._mode == RobotMode.ERROR or self._estop_pressed:
                    return format_reply(-1, (), cmd.text)
                if self._mode not in (RobotMode.ENABLE, RobotMode.RUNNING):
                    self._mode = RobotMode.ENABLE
                return format_reply(0, (), cmd.text)
            if name == "disablerobot":
                if self._mode != RobotMode.ERROR:
                    self._mode = RobotMode.DISABLED
                self._target = None
                return format_reply(0, (), cmd.text)
            if name == "clearerror":
                if self._mode == RobotMode.ERROR and not (self._estop_pressed and self.protocol == "v4"):
                    self._mode = RobotMode.DISABLED
                    self._estop_pressed = False
                return format_reply(0, (), cmd.text)
            if name in ("resetrobot", "stop"):
                self._target = None
                return format_reply(0, (), cmd.text)
            if name == "emergencystop":
                if cmd.args in ((), ("1",)):
                    self._estop_pressed = True
                    self._mode = RobotMode.ERROR
                    self._target = None
                    self.estop_count += 1
                elif cmd.args == ("0",):
                    self._estop_pressed = False
                else:
                    return format_reply(-40001, (), cmd.text)
                return format_reply(0, (), cmd.text)
            if name == "robotmode":
                return format_reply(0, (int(self._mode),), cmd.text)
            if name == "getangle":
                return format_reply(0, [float(v) for v in self._q], cmd.text)
            if name == "speedfactor":
                if n != 1:
                    return format_reply(-20000, (), cmd.text)
                try:
                    ratio = int(cmd.args[0])
                except ValueError:
                    return format_reply(-30001, (), cmd.text)
                if not 1 <= ratio <= 100:
                    return format_reply(-40001, (), cmd.text)
                self._speed_factor = ratio
                return format_reply(0, (), cmd.text)
            if name in ("tooldoexecute", "tooldo"):
                if n != 2:
                    return format_reply(-20000, (), cmd.text)
                try:
                    index, level = int(cmd.args[0]), int(cmd.args[1])
                except ValueError:
                    return format_reply(-30001, (), cmd.text)
                if level not in (0, 1):
                    return format_reply(-40002, (), cmd.text)
                self.tool_do[index] = level
                return format_reply(0, (), cmd.text)
        return format_reply(-10000, (), cmd.text)

    def _motion_command(self, cmd: Command) -> str:
        if len(cmd.args) != 6:
            return format_reply(-20000, (), cmd.text)
        values = []
        for i, raw in enumerate(cmd.args):
            try:
                v = float(raw)
            except ValueError:
                return format_reply(-30001 - i, (), cmd.text)
            if not (math.isfinite(v) and self.lower_deg[i] <= v <= self.upper_deg[i]):
                return format_reply(-40001 - i, (), cmd.text)
            values.append(v)
        try:
            t = float(cmd.kwargs.get("t", "0.1"))
        except ValueError:
            return format_reply(-30007, (), cmd.text)
        if not (math.isfinite(t) and t > 0):
            return format_reply(-40007, (), cmd.text)
        target = np.array(values)
        with self._lock:
            if self._mode not in (RobotMode.ENABLE, RobotMode.RUNNING):
                return format_reply(-1, (), cmd.text)
            vmax = self.max_speed_deg_s * self._speed_factor / 100.0
            if cmd.name.lower() == "servoj":
                self._speed = np.minimum(np.abs(target - self._q) / t, vmax)
                self.servo_count += 1
            else:
                self._speed = np.full(6, vmax)
            self._target = target
        return format_reply(0, (), cmd.text)
