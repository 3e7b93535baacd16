"""URRobot: Universal Robots driver; RTDE for state and servo targets, URScript for the servo loop."""

from __future__ import annotations

import collections
import contextlib
import logging
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from types import TracebackType
from typing import Literal

import numpy as np

from telerig.errors import RobotError, WireError
from telerig.ir.types import FloatArray, GripperCommand, JointCommand, JointState, Stamp
from telerig.robots.base import JointLimits
from telerig.robots.ur import rtde
from telerig.robots.ur.limits import UR_JOINT_NAMES, ur_limits
from telerig.robots.ur.robotiq import RobotiqSocket
from telerig.robots.ur.rtde import (
    Command,
    MessageLevel,
    Recipe,
    RobotMode,
    RuntimeState,
    SafetyMode,
    SetupReply,
    TextMessage,
)
from telerig.robots.ur.script import SCRIPT_PORT, STOP_WORD, ServoProgram, stop_program

__all__ = ["ClockMapper", "URRobot", "URStats", "URStatus"]

_log = logging.getLogger(__name__)

#: Robotiq 2F-85 grip force range [N] that FOR 0..255 spans (datasheet: 20-235 N).
_GRIP_FORCE_RANGE = (20.0, 235.0)
_WORD_MAX = 2**31 - 1
_BASE_OUTPUTS = (
    "timestamp",
    "actual_q",
    "actual_qd",
    "target_q",
    "robot_mode",
    "safety_mode",
    "runtime_state",
)


@dataclass(frozen=True, slots=True)
class URStatus:
    """Controller status from the latest RTDE data package.

    Attributes:
        controller_time_s: Controller ``timestamp``: time since it booted [s].
        robot_mode: Robot mode (:class:`~telerig.robots.ur.rtde.RobotMode` value).
        safety_mode: Safety mode (:class:`~telerig.robots.ur.rtde.SafetyMode` value).
        runtime_state: Program state (:class:`~telerig.robots.ur.rtde.RuntimeState` value).
        target_q: Joint targets the controller is servoing to [rad]. Shape (6,).
        word: Watchdog word the controller holds (echo of the last one written).
        arrival_ns: When the package arrived, host common clock [ns].
    """

    controller_time_s: float
    robot_mode: int
    safety_mode: int
    runtime_state: int
    target_q: FloatArray
    word: int
    arrival_ns: int


@dataclass(frozen=True, slots=True)
class URStats:
    """Connection counters since :meth:`URRobot.connect`.

    Attributes:
        packages: RTDE data packages received.
        malformed: Packages that could not be decoded or were not expected; each was dropped.
        commands: Register writes sent (``send`` calls that reached the wire).
        clock_offset_ns: Current controller-to-host clock offset [ns] (see :class:`ClockMapper`).
    """

    packages: int
    malformed: int
    commands: int
    clock_offset_ns: int


class ClockMapper:
    """Maps a device clock to the host clock: ``host = device + offset``.

    The offset is the minimum of ``arrival - device`` over the last ``window_ns`` of device time:
    the package that crossed the network fastest bounds it best, and the window lets the estimate
    follow the drift between the two clocks. The mapped time is late by the minimum one-way
    latency, which one-way traffic cannot observe (sub-millisecond on a direct cable).
    """

    def __init__(self, window_ns: int = 2_000_000_000) -> None:
        if window_ns <= 0:
            raise ValueError(f"window_ns must be positive, got {window_ns}")
        self._window = window_ns
        self._mins: collections.deque[tuple[int, int]] = collections.deque()

    def update(self, device_ns: int, arrival_ns: int) -> int:
        """Add one package's device time and arrival time [ns]; return the current offset [ns]."""
        offset = arrival_ns - device_ns
        mins = self._mins
        while mins and mins[-1][1] >= offset:
            mins.pop()
        mins.append((device_ns, offset))
        while mins[0][0] < device_ns - self._window:
            mins.popleft()
        return mins[0][1]

    @property
    def offset_ns(self) -> int:
        """Current offset [ns]; 0 before the first update."""
        return self._mins[0][1] if self._mins else 0

    def to_host(self, device_ns: int) -> int:
        """Host-clock time of a device time [ns]."""
        return device_ns + self.offset_ns


