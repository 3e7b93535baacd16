"""Dobot CR-series arm driver over the controller's TCP/IP interface (dashboard, motion, feedback ports)."""

from __future__ import annotations

import contextlib
import logging
import math
import socket
import threading
import time
from collections.abc import Callable
from types import TracebackType
from typing import Literal

import numpy as np

from telerig.errors import RobotError, WireError
from telerig.ir.clock import ClockOffsetEstimator
from telerig.ir.types import FloatArray, GripperCommand, JointCommand, JointState, Stamp, now_ns
from telerig.robots.base import JointLimits
from telerig.robots.dobot.protocol import (
    FeedbackFramer,
    FeedbackPacket,
    Reply,
    RobotMode,
    format_command,
    parse_reply,
    split_replies,
)

__all__ = ["CR5_ACCELERATION_LIMIT", "CR5_JOINTS", "CR5_LIMITS", "CR5_VELOCITY_LIMIT", "DobotRobot"]

_log = logging.getLogger(__name__)

#: Joint names of the CR5, as in Dobot's ``cr5_robot.urdf``.
CR5_JOINTS = ("joint1", "joint2", "joint3", "joint4", "joint5", "joint6")
#: CR5 maximum joint speed [rad/s]: 180 deg/s for every joint (Dobot CR5 datasheet).
CR5_VELOCITY_LIMIT = math.pi
#: Joint acceleration limit [rad/s^2]. Dobot publishes none per joint; a conservative
#: teleoperation value (the same as the UR5e sim driver's).
CR5_ACCELERATION_LIMIT = 8.0
#: CR5 limits. Position ranges from Dobot's ``DOBOT_6Axis_ROS2_V4/dobot_rviz/urdf/cr5_robot.urdf``
#: (+-6.27 rad, J3 +-2.86 rad; the datasheet says +-360 deg and J3 +-160 deg).
CR5_LIMITS = JointLimits(
    names=CR5_JOINTS,
    lower=np.array([-6.27, -6.27, -2.86, -6.27, -6.27, -6.27]),
    upper=np.array([6.27, 6.27, 2.86, 6.27, 6.27, 6.27]),
    velocity=np.full(6, CR5_VELOCITY_LIMIT),
    acceleration=np.full(6, CR5_ACCELERATION_LIMIT),
)

_ENABLED_MODES = frozenset((RobotMode.ENABLE, RobotMode.RUNNING, RobotMode.JOG))


def _mode_name(mode: int) -> str:
    try:
        return RobotMode(mode).name
    except ValueError:
        return f"unknown ({mode})"