class URRobot:
    """A Universal Robots arm over its real interfaces; a :class:`~telerig.robots.base.RobotDriver`.

    :meth:`connect` negotiates RTDE protocol 2 on ``rtde_port``, subscribes to joint state and
    robot/safety/program modes at ``control_rate_hz``, takes six input double registers (joint
    targets) and one input integer register (watchdog word) as inputs, then uploads the
    :class:`~telerig.robots.ur.script.ServoProgram` on ``script_port``. Each :meth:`send` writes the
    targets and a new word in one RTDE package; the program ``servoj``s to them and stops the arm
    (``stopj``) when the word stops changing for its watchdog time, so a dead host stops the robot.

    The robot must be powered on, brakes released, and in Remote Control mode (e-Series).
    """

    def __init__(
        self,
        host: str,
        *,
        name: str = "ur",
        rtde_port: int = rtde.DEFAULT_PORT,
        script_port: int = SCRIPT_PORT,
        control_rate_hz: float = 125.0,
        program: ServoProgram | None = None,
        limits: JointLimits | None = None,
        estop_action: Literal["protective_stop", "stopj"] = "protective_stop",
        gripper_port: int | None = None,
        timeout_s: float = 2.0,
        stale_timeout_s: float = 0.5,
        extra_outputs: tuple[str, ...] = (),
        robot_model: str | None = None,
    ) -> None:
        """Create the driver (no I/O until :meth:`connect`).

        Args:
            host: Controller IP address or host name.
            name: Driver name; the ``source_id`` of every stamp it produces.
            rtde_port: RTDE port (30004).
            script_port: Secondary client interface port taking URScript (30002).
            control_rate_hz: State output rate [Hz], at most 500 (e-Series) or 125 (CB3).
            program: Servo loop parameters; :class:`ServoProgram` defaults when None.
            limits: Joint limits in :data:`UR_JOINT_NAMES` order; the UR5e's when None.
            estop_action: ``protective_stop`` (latches on the robot) or ``stopj`` (decelerate only).
            gripper_port: Robotiq URCap socket port (63352), None when no Robotiq gripper is fitted.
            timeout_s: Connect and handshake timeout [s].
            stale_timeout_s: No RTDE package for this long [s] counts as a lost connection.
            extra_outputs: More RTDE output variables to subscribe to (e.g. ``actual_TCP_pose``);
                read them with :meth:`outputs`.
            robot_model: The arm's model in :mod:`telerig.robots.models` (e.g. ``ur5e_robotiq85``),
                for IK and the workspace and self-collision guards; None: none.
        """
        if not 0 < control_rate_hz <= 500:
            raise ValueError(f"control_rate_hz must be in (0, 500], got {control_rate_hz}")
        if stale_timeout_s <= 2.0 / control_rate_hz:
            raise ValueError(f"stale_timeout_s must exceed two state periods ({2.0 / control_rate_hz:g} s)")
        self._name = name
        self._host = host
        self._robot_model = robot_model
        self._rtde_port = rtde_port
        self._script_port = script_port
        self._rate = control_rate_hz
        self._program = program if program is not None else ServoProgram()
        self._limits = limits if limits is not None else ur_limits("ur5e")
        if self._limits.names != UR_JOINT_NAMES:
            raise ValueError(f"limits must name the UR joints {UR_JOINT_NAMES}, got {self._limits.names}")
        self._estop_action = estop_action
        self._gripper = (
            RobotiqSocket(host, gripper_port, timeout_s=timeout_s, name=name) if gripper_port else None
        )
        self._timeout = timeout_s
        self._stale_timeout = stale_timeout_s
        self._index = {j: i for i, j in enumerate(UR_JOINT_NAMES)}
        w = self._program.int_register
        self._word_var = f"input_int_register_{w}"
        self._target_vars = tuple(f"input_double_register_{i}" for i in self._program.double_registers)
        self._output_names = (
            *_BASE_OUTPUTS,
            self._word_var,
            *(n for n in extra_outputs if n not in _BASE_OUTPUTS and n != self._word_var),
        )

        self._lock = threading.Lock()
        self._send_lock = threading.Lock()
        self._cond = threading.Condition(self._lock)
        self._sock: socket.socket | None = None
        self._script: socket.socket | None = None
        self._reader: threading.Thread | None = None
        self._stop = threading.Event()
        self._output: Recipe | None = None
        self._input: Recipe | None = None
        self._clock = ClockMapper()
        self._latest: tuple[dict[str, rtde.Value], int] | None = None
        self._lost: str | None = None
        self._connected = False
        self._closed = False
        self._estopped = False
        self._program_seen = False
        self._targets = np.zeros(6)
        self._word = 0
        self._packages = 0
        self._malformed = 0
        self._commands = 0
        self._state_seq = 0
        self._cmd_seq = 0
        self._grip_seq = 0
        self._grip_last: tuple[int, int] | None = None
        self._grip_applied = GripperCommand(Stamp(name, 0, 0, 0), opening=1.0)
        self.last_message: TextMessage | None = None
        """Latest text message from the controller."""

    # -- RobotDriver ------------------------------------------------------------------------------

    @property
    def name(self) -> str:
        """Driver name, used as the stamps' ``source_id``."""
        return self._name

    @property
    def joint_names(self) -> tuple[str, ...]:
        """UR joints, base to tool."""
        return UR_JOINT_NAMES

    @property
    def robot_model(self) -> str | None:
        """The arm's model name (:class:`~telerig.robots.models.ModelledRobot`), None when not set."""
        return self._robot_model

    @property
    def limits(self) -> JointLimits:
        """Joint position [rad], speed [rad/s] and acceleration [rad/s^2] limits."""
        return self._limits

    @property
    def connected(self) -> bool:
        """True between a successful :meth:`connect` and :meth:`close` or a lost connection."""
        return self._connected and self._lost is None

    @property
    def estopped(self) -> bool:
        """Whether the emergency stop is latched in the driver."""
        return self._estopped

    def connect(self) -> None:
        """Handshake RTDE, subscribe, start the servo program (and activate the gripper). Idempotent.

        Raises:
            RobotError: the controller is unreachable, refuses protocol 2 or a recipe variable, or
                does not start the program; the message says what to check.
        """
        if self._closed:
            raise RobotError(f"{self._name}: driver is closed; create a new one")
        if self._connected:
            return
        try:
            self._open_rtde()
            self._wait_state(lambda values: True, "the first RTDE data package")
            self._script = self._open_script()
            self._start_program()
            if self._gripper is not None:
                self._gripper.connect()
        except BaseException:
            self._teardown()
            raise
        self._connected = True
        _log.info("%s: connected to %s (RTDE %g Hz)", self._name, self._host, self._rate)

    def read_state(self) -> JointState:
        """Latest measured joint positions [rad] and velocities [rad/s] (no efforts).

        ``device_ns`` is the controller clock, ``capture_ns`` the same instant in the host clock
        (:class:`ClockMapper`), ``arrival_ns`` when the package arrived.

        Raises:
            RobotError: not connected, or the connection was lost.
        """
        self._require_live()
        return self._snapshot()

    def _snapshot(self) -> JointState:
        with self._lock:
            latest = self._latest
            seq = self._state_seq
            self._state_seq += 1
            offset = self._clock.offset_ns
        assert latest is not None  # connect() waited for the first package
        values, arrival = latest
        device_ns = round(float(values["timestamp"]) * 1e9)  # type: ignore[arg-type]
        stamp = Stamp(self._name, seq, device_ns=device_ns, capture_ns=device_ns + offset, arrival_ns=arrival)
        return JointState(stamp, UR_JOINT_NAMES, np.array(values["actual_q"]), np.array(values["actual_qd"]))

    def status(self) -> URStatus:
        """Robot, safety and program modes and servo targets from the latest package.

        Raises:
            RobotError: not connected, or the connection was lost.
        """
        self._require_live()
        with self._lock:
            assert self._latest is not None
            values, arrival = self._latest
        return URStatus(
            controller_time_s=float(values["timestamp"]),  # type: ignore[arg-type]
            robot_mode=int(values["robot_mode"]),  # type: ignore[arg-type]
            safety_mode=int(values["safety_mode"]),  # type: ignore[arg-type]
            runtime_state=int(values["runtime_state"]),  # type: ignore[arg-type]
            target_q=np.array(values["target_q"]),
            word=int(values[self._word_var]),  # type: ignore[arg-type]
            arrival_ns=arrival,
        )

    def outputs(self) -> dict[str, rtde.Value]:
        """Every subscribed RTDE output of the latest package, by name (vectors as tuples).

        Raises:
            RobotError: not connected, or the connection was lost.
        """
        self._require_live()
        with self._lock:
            assert self._latest is not None
            return dict(self._latest[0])

    def stats(self) -> URStats:
        """Connection counters."""
        with self._lock:
            return URStats(self._packages, self._malformed, self._commands, self._clock.offset_ns)

    def send(self, command: JointCommand) -> JointCommand:
        """Write joint position targets [rad] for the named joints (any subset, any order).

        Targets are clipped to the position limits; joints not named keep their last target.
        Velocities are ignored (``servoj`` position control). While the e-stop is latched nothing
        is written and the held targets are returned.

        Returns:
            The targets written for ``command.names``, stamped when the package left.

        Raises:
            RobotError: unknown joint; connection lost; the robot is stopped (protective or
                emergency stop, or the servo program ended, e.g. by its watchdog).
        """
        self._require_live()
        idx = self._indices(command.names)
        if not self._estopped:
            self._check_running()
            with self._send_lock:
                targets = self._targets.copy()
                targets[idx] = np.clip(command.positions, self._limits.lower[idx], self._limits.upper[idx])
                self._word = self._word % _WORD_MAX + 1
                self._write(targets, self._word)
                self._targets = targets
        t = time.time_ns()
        with self._lock:
            seq = self._cmd_seq
            self._cmd_seq += 1
        return JointCommand(
            Stamp(self._name, seq, device_ns=t, capture_ns=t), command.names, self._targets[idx]
        )

    @property
    def has_gripper(self) -> bool:
        """Whether a gripper is configured (``gripper: robotiq_urcap``)."""
        return self._gripper is not None

    def send_gripper(self, command: GripperCommand) -> GripperCommand:
        """Move the Robotiq gripper: opening in [0, 1] (clipped) -> POS 255..0, max_force [N] -> FOR.

        A command equal (after quantisation) to the previous one is not sent again. While the
        e-stop is latched nothing is sent and the held command is returned.

        Raises:
            RobotError: no gripper is configured, or the gripper socket failed.
        """
        if self._gripper is None:
            raise RobotError(
                f"{self._name}: no gripper on this robot; set `gripper: robotiq_urcap` in its config "
                "or remove the gripper binding"
            )
        self._require_live()
        t = time.time_ns()
        with self._lock:
            seq = self._grip_seq
            self._grip_seq += 1
        if self._estopped:
            held = self._grip_applied
            return GripperCommand(Stamp(self._name, seq, t, t), held.opening, held.max_force)
        opening = float(np.clip(command.opening, 0.0, 1.0))
        pos = round((1.0 - opening) * 255)
        lo, hi = _GRIP_FORCE_RANGE
        force = (
            round(np.clip((command.max_force - lo) / (hi - lo), 0.0, 1.0) * 255)
            if command.max_force > 0
            else -1
        )
        if (pos, force) != self._grip_last:
            values = {"POS": pos} if force < 0 else {"POS": pos, "FOR": force}
            self._gripper.set(**values)
            self._grip_last = (pos, force)
            t = time.time_ns()
        applied_force = lo + force / 255 * (hi - lo) if force >= 0 else 0.0
        self._grip_applied = GripperCommand(Stamp(self._name, seq, t, t), 1.0 - pos / 255, applied_force)
        return self._grip_applied

    def estop(self) -> None:
        """Latch the e-stop: stop word over RTDE, then the stop program (``estop_action``) over URScript.

        Never raises: a driver that lost its connection cannot reach the robot, whose own watchdog
        then stops it within the program's watchdog time.
        """
        self._estopped = True
        if self.connected:
            try:
                with self._send_lock:
                    self._write(self._targets, STOP_WORD)
                self._send_script(stop_program(self._estop_action, self._program.stop_deceleration))
            except (RobotError, OSError) as exc:
                _log.error(
                    "%s: e-stop could not reach the robot (%s); its watchdog stops it", self._name, exc
                )
        _log.warning("%s: emergency stop latched (%s)", self._name, self._estop_action)

    def reset_estop(self) -> None:
        """Release the latch and restart the servo program from the current position.

        Raises:
            RobotError: not connected, or the robot is still stopped (unlock the protective stop or
                release the emergency stop on the teach pendant first).
        """
        self._require_live()
        self._wait_state(lambda v: True, "a fresh RTDE package", after_ns=time.time_ns())
        self._require_unlocked()
        try:
            self._start_program()
        except RobotError:
            # The controller may report the stop only after the package read above (a reset right
            # after the e-stop): then the program was refused for the stop, and that is what to say.
            self._require_unlocked()
            raise
        self._estopped = False
        _log.info("%s: emergency stop released", self._name)

    def _require_unlocked(self) -> None:
        status = self.status()
        if status.safety_mode not in (SafetyMode.NORMAL, SafetyMode.REDUCED):
            raise RobotError(
                f"{self._name}: robot is in {_mode(SafetyMode, status.safety_mode)}; unlock it on the teach "
                "pendant, then reset the e-stop"
            )

    def close(self) -> None:
        """Stop the servo program (``stopj``), leave RTDE and close every socket. Idempotent."""
        if self._closed:
            return
        self._closed = True
        if self.connected and not self._estopped:
            with contextlib.suppress(RobotError, OSError), self._send_lock:
                self._write(self._targets, STOP_WORD)
        if self.connected and self._sock is not None:
            with contextlib.suppress(OSError):
                self._sock.sendall(rtde.pack(Command.CONTROL_PACKAGE_PAUSE))
        self._teardown()
        self._connected = False
        _log.info("%s: closed (%s)", self._name, self.stats())

    def __enter__(self) -> URRobot:
        self.connect()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    # -- connection -------------------------------------------------------------------------------

    def _where(self, port: int) -> str:
        return f"{self._host}:{port}"

    def _open_rtde(self) -> None:
        where = self._where(self._rtde_port)
        try:
            sock = socket.create_connection((self._host, self._rtde_port), timeout=self._timeout)
        except OSError as exc:
            raise RobotError(
                f"{self._name}: cannot reach the UR controller's RTDE port at {where} ({exc}); "
                "check the IP address and that the controller is on"
            ) from None
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock = sock
        reader = rtde.FrameReader()
        with self._lock:
            self._lost = None
            self._latest = None
            self._clock = ClockMapper()

        reply = self._request(
            reader, rtde.ProtocolVersionRequest().encode(), Command.REQUEST_PROTOCOL_VERSION
        )
        if not rtde.Accepted.decode(Command.REQUEST_PROTOCOL_VERSION, reply).accepted:
            raise RobotError(
                f"{self._name}: the controller at {where} refused RTDE protocol {rtde.PROTOCOL_VERSION}; "
                "update it to PolyScope 3.5+ (CB3) or 5.0+ (e-Series)"
            )
        reply = self._request(reader, rtde.pack(Command.GET_URCONTROL_VERSION), Command.GET_URCONTROL_VERSION)
        version = rtde.ControllerVersion.decode(reply)
        _log.info("%s: URControl %s at %s", self._name, version, where)

        setup = rtde.OutputSetup(self._rate, self._output_names).encode()
        out_cmd = Command.CONTROL_PACKAGE_SETUP_OUTPUTS
        out = SetupReply.decode(out_cmd, self._request(reader, setup, out_cmd))
        self._output = self._recipe(self._output_names, out, "output")
        setup = rtde.InputSetup((*self._target_vars, self._word_var)).encode()
        in_cmd = Command.CONTROL_PACKAGE_SETUP_INPUTS
        inp = SetupReply.decode(in_cmd, self._request(reader, setup, in_cmd))
        self._input = self._recipe((*self._target_vars, self._word_var), inp, "input")
        reply = self._request(reader, rtde.pack(Command.CONTROL_PACKAGE_START), Command.CONTROL_PACKAGE_START)
        if not rtde.Accepted.decode(Command.CONTROL_PACKAGE_START, reply).accepted:
            raise RobotError(f"{self._name}: the controller at {where} refused to start RTDE synchronisation")

        sock.settimeout(self._stale_timeout)
        self._stop.clear()
        self._reader = threading.Thread(
            target=self._read_loop, args=(sock, reader), name=f"{self._name}-rtde", daemon=True
        )
        self._reader.start()

    def _recipe(self, names: tuple[str, ...], reply: SetupReply, kind: str) -> Recipe:
        bad = reply.problems(names)
        if bad:
            hint = (
                "another RTDE client or a fieldbus (EtherNet/IP, PROFINET) writes these registers; "
                "use register_offset 24"
                if any(rtde.IN_USE in b for b in bad)
                else "check the names against the RTDE guide"
            )
            raise RobotError(f"{self._name}: RTDE {kind} setup refused {', '.join(bad)}; {hint}")
        if reply.recipe_id == 0:
            why = self.last_message.message if self.last_message is not None else "no reason given"
            raise RobotError(f"{self._name}: RTDE {kind} setup refused ({why})")
        return Recipe(reply.recipe_id, names, reply.types)

    def _request(self, reader: rtde.FrameReader, frame: bytes, expect: int) -> bytes:
        """Send a handshake package and return the payload of the reply of type ``expect``."""
        assert self._sock is not None
        deadline = time.monotonic() + self._timeout
        try:
            self._sock.sendall(frame)
            while True:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise TimeoutError("timed out")
                self._sock.settimeout(remaining)
                data = self._sock.recv(65536)
                if not data:
                    raise OSError("connection closed by the controller")
                for reply in reader.feed(data):
                    if reply.command == expect:
                        return reply.payload
                    self._on_other(reply)
        except (OSError, WireError) as exc:
            raise RobotError(
                f"{self._name}: RTDE handshake with {self._where(self._rtde_port)} failed waiting for "
                f"{Command(expect).name} ({exc}); is it a UR controller?"
            ) from None

    def _open_script(self) -> socket.socket:
        try:
            sock = socket.create_connection((self._host, self._script_port), timeout=self._timeout)
        except OSError as exc:
            raise RobotError(
                f"{self._name}: cannot reach the URScript port at {self._where(self._script_port)} ({exc}); "
                "put the robot in Remote Control mode"
            ) from None
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        # The controller streams robot state on this port; drain it so its buffers never fill.
        threading.Thread(target=_drain, args=(sock,), name=f"{self._name}-script", daemon=True).start()
        return sock

    def _send_script(self, text: str) -> None:
        for attempt in (0, 1):
            if self._script is None:
                self._script = self._open_script()
            try:
                self._script.sendall(text.encode("ascii"))
                return
            except OSError as exc:
                self._script.close()
                self._script = None
                if attempt:
                    raise RobotError(
                        f"{self._name}: could not send URScript to {self._where(self._script_port)} ({exc})"
                    ) from None

    def _start_program(self) -> None:
        """Hold the current position in the registers, then upload the servo program and wait for it."""
        actual = self._snapshot().positions
        with self._send_lock:
            self._targets = np.clip(actual, self._limits.lower, self._limits.upper)
            self._word = 0
            self._write(self._targets, self._word)
        # The program reads the word once at start; it must see ours, not a stale one.
        self._wait_state(lambda v: v[self._word_var] == 0, "the controller to apply the registers")
        self._program_seen = False
        uploaded = time.time_ns()
        self._send_script(self._program.render())
        self._wait_state(
            lambda v: v["runtime_state"] == RuntimeState.PLAYING,
            "the servo program to start (is the robot powered on and in Remote Control mode?)",
            after_ns=uploaded,
        )
        self._program_seen = True

    def _wait_state(
        self, predicate: Callable[[dict[str, rtde.Value]], bool], what: str, after_ns: int = 0
    ) -> None:
        """Wait for a package that arrived after ``after_ns`` (host clock) and satisfies ``predicate``."""
        deadline = time.monotonic() + self._timeout
        with self._cond:
            while True:
                if self._lost is not None:
                    raise RobotError(f"{self._name}: {self._lost} while waiting for {what}")
                latest = self._latest
                if latest is not None and latest[1] > after_ns and predicate(latest[0]):
                    return
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise RobotError(f"{self._name}: timed out after {self._timeout:g} s waiting for {what}")
                self._cond.wait(remaining)

    def _write(self, targets: FloatArray, word: int) -> None:
        """One RTDE input package with ``targets`` [rad] and the watchdog ``word`` (send lock held)."""
        assert self._input is not None
        assert self._sock is not None
        values: dict[str, rtde.Value] = dict(zip(self._target_vars, targets.tolist(), strict=True))
        values[self._word_var] = word
        try:
            self._sock.sendall(self._input.encode(values))
        except OSError as exc:
            self._mark_lost(f"lost the RTDE connection to {self._where(self._rtde_port)} ({exc})")
            raise RobotError(f"{self._name}: {self._lost}; check the network and reconnect") from None
        self._commands += 1

    def _check_running(self) -> None:
        status = self.status()
        if status.safety_mode not in (SafetyMode.NORMAL, SafetyMode.REDUCED):
            raise RobotError(
                f"{self._name}: robot is in {_mode(SafetyMode, status.safety_mode)}; clear it on the teach "
                "pendant, then reset the e-stop"
            )
        if status.robot_mode != RobotMode.RUNNING:
            raise RobotError(
                f"{self._name}: robot mode is {_mode(RobotMode, status.robot_mode)}; power it on"
            )
        if self._program_seen and status.runtime_state != RuntimeState.PLAYING:
            raise RobotError(
                f"{self._name}: the servo program stopped on the controller (watchdog: no command for "
                f"{self._program.watchdog_cycles * self._program.period_s:g} s, or stopped on the pendant); "
                "call reset_estop() to restart it"
            )

    def _read_loop(self, sock: socket.socket, reader: rtde.FrameReader) -> None:
        assert self._output is not None
        output = self._output
        while not self._stop.is_set():
            try:
                data = sock.recv(65536)
            except TimeoutError:
                self._mark_lost(
                    f"no RTDE data from {self._where(self._rtde_port)} for {self._stale_timeout:g} s"
                )
                return
            except OSError as exc:
                if not self._stop.is_set():
                    self._mark_lost(f"lost the RTDE connection to {self._where(self._rtde_port)} ({exc})")
                return
            arrival = time.time_ns()
            if not data:
                if not self._stop.is_set():
                    self._mark_lost(
                        f"the controller at {self._where(self._rtde_port)} closed the RTDE connection"
                    )
                return
            try:
                frames = reader.feed(data)
            except WireError as exc:
                self._mark_lost(f"corrupt RTDE stream ({exc})")
                return
            for frame in frames:
                if frame.command != Command.DATA_PACKAGE:
                    self._on_other(frame)
                    continue
                try:
                    values = output.decode(frame.payload)
                except WireError as exc:
                    with self._lock:
                        self._malformed += 1
                    _log.debug("%s: dropped RTDE package: %s", self._name, exc)
                    continue
                device_ns = round(float(values["timestamp"]) * 1e9)  # type: ignore[arg-type]
                with self._cond:
                    self._clock.update(device_ns, arrival)
                    self._latest = (values, arrival)
                    self._packages += 1
                    self._cond.notify_all()

    def _on_other(self, frame: rtde.Frame) -> None:
        if frame.command == Command.TEXT_MESSAGE:
            try:
                msg = TextMessage.decode(frame.payload)
            except WireError:
                pass
            else:
                self.last_message = msg
                level = logging.ERROR if msg.level <= MessageLevel.ERROR else logging.INFO
                if msg.level == MessageLevel.WARNING:
                    level = logging.WARNING
                _log.log(level, "%s: controller says (%s): %s", self._name, msg.source, msg.message)
                return
        if frame.command == Command.CONTROL_PACKAGE_PAUSE:
            return
        with self._lock:
            self._malformed += 1
        _log.debug("%s: dropped unexpected RTDE package type %d", self._name, frame.command)

    def _mark_lost(self, reason: str) -> None:
        with self._cond:
            if self._lost is None:
                self._lost = reason
                _log.error("%s: %s", self._name, reason)
            self._cond.notify_all()

    def _teardown(self) -> None:
        self._stop.set()
        for sock in (self._sock, self._script):
            if sock is not None:
                with contextlib.suppress(OSError):
                    sock.shutdown(socket.SHUT_RDWR)
                sock.close()
        self._sock = self._script = None
        reader, self._reader = self._reader, None
        if reader is not None and reader is not threading.current_thread():
            reader.join(timeout=2.0)
        if self._gripper is not None:
            self._gripper.close()

    def _require_live(self) -> None:
        if not self._connected:
            state = "closed" if self._closed else "not connected; call connect() first"
            raise RobotError(f"{self._name}: driver is {state}")
        if self._lost is not None:
            raise RobotError(f"{self._name}: {self._lost}; check the robot and reconnect")

    def _indices(self, names: tuple[str, ...]) -> list[int]:
        try:
            return [self._index[n] for n in names]
        except KeyError as exc:
            raise RobotError(
                f"{self._name}: joint {exc.args[0]!r} not found. Available: {', '.join(UR_JOINT_NAMES)}"
            ) from None


def _mode(enum: type[SafetyMode] | type[RobotMode], value: int) -> str:
    try:
        return enum(value).name
    except ValueError:
        return f"mode {value}"


def _drain(sock: socket.socket) -> None:
    sock.settimeout(None)
    with contextlib.suppress(OSError):
        while sock.recv(65536):
            pass