class DobotRobot:
    """A Dobot CR-series arm (CR5 limits by default), implementing :class:`~telerig.robots.base.RobotDriver`.

    Three TCP connections to the controller: the dashboard port (request/reply: ``ClearError()``,
    ``EnableRobot()``, ``SpeedFactor(n)``, ``EmergencyStop()``), the motion port (``ServoJ`` streamed
    without waiting; a thread reads and counts the replies) and the real-time feedback port (one
    1440-byte packet every 8 ms, read on a thread). With ``motion_port=None`` (V4 controllers, which
    take motion commands on the dashboard port) each ``ServoJ`` waits for its reply.

    Units: telerig radians in and out; degrees on the wire. State stamps: ``device_ns`` = the
    packet's controller ``TimeStamp`` [ms] x 1e6 (1 ms resolution), ``capture_ns`` = that mapped to
    host time with a windowed-minimum offset estimate
    (:class:`~telerig.ir.clock.ClockOffsetEstimator`), ``arrival_ns`` = when the packet was read.

    E-stop: :meth:`estop` sends ``EmergencyStop()`` (V3) or ``EmergencyStop(1)`` (V4) and latches;
    :meth:`send` then transmits nothing and returns the position held at the stop, until
    :meth:`reset_estop` (``EmergencyStop(0)`` on V4, ``ClearError()``, ``EnableRobot()``).

    A closed feedback or motion connection, a failed write, or no feedback for
    ``stale_timeout_s`` makes :meth:`read_state` and :meth:`send` raise a one-line
    :class:`~telerig.errors.RobotError`; :meth:`connect` then opens new connections.

    Args:
        host: Controller address (192.168.5.1 on the CR LAN port by default).
        name: Driver name; the stamps' ``source_id``.
        dashboard_port: Dashboard port (29999).
        motion_port: Motion port (30003, V3), or None to send motion on the dashboard port (V4).
        feedback_port: Real-time feedback port (30004, 8 ms).
        protocol: ``"v3"`` or ``"v4"``: the form of ``EmergencyStop`` and its release.
        limits: Joint limits [rad] in controller joint order; :data:`CR5_LIMITS` by default.
        speed_factor: Global speed ratio set with ``SpeedFactor(n)`` on connect [%], 1..100.
        servo_time_s: ``t=`` of every ``ServoJ`` (time to reach the point [s]); None omits it.
        enable_on_connect: Send ``ClearError()`` + ``EnableRobot()`` on connect and wait until enabled.
        disable_on_close: Send ``DisableRobot()`` on close.
        gripper_tool_do: Tool digital output driving a binary gripper (``ToolDOExecute``), or None.
        gripper_close_level: Output level (0 or 1) that closes that gripper.
        timeout_s: Connect, reply and enable timeout [s].
        stale_timeout_s: Feedback silence that counts as a lost connection [s].
    """

    def __init__(
        self,
        host: str = "192.168.5.1",
        *,
        name: str = "dobot",
        dashboard_port: int = 29999,
        motion_port: int | None = 30003,
        feedback_port: int = 30004,
        protocol: Literal["v3", "v4"] = "v3",
        limits: JointLimits = CR5_LIMITS,
        speed_factor: int = 50,
        servo_time_s: float | None = 0.1,
        enable_on_connect: bool = True,
        disable_on_close: bool = True,
        gripper_tool_do: int | None = None,
        gripper_close_level: int = 1,
        timeout_s: float = 2.0,
        stale_timeout_s: float = 0.5,
    ) -> None:
        if len(limits.names) != 6:
            raise RobotError(f"a Dobot CR arm has 6 joints; limits name {len(limits.names)}")
        if not 1 <= speed_factor <= 100:
            raise RobotError(f"speed_factor must be in 1..100 [%], got {speed_factor}")
        if servo_time_s is not None and not 0.004 <= servo_time_s <= 3600.0:
            raise RobotError(f"servo_time_s must be in [0.004, 3600] s or None, got {servo_time_s}")
        if protocol not in ("v3", "v4"):
            raise RobotError(f"protocol must be 'v3' or 'v4', got {protocol!r}")
        for label, value in (("timeout_s", timeout_s), ("stale_timeout_s", stale_timeout_s)):
            if not (math.isfinite(value) and value > 0):
                raise RobotError(f"{label} must be > 0 s, got {value}")
        self._name = name
        self.host = host
        self.dashboard_port = dashboard_port
        self.motion_port = motion_port
        self.feedback_port = feedback_port
        self.protocol = protocol
        self._limits = limits
        self._lower_deg = np.degrees(limits.lower)
        self._upper_deg = np.degrees(limits.upper)
        self.speed_factor = speed_factor
        self.servo_time_s = servo_time_s
        self.enable_on_connect = enable_on_connect
        self.disable_on_close = disable_on_close
        self.gripper_tool_do = gripper_tool_do
        self.gripper_close_level = gripper_close_level
        self.timeout_s = timeout_s
        self.stale_timeout_s = stale_timeout_s
        self._index = {j: i for i, j in enumerate(limits.names)}

        self._lock = threading.Lock()  # guards the state below
        self._dash_lock = threading.Lock()  # one dashboard request at a time
        self._motion_lock = threading.Lock()
        self._dash: socket.socket | None = None
        self._motion: socket.socket | None = None
        self._feedback: socket.socket | None = None
        self._dash_buf = ""
        self._threads: list[threading.Thread] = []
        self._stop = threading.Event()
        self._first_packet = threading.Event()
        self._packet: FeedbackPacket | None = None
        self._packet_arrival_ns = 0
        self._packet_capture_ns = 0
        self._state_seq = 0
        self._clock = ClockOffsetEstimator(reset_ns=1_000_000_000)
        self._framer = FeedbackFramer()
        self._connected = False
        self._closed = False
        self._lost: str | None = None
        self._estopped = False
        self._hold_deg: FloatArray = np.zeros(6)
        self._target_deg: FloatArray = np.zeros(6)
        self._gripper_opening = 0.0
        self._cmd_seq = 0
        self._grip_seq = 0
        self._stats: dict[str, int] = dict.fromkeys(
            ("commands", "motion_replies", "motion_errors", "malformed_replies", "stale_replies", "connects"),
            0,
        )

    # -- RobotDriver --------------------------------------------------------------------------

    @property
    def name(self) -> str:
        """Driver name, used as the stamps' ``source_id``."""
        return self._name

    @property
    def joint_names(self) -> tuple[str, ...]:
        """Arm joints J1..J6, base to tool."""
        return self._limits.names

    @property
    def limits(self) -> JointLimits:
        """Joint position [rad], speed [rad/s] and acceleration [rad/s^2] limits."""
        return self._limits

    @property
    def connected(self) -> bool:
        """Whether all connections are open and none was lost."""
        return self._connected and self._lost is None

    @property
    def estopped(self) -> bool:
        """Whether the emergency stop is latched."""
        return self._estopped

    @property
    def robot_mode(self) -> int | None:
        """``RobotMode`` of the latest feedback packet, None before the first."""
        with self._lock:
            return None if self._packet is None else self._packet.robot_mode

    @property
    def stats(self) -> dict[str, int]:
        """Counters: ``packets``, ``malformed`` and ``resyncs`` (feedback), ``commands`` (ServoJ sent),
        ``motion_replies``, ``motion_errors`` (non-zero ErrorID), ``malformed_replies``,
        ``stale_replies`` (a reply to an earlier request), ``connects``."""
        with self._lock:
            out = dict(self._stats)
            out.update(
                packets=self._framer.packets, malformed=self._framer.malformed, resyncs=self._framer.resyncs
            )
        return out

    def connect(self) -> None:
        """Open the three connections, wait for feedback, and (by default) clear alarms and enable.

        Idempotent while connected; after a lost connection it reconnects.

        Raises:
            RobotError: the driver is closed, a port cannot be reached, no feedback arrives, or the
                controller refuses to enable (the message says which and what to check).
        """
        if self._closed:
            raise RobotError(f"{self._name}: driver is closed; create a new one")
        if self.connected:
            return
        self._teardown()
        try:
            self._open()
        except BaseException:
            self._teardown()
            raise
        self._connected = True
        _log.info("%s: connected to %s (mode %s)", self._name, self.host, _mode_name(self.robot_mode or 0))

    def read_state(self) -> JointState:
        """Latest measured joint positions [rad], velocities [rad/s] and torques [N m].

        Each read is one sample: ``seq`` counts reads (packets received are in :attr:`stats`).

        Raises:
            RobotError: not connected, the connection was lost, or feedback is stale.
        """
        self._require_ok()
        with self._lock:
            packet, arrival, capture = self._packet, self._packet_arrival_ns, self._packet_capture_ns
            # One sample per read, as every driver numbers them: a per-packet number would make the
            # recorder count the packets a slower control loop never read as dropped samples.
            seq = self._state_seq
            self._state_seq += 1
        assert packet is not None  # connect() waited for the first packet
        stamp = Stamp(self._name, seq, device_ns=packet.timestamp_ms * 1_000_000, capture_ns=capture)
        return JointState(
            stamp.arrived(arrival),
            self.joint_names,
            np.radians(packet.q_actual),
            np.radians(packet.qd_actual),
            packet.m_actual,
        )

    def send(self, command: JointCommand) -> JointCommand:
        """Stream a ``ServoJ`` to the clipped targets [rad] (any subset of joints; the others keep
        their last target). Feed-forward velocities are ignored.

        While the e-stop is latched nothing is sent and the held position is returned.

        Returns:
            The targets sent for ``command.names`` [rad], stamped when they were written.

        Raises:
            RobotError: unknown joint, not connected, connection lost, or the robot is not enabled.
        """
        self._require_ok()
        idx = self._indices(command.names)
        if self._estopped:
            return self._stamped(command.names, np.radians(self._hold_deg[idx]))
        mode = self.robot_mode
        if mode not in _ENABLED_MODES:
            raise RobotError(
                f"{self._name}: robot is not enabled (mode {_mode_name(mode or 0)}); "
                "clear the alarm and call reset_estop() or enable it on the pendant"
            )
        target = self._target_deg.copy()
        target[idx] = np.clip(np.degrees(command.positions), self._lower_deg[idx], self._upper_deg[idx])
        extra = {} if self.servo_time_s is None else {"t": float(self.servo_time_s)}
        text = format_command("ServoJ", *(float(v) for v in target), **extra)
        if self.motion_port is None:
            reply = self._request(text)
            if not reply.ok:
                raise RobotError(f"{self._name}: controller refused {text} with ErrorID {reply.error_id}")
        else:
            self._write_motion(text)
        self._target_deg = target
        with self._lock:
            self._stats["commands"] += 1
        return self._stamped(command.names, np.radians(target[idx]))

    @property
    def has_gripper(self) -> bool:
        """Whether a gripper is configured (``gripper_tool_do``)."""
        return self.gripper_tool_do is not None

    def send_gripper(self, command: GripperCommand) -> GripperCommand:
        """Open (``opening`` >= 0.5) or close a binary gripper on ``gripper_tool_do``.

        While the e-stop is latched the held opening is returned.

        Raises:
            RobotError: not connected, no gripper configured, or the controller refused the output.
        """
        self._require_ok()
        if self.gripper_tool_do is None:
            raise RobotError(
                f"{self._name}: no gripper on this robot; set `gripper_tool_do` (the tool output it is "
                "wired to) in its config or remove the gripper from its binding"
            )
        if self._estopped:
            return self._stamped_gripper(self._gripper_opening)
        opening = 1.0 if command.opening >= 0.5 else 0.0
        level = self.gripper_close_level if opening == 0.0 else 1 - self.gripper_close_level
        reply = self._request(format_command("ToolDOExecute", self.gripper_tool_do, level))
        if not reply.ok:
            raise RobotError(f"{self._name}: ToolDOExecute refused with ErrorID {reply.error_id}")
        self._gripper_opening = opening
        return self._stamped_gripper(opening)

    def estop(self) -> None:
        """Latch the emergency stop and send ``EmergencyStop`` to the controller.

        The latch holds even when the controller cannot be reached (logged as an error);
        :meth:`send` then transmits nothing until :meth:`reset_estop`.
        """
        with self._lock:
            if self._packet is not None:
                self._hold_deg = self._packet.q_actual.copy()
            self._estopped = True
        text = "EmergencyStop(1)" if self.protocol == "v4" else "EmergencyStop()"
        try:
            reply = self._request(text)
        except RobotError as exc:
            _log.error("%s: emergency stop latched locally, controller not reached: %s", self._name, exc)
            return
        if not reply.ok:
            _log.error("%s: %s answered ErrorID %d; stop latched locally", self._name, text, reply.error_id)
        else:
            _log.warning("%s: emergency stop latched", self._name)

    def reset_estop(self) -> None:
        """Release the e-stop and re-enable the robot.

        Sends ``EmergencyStop(0)`` (V4 only), ``ClearError()`` and ``EnableRobot()``, then waits
        until the feedback reports the robot enabled. The arm holds its position until the next :meth:`send`.

        Raises:
            RobotError: not connected, or the controller does not enable (release the hardware
                e-stop button first).
        """
        self._require_ok()
        if self.protocol == "v4":
            self._checked("EmergencyStop(0)")
        self._enable()
        with self._lock:
            assert self._packet is not None
            self._target_deg = self._packet.q_actual.copy()
            self._estopped = False
        _log.info("%s: emergency stop released", self._name)

    def close(self) -> None:
        """Disable the robot (if configured) and close every connection. Idempotent."""
        if self._closed:
            return
        self._closed = True
        if self.disable_on_close and self.connected:
            try:
                self._request("DisableRobot()")
            except RobotError as exc:
                _log.warning("%s: DisableRobot() on close failed: %s", self._name, exc)
        self._teardown()
        _log.info("%s: closed (%s)", self._name, self.stats)

    def __enter__(self) -> DobotRobot:
        self.connect()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    # -- connection ---------------------------------------------------------------------------

    def _open(self) -> None:
        self._lost = None
        self._stop.clear()
        self._first_packet.clear()
        self._framer = FeedbackFramer()
        self._clock.reset()
        self._dash_buf = ""
        self._dash = self._dial(self.dashboard_port, "dashboard")
        self._feedback = self._dial(self.feedback_port, "feedback")
        if self.motion_port is not None:
            self._motion = self._dial(self.motion_port, "motion")
        self._spawn(self._read_feedback, self._feedback, "feedback")
        if self._motion is not None:
            self._spawn(self._read_motion, self._motion, "motion")
        if not self._first_packet.wait(self.timeout_s):
            raise RobotError(
                f"{self._name}: no feedback packet from {self.host}:{self.feedback_port} within "
                f"{self.timeout_s:g} s; check the feedback port (30004 on CR controllers >= 3.5.2)"
            )
        if self._lost is not None:
            raise RobotError(f"{self._name}: {self._lost}")
        with self._lock:
            self._stats["connects"] += 1
        if self.enable_on_connect:
            self._enable()
        self._checked(format_command("SpeedFactor", self.speed_factor))
        with self._lock:
            assert self._packet is not None
            self._target_deg = self._packet.q_actual.copy()

    def _dial(self, port: int, what: str) -> socket.socket:
        try:
            sock = socket.create_connection((self.host, port), timeout=self.timeout_s)
        except OSError as exc:
            raise RobotError(
                f"{self._name}: cannot reach the {what} port {self.host}:{port} ({exc.strerror or exc}); "
                "check the address and that the controller is in TCP/IP mode"
            ) from None
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return sock

    def _spawn(self, target: Callable[[socket.socket], None], sock: socket.socket, what: str) -> None:
        thread = threading.Thread(
            target=target, args=(sock,), name=f"telerig-{self._name}-{what}", daemon=True
        )
        thread.start()
        self._threads.append(thread)

    def _teardown(self) -> None:
        self._stop.set()
        self._connected = False
        for sock in (self._dash, self._motion, self._feedback):
            if sock is not None:
                with contextlib.suppress(OSError):  # already reset by the peer
                    sock.shutdown(socket.SHUT_RDWR)
                sock.close()
        self._dash = self._motion = self._feedback = None
        for thread in self._threads:
            thread.join()
        self._threads.clear()

    def _mark_lost(self, reason: str) -> None:
        if self._lost is None and not self._stop.is_set():
            self._lost = reason
            _log.error("%s: %s", self._name, reason)

    def _read_feedback(self, sock: socket.socket) -> None:
        sock.settimeout(0.2)
        while not self._stop.is_set():
            try:
                data = sock.recv(65536)
            except TimeoutError:
                continue
            except OSError as exc:
                self._mark_lost(f"feedback connection to {self.host}:{self.feedback_port} failed ({exc})")
                break
            if not data:
                self._mark_lost(
                    f"feedback connection to {self.host}:{self.feedback_port} closed by the controller"
                )
                break
            arrival = now_ns()
            for packet in self._framer.feed(data):
                device_ns = packet.timestamp_ms * 1_000_000
                offset = self._clock.update(device_ns, arrival)
                with self._lock:
                    self._packet = packet
                    self._packet_arrival_ns = arrival
                    self._packet_capture_ns = device_ns + offset
                self._first_packet.set()
        self._first_packet.set()

    def _read_motion(self, sock: socket.socket) -> None:
        sock.settimeout(0.2)
        buf = ""
        while not self._stop.is_set():
            try:
                data = sock.recv(65536)
            except TimeoutError:
                continue
            except OSError as exc:
                self._mark_lost(f"motion connection to {self.host}:{self.motion_port} failed ({exc})")
                return
            if not data:
                self._mark_lost(
                    f"motion connection to {self.host}:{self.motion_port} closed by the controller"
                )
                return
            replies, buf = split_replies(buf + data.decode("ascii", errors="replace"))
            for text in replies:
                try:
                    reply = parse_reply(text)
                except WireError:
                    with self._lock:
                        self._stats["malformed_replies"] += 1
                    continue
                with self._lock:
                    self._stats["motion_replies"] += 1
                    if not reply.ok:
                        self._stats["motion_errors"] += 1
                if not reply.ok:
                    _log.warning("%s: motion command refused: %s", self._name, text)

    def _write_motion(self, text: str) -> None:
        sock = self._motion
        assert sock is not None
        try:
            with self._motion_lock:
                sock.sendall(text.encode("ascii"))
        except OSError as exc:
            self._mark_lost(f"writing to the motion port {self.host}:{self.motion_port} failed ({exc})")
            raise RobotError(f"{self._name}: {self._lost}") from None

    def _request(self, text: str) -> Reply:
        """Send one dashboard command and wait for its reply (matched by the echoed command name)."""
        sock = self._dash
        if sock is None or self._lost is not None:
            raise RobotError(f"{self._name}: {self._lost or 'not connected; call connect() first'}")
        name = text.split("(", 1)[0].lower()
        where = f"{self.host}:{self.dashboard_port}"
        with self._dash_lock:
            try:
                sock.settimeout(self.timeout_s)
                sock.sendall(text.encode("ascii"))
                deadline = time.monotonic() + self.timeout_s
                while True:
                    replies, self._dash_buf = split_replies(self._dash_buf)
                    for raw in replies:
                        try:
                            reply = parse_reply(raw)
                        except WireError:
                            with self._lock:
                                self._stats["malformed_replies"] += 1
                            continue
                        if reply.command.split("(", 1)[0].lower() == name:
                            return reply
                        with self._lock:
                            self._stats["stale_replies"] += 1
                    left = deadline - time.monotonic()
                    if left <= 0:
                        raise TimeoutError
                    sock.settimeout(left)
                    data = sock.recv(65536)
                    if not data:
                        self._mark_lost(f"dashboard connection to {where} closed by the controller")
                        raise RobotError(f"{self._name}: {self._lost}")
                    self._dash_buf += data.decode("ascii", errors="replace")
            except TimeoutError:
                raise RobotError(
                    f"{self._name}: no reply to {text} from {where} within {self.timeout_s:g} s"
                ) from None
            except OSError as exc:
                self._mark_lost(f"dashboard connection to {where} failed ({exc})")
                raise RobotError(f"{self._name}: {self._lost}") from None

    def _checked(self, text: str) -> Reply:
        reply = self._request(text)
        if not reply.ok:
            raise RobotError(f"{self._name}: {text} failed with ErrorID {reply.error_id}; check the pendant")
        return reply

    def _enable(self) -> None:
        self._checked("ClearError()")
        reply = self._request("EnableRobot()")
        if not reply.ok:
            raise RobotError(
                f"{self._name}: EnableRobot() failed with ErrorID {reply.error_id}; "
                "release the e-stop button and clear the alarm on the pendant"
            )
        deadline = time.monotonic() + self.timeout_s
        while self.robot_mode not in _ENABLED_MODES:
            if self._lost is not None:
                raise RobotError(f"{self._name}: {self._lost}")
            if time.monotonic() > deadline:
                raise RobotError(
                    f"{self._name}: robot not enabled {self.timeout_s:g} s after EnableRobot() "
                    f"(mode {_mode_name(self.robot_mode or 0)}); check the pendant for alarms"
                )
            time.sleep(0.004)

    # -- helpers ------------------------------------------------------------------------------

    def _require_ok(self) -> None:
        if self._lost is not None:
            raise RobotError(f"{self._name}: {self._lost}; call connect() to reconnect")
        if not self._connected:
            state = "closed" if self._closed else "not connected; call connect() first"
            raise RobotError(f"{self._name}: driver is {state}")
        age = (now_ns() - self._packet_arrival_ns) / 1e9
        if age > self.stale_timeout_s:
            self._mark_lost(f"no feedback from {self.host}:{self.feedback_port} for {age:.2f} s")
            raise RobotError(f"{self._name}: {self._lost}; call connect() to reconnect")

    def _indices(self, names: tuple[str, ...]) -> list[int]:
        try:
            return [self._index[n] for n in names]
        except KeyError as exc:
            raise RobotError(
                f"{self._name}: joint {exc.args[0]!r} not found. Available: {', '.join(self.joint_names)}"
            ) from None

    def _stamped(self, names: tuple[str, ...], positions: FloatArray) -> JointCommand:
        with self._lock:
            seq = self._cmd_seq
            self._cmd_seq += 1
        return JointCommand(Stamp.now(self._name, seq), names, positions)

    def _stamped_gripper(self, opening: float) -> GripperCommand:
        with self._lock:
            seq = self._grip_seq
            self._grip_seq += 1
        return GripperCommand(Stamp.now(self._name, seq), opening=opening)
