"""FakeURController: a local UR controller peer speaking RTDE, taking URScript and a Robotiq URCap socket."""

from __future__ import annotations

import contextlib
import logging
import math
import re
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from types import TracebackType

import numpy as np

from telerig.bus.peer_loop import accept_loop
from telerig.errors import WireError
from telerig.ir.types import FloatArray
from telerig.robots.ur import rtde
from telerig.robots.ur.limits import ur_limits
from telerig.robots.ur.rtde import (
    Command,
    ControllerVersion,
    MessageLevel,
    Recipe,
    RobotMode,
    RuntimeState,
    SafetyMode,
    SetupReply,
    TextMessage,
    Value,
)
from telerig.robots.ur.script import ServoProgram

__all__ = ["FakeURController"]

_log = logging.getLogger(__name__)

#: Home configuration of the fake arm [rad]: elbow up, tool pointing down.
_HOME = (0.0, -math.pi / 2, math.pi / 2, -math.pi / 2, -math.pi / 2, 0.0)


@dataclass(eq=False)
class _RtdeClient:
    sock: socket.socket
    address: str
    send_lock: threading.Lock = field(default_factory=threading.Lock)
    version: int = 0
    output: Recipe | None = None
    divisor: int = 1
    started: bool = False
    inputs: dict[int, Recipe] = field(default_factory=dict)
    next_input_id: int = 1


@dataclass
class _Servo:
    program: ServoProgram
    word_last: int
    stale: int = 0
    armed: bool = False


class FakeURController:
    """A simulated UR e-Series controller on 127.0.0.1 for tests and dry runs of a rig.

    It speaks the real protocols, so the real :class:`~telerig.robots.ur.driver.URRobot` talks to
    it unchanged: RTDE protocol 2 on ``rtde_port`` (any number of clients, output recipes at up to
    the controller rate, input registers with ``IN_USE`` ownership), URScript programs on
    ``script_port`` and, when ``gripper_port`` is given, the Robotiq 2F URCap text socket.

    What it simulates, every ``cycle_s`` (2 ms, the e-Series rate): six joints with the model's
    position, speed and acceleration limits following ``servoj`` targets as a first-order lag of
    time constant ``lookahead``; robot, safety and runtime modes; protective and emergency stops.
    It does not interpret URScript: it runs the program :class:`~telerig.robots.ur.script.ServoProgram`
    renders (parameters read back from its statements), and programs that only call
    ``protective_stop()`` or ``stopj(a)``. Any other script is counted in :attr:`rejected_scripts`.
    Variables it does not simulate (currents, TCP pose, temperatures, ...) read as zeros.

    Ports given as 0 are picked by the OS; read the bound ones from :attr:`rtde_port` and friends.
    """

    def __init__(
        self,
        host: str = "127.0.0.1",
        rtde_port: int = rtde.DEFAULT_PORT,
        script_port: int = 30002,
        gripper_port: int | None = None,
        *,
        model: str = "ur5e",
        home: tuple[float, ...] = _HOME,
        cycle_s: float = 0.002,
        version: ControllerVersion = ControllerVersion(5, 15, 2, 0),  # noqa: B008 (frozen)
        protocol_versions: tuple[int, ...] = (rtde.PROTOCOL_VERSION,),
        clock_offset_s: float = 1000.0,
    ) -> None:
        """Create the fake (nothing listens until :meth:`start`).

        Args:
            host: Address to listen on.
            rtde_port: RTDE port (30004 on a robot; 0 = any free port).
            script_port: Secondary-interface port for URScript (30002 on a robot; 0 = any free port).
            gripper_port: Robotiq URCap socket port (63352 on a robot; 0 = any); None = no gripper.
            model: Arm model whose limits the joints obey, e.g. ``"ur5e"``.
            home: Initial joint positions [rad]. Shape (6,).
            cycle_s: Controller period [s].
            version: URControl version reported to ``v`` requests.
            protocol_versions: RTDE protocol versions accepted (only 2 is implemented).
            clock_offset_s: Controller ``timestamp`` at start [s] (time since the controller booted).
        """
        self._host = host
        self._ports = {"rtde": rtde_port, "script": script_port, "gripper": gripper_port}
        self._limits = ur_limits(model)
        self._cycle = cycle_s
        self._version = version
        self._protocol_versions = protocol_versions
        self._clock_offset = clock_offset_s
        self._home = np.array(home, dtype=np.float64)
        if self._home.shape != (6,):
            raise ValueError(f"home must have 6 joint positions, got shape {self._home.shape}")

        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._listeners: dict[str, socket.socket] = {}
        self._conns: set[socket.socket] = set()
        self._rtde_clients: list[_RtdeClient] = []
        self._owners: dict[str, _RtdeClient] = {}
        self._started = False

        self._q = self._home.copy()
        self._qd = np.zeros(6)
        self._qdd = np.zeros(6)
        self._target = self._home.copy()
        self._servo: _Servo | None = None
        self._stop_decel: float | None = None
        self._robot_mode = RobotMode.RUNNING
        self._safety_mode = SafetyMode.NORMAL
        self._int_in = [0] * 48
        self._double_in = [0.0] * 48
        self._tick = 0

        self._grip = {
            "ACT": 0,
            "GTO": 0,
            "STA": 0,
            "PRE": 0,
            "POS": 0,
            "SPE": 255,
            "FOR": 150,
            "OBJ": 3,
            "FLT": 0,
        }

        self.malformed_packets = 0
        """Packages received that could not be decoded or had no meaning; each was dropped."""
        self.watchdog_stops = 0
        """Times the servo program stopped because its watchdog word stopped changing."""
        self.stop_requests = 0
        """Times the servo program stopped because the watchdog word turned negative."""
        self.programs_received = 0
        """URScript programs and statements received on the script port."""
        self.rejected_scripts = 0
        """Scripts the fake does not understand or refused (robot stopped); none was run."""
        self.last_program = ""
        """Text of the latest program received."""
        self.text_messages: list[TextMessage] = []
        """Text messages clients sent."""

    # -- lifecycle --------------------------------------------------------------------------

    def start(self) -> FakeURController:
        """Listen on the ports and start the controller cycle. Idempotent."""
        if self._started:
            return self
        self._started = True
        handlers: dict[str, Callable[[socket.socket, str], None]] = {
            "rtde": self._serve_rtde,
            "script": self._serve_script,
            "gripper": self._serve_gripper,
        }
        for kind, port in self._ports.items():
            if port is None:
                continue
            listener = socket.create_server((self._host, port))
            listener.settimeout(0.1)
            self._listeners[kind] = listener
            self._ports[kind] = listener.getsockname()[1]
            self._spawn(f"fake-ur-accept-{kind}", self._accept, listener, handlers[kind])
        self._t0 = time.monotonic()
        self._spawn("fake-ur-cycle", self._run)
        _log.info("fake UR controller listening on %s: %s", self._host, self._ports)
        return self

    def close(self) -> None:
        """Stop the controller and drop every connection, as a controller that dies would. Idempotent."""
        self._stop.set()
        for listener in self._listeners.values():
            listener.close()
        with self._lock:
            conns = list(self._conns)
        for conn in conns:
            with contextlib.suppress(OSError):
                conn.shutdown(socket.SHUT_RDWR)
            conn.close()
        for thread in self._threads:
            if thread is not threading.current_thread():
                thread.join(timeout=2.0)

    def __enter__(self) -> FakeURController:
        return self.start()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    # -- inspection and fault injection -------------------------------------------------------

    @property
    def host(self) -> str:
        """Address the fake listens on."""
        return self._host

    @property
    def rtde_port(self) -> int:
        """Bound RTDE port."""
        return int(self._ports["rtde"] or 0)

    @property
    def script_port(self) -> int:
        """Bound URScript port."""
        return int(self._ports["script"] or 0)

    @property
    def gripper_port(self) -> int | None:
        """Bound Robotiq URCap port, None without a gripper."""
        return self._ports["gripper"]

    @property
    def positions(self) -> FloatArray:
        """Actual joint positions [rad]. Shape (6,)."""
        with self._lock:
            return self._q.copy()

    @property
    def targets(self) -> FloatArray:
        """Servo targets in force [rad] (``target_q``). Shape (6,)."""
        with self._lock:
            return self._target.copy()

    @property
    def program_running(self) -> bool:
        """Whether a servo program is running (``runtime_state`` PLAYING)."""
        with self._lock:
            return self._servo is not None

    @property
    def safety_mode(self) -> SafetyMode:
        """Current safety mode."""
        return self._safety_mode

    @property
    def robot_mode(self) -> RobotMode:
        """Current robot mode."""
        return self._robot_mode

    @property
    def input_int_registers(self) -> tuple[int, ...]:
        """``input_int_register_0`` .. ``47`` as clients last wrote them."""
        with self._lock:
            return tuple(self._int_in)

    @property
    def input_double_registers(self) -> tuple[float, ...]:
        """``input_double_register_0`` .. ``47`` as clients last wrote them."""
        with self._lock:
            return tuple(self._double_in)

    @property
    def gripper_position(self) -> int:
        """Robotiq finger position 0 (open) .. 255 (closed)."""
        with self._lock:
            return int(self._grip["POS"])

    def protective_stop(self) -> None:
        """Enter a protective stop (as a collision would): the program stops, the joints brake."""
        with self._lock:
            self._safety_mode = SafetyMode.PROTECTIVE_STOP
            self._end_program(None)
            self._stop_decel = float(self._limits.acceleration.max())

    def emergency_stop(self) -> None:
        """Press the robot's emergency stop: the program stops, the arm powers off and stands still."""
        with self._lock:
            self._safety_mode = SafetyMode.ROBOT_EMERGENCY_STOP
            self._robot_mode = RobotMode.POWER_OFF
            self._end_program(None)
            self._qd[:] = 0.0

    def release(self) -> None:
        """Unlock a protective stop / release the emergency stop and power on (pendant actions)."""
        with self._lock:
            self._safety_mode = SafetyMode.NORMAL
            self._robot_mode = RobotMode.RUNNING

    def inject(self, data: bytes) -> None:
        """Send raw bytes to every connected RTDE client (to test a client's handling of bad packages)."""
        with self._lock:
            clients = list(self._rtde_clients)
        for client in clients:
            with client.send_lock, contextlib.suppress(OSError):
                client.sock.sendall(data)

    # -- plumbing -----------------------------------------------------------------------------

    def _spawn(self, name: str, target: Callable[..., None], *args: object) -> None:
        thread = threading.Thread(target=target, args=args, name=name, daemon=True)
        self._threads.append(thread)
        thread.start()

    def _accept(self, listener: socket.socket, handler: Callable[[socket.socket, str], None]) -> None:
        def client(conn: socket.socket, addr: tuple[str, int]) -> None:
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            conn.settimeout(0.1)
            with self._lock:
                self._conns.add(conn)
            self._spawn(f"fake-ur-conn-{addr[1]}", self._connection, conn, f"{addr[0]}:{addr[1]}", handler)

        accept_loop(listener, self._stop, client)

    def _connection(
        self, conn: socket.socket, address: str, handler: Callable[[socket.socket, str], None]
    ) -> None:
        try:
            handler(conn, address)
        except OSError:
            pass
        finally:
            with self._lock:
                self._conns.discard(conn)
            conn.close()

    def _recv(self, conn: socket.socket) -> bytes | None:
        """Next bytes from ``conn``; b"" on a poll timeout, None when the peer or the fake closed."""
        try:
            data = conn.recv(65536)
        except TimeoutError:
            return None if self._stop.is_set() else b""
        except OSError:
            return None
        return data or None

    # -- RTDE -----------------------------------------------------------------------------------

    def _serve_rtde(self, conn: socket.socket, address: str) -> None:
        client = _RtdeClient(conn, address)
        reader = rtde.FrameReader()
        with self._lock:
            self._rtde_clients.append(client)
        try:
            while (data := self._recv(conn)) is not None:
                try:
                    frames = reader.feed(data)
                except WireError as exc:
                    self.malformed_packets += 1
                    self._reply(client, TextMessage(str(exc), "fake-ur", MessageLevel.ERROR).encode())
                    return
                for frame in frames:
                    try:
                        self._handle_rtde(client, frame)
                    except WireError as exc:
                        self.malformed_packets += 1
                        _log.debug("fake UR: dropped package from %s: %s", address, exc)
                        self._reply(client, TextMessage(str(exc), "fake-ur", MessageLevel.ERROR).encode())
        finally:
            with self._lock:
                self._rtde_clients.remove(client)
                for name in [n for n, owner in self._owners.items() if owner is client]:
                    del self._owners[name]

    def _reply(self, client: _RtdeClient, data: bytes) -> None:
        with client.send_lock, contextlib.suppress(OSError):
            client.sock.sendall(data)

    def _handle_rtde(self, client: _RtdeClient, frame: rtde.Frame) -> None:
        cmd = frame.command
        if cmd == Command.DATA_PACKAGE:
            self._write_inputs(client, frame.payload)
        elif cmd == Command.REQUEST_PROTOCOL_VERSION:
            version = rtde.ProtocolVersionRequest.decode(frame.payload).version
            ok = version in self._protocol_versions
            if ok:
                client.version = version
            self._reply(client, rtde.Accepted(Command.REQUEST_PROTOCOL_VERSION, ok).encode())
        elif cmd == Command.GET_URCONTROL_VERSION:
            self._reply(client, self._version.encode())
        elif cmd == Command.CONTROL_PACKAGE_SETUP_OUTPUTS:
            self._setup_outputs(client, rtde.OutputSetup.decode(frame.payload))
        elif cmd == Command.CONTROL_PACKAGE_SETUP_INPUTS:
            self._setup_inputs(client, rtde.InputSetup.decode(frame.payload))
        elif cmd == Command.CONTROL_PACKAGE_START:
            # The reply goes out before the first data package, as on a controller (ur_rtde waits for it).
            ok = client.output is not None
            with client.send_lock:
                with contextlib.suppress(OSError):
                    client.sock.sendall(rtde.Accepted(Command.CONTROL_PACKAGE_START, ok).encode())
                client.started = ok
        elif cmd == Command.CONTROL_PACKAGE_PAUSE:
            client.started = False
            self._reply(client, rtde.Accepted(Command.CONTROL_PACKAGE_PAUSE, True).encode())
        elif cmd == Command.TEXT_MESSAGE:
            self.text_messages.append(TextMessage.decode(frame.payload))
        else:
            raise WireError(f"unknown RTDE package type {cmd}")

    def _require_v2(self, client: _RtdeClient, what: str) -> None:
        if client.version != rtde.PROTOCOL_VERSION:
            raise WireError(f"{what} before protocol version 2 was negotiated")

    def _setup_outputs(self, client: _RtdeClient, setup: rtde.OutputSetup) -> None:
        self._require_v2(client, "output setup")
        types = tuple(rtde.OUTPUT_TYPES.get(n, rtde.NOT_FOUND) for n in setup.names)
        max_rate = 1.0 / self._cycle
        ok = bool(setup.names) and rtde.NOT_FOUND not in types and 0 < setup.frequency <= max_rate
        if not 0 < setup.frequency <= max_rate:
            msg = f"output frequency {setup.frequency:g} Hz is outside (0, {max_rate:g}]"
            self._reply(client, TextMessage(msg, "fake-ur", MessageLevel.ERROR).encode())
        if ok:
            client.output = Recipe(1, setup.names, types)
            client.divisor = max(1, round(max_rate / setup.frequency))
        self._reply(client, SetupReply(Command.CONTROL_PACKAGE_SETUP_OUTPUTS, 1 if ok else 0, types).encode())

    def _setup_inputs(self, client: _RtdeClient, setup: rtde.InputSetup) -> None:
        self._require_v2(client, "input setup")
        with self._lock:
            types = []
            for name in setup.names:
                owner = self._owners.get(name)
                if name not in rtde.INPUT_TYPES:
                    types.append(rtde.NOT_FOUND)
                elif owner is not None and owner is not client:
                    types.append(rtde.IN_USE)
                else:
                    types.append(rtde.INPUT_TYPES[name])
            ok = bool(setup.names) and all(t in rtde.TYPE_FORMATS for t in types)
            recipe_id = 0
            if ok:
                recipe_id = client.next_input_id
                client.next_input_id += 1
                client.inputs[recipe_id] = Recipe(recipe_id, setup.names, tuple(types))
                for name in setup.names:
                    self._owners[name] = client
        self._reply(
            client, SetupReply(Command.CONTROL_PACKAGE_SETUP_INPUTS, recipe_id, tuple(types)).encode()
        )

    def _write_inputs(self, client: _RtdeClient, payload: bytes) -> None:
        recipe = client.inputs.get(rtde.recipe_id_of(payload))
        if recipe is None:
            raise WireError(f"data package for unknown input recipe {payload[0]}")
        values = recipe.decode(payload)
        with self._lock:
            for name, value in values.items():
                if name.startswith("input_int_register_"):
                    self._int_in[int(name.rsplit("_", 1)[1])] = int(value)  # type: ignore[arg-type]
                elif name.startswith("input_double_register_"):
                    self._double_in[int(name.rsplit("_", 1)[1])] = float(value)  # type: ignore[arg-type]

    def _output_value(self, name: str) -> Value:
        if name == "timestamp":
            return self._clock_offset + self._tick * self._cycle
        if name == "actual_q":
            return tuple(self._q.tolist())
        if name == "actual_qd":
            return tuple(self._qd.tolist())
        if name == "target_q":
            return tuple(self._target.tolist())
        if name == "target_qd":
            return tuple(self._qd.tolist())
        if name == "target_qdd":
            return tuple(self._qdd.tolist())
        if name == "robot_mode":
            return int(self._robot_mode)
        if name in ("safety_mode", "safety_status"):
            return int(self._safety_mode)
        if name == "runtime_state":
            return int(RuntimeState.PLAYING if self._servo is not None else RuntimeState.STOPPED)
        if name in ("speed_scaling", "target_speed_fraction"):
            return 1.0
        if name == "robot_status_bits":
            powered = self._robot_mode == RobotMode.RUNNING
            return int(powered) | (int(self._servo is not None) << 1)
        if name == "safety_status_bits":
            return 1 << (int(self._safety_mode) - 1)
        if name.startswith("input_int_register_"):
            return self._int_in[int(name.rsplit("_", 1)[1])]
        if name.startswith("input_double_register_"):
            return self._double_in[int(name.rsplit("_", 1)[1])]
        type_name = rtde.OUTPUT_TYPES[name]
        fmt = rtde.TYPE_FORMATS[type_name]
        if fmt[0].isdigit():
            return (0,) * int(fmt[0]) if fmt[-1] in "iI" else (0.0,) * int(fmt[0])
        return 0.0 if fmt == "d" else 0

    # -- URScript -------------------------------------------------------------------------------

    def _serve_script(self, conn: socket.socket, address: str) -> None:
        pending = ""
        block: list[str] | None = None
        while (data := self._recv(conn)) is not None:
            pending += data.decode("utf-8", "replace")
            *lines, pending = pending.split("\n")
            for line in lines:
                if block is not None:
                    block.append(line)
                    if line.rstrip() == "end":
                        self._run_script("\n".join(block) + "\n")
                        block = None
                elif line.startswith("def ") or line.startswith("sec "):
                    block = [line]
                elif line.strip():
                    self._run_script(line + "\n")

    def _run_script(self, text: str) -> None:
        with self._lock:
            self.programs_received += 1
            self.last_program = text
            servo = ServoProgram.parse(text)
            if servo is not None:
                if self._safety_mode != SafetyMode.NORMAL or self._robot_mode != RobotMode.RUNNING:
                    self.rejected_scripts += 1
                    _log.warning("fake UR: refused program, robot is in %s", self._safety_mode.name)
                    return
                self._servo = _Servo(servo, self._int_in[servo.int_register])
                self._stop_decel = None
                return
            if "protective_stop()" in text:
                self.protective_stop()
                return
            if (
                "servoj" not in text
                and (decel := next((float(v) for v in _stopj_args(text)), None)) is not None
            ):
                self._end_program(decel)
                return
            self.rejected_scripts += 1
            _log.warning("fake UR: does not understand this script, ignored:\n%s", text)

    def _end_program(self, decel: float | None) -> None:
        """Stop the servo program (lock held); brake at ``decel`` [rad/s^2] (None: keep the current plan)."""
        self._servo = None
        self._target = self._q.copy()
        if decel is not None:
            self._stop_decel = decel

    # -- Robotiq URCap ----------------------------------------------------------------------------

    def _serve_gripper(self, conn: socket.socket, address: str) -> None:
        pending = b""
        while (data := self._recv(conn)) is not None:
            pending += data
            *lines, pending = pending.split(b"\n")
            for line in lines:
                conn.sendall(self._gripper_command(line.decode("ascii", "replace").strip()).encode() + b"\n")

    def _gripper_command(self, line: str) -> str:
        words = line.split()
        with self._lock:
            if len(words) == 2 and words[0] == "GET" and words[1] in self._grip:
                return f"{words[1]} {self._grip[words[1]]}"
            if len(words) >= 3 and words[0] == "SET" and len(words) % 2 == 1:
                pairs = list(zip(words[1::2], words[2::2], strict=True))
                if all(k in ("ACT", "GTO", "POS", "SPE", "FOR") and v.isdigit() for k, v in pairs):
                    for key, value in pairs:
                        number = min(int(value), 255)
                        self._grip["PRE" if key == "POS" else key] = number
                    self._grip["STA"] = 3 if self._grip["ACT"] else 0
                    return "ack"
        return "?"

    # -- controller cycle -------------------------------------------------------------------------

    def _run(self) -> None:
        period = self._cycle
        deadline = time.monotonic()
        try:
            while not self._stop.is_set():
                self._step()
                self._publish()
                deadline += period
                delay = deadline - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                elif delay < -25 * period:
                    deadline = time.monotonic()  # too far behind: the fake clock slips, like a loaded host
        except Exception:
            _log.exception("fake UR: controller cycle failed")
            raise

    def _step(self) -> None:
        dt = self._cycle
        lim = self._limits
        with self._lock:
            self._tick += 1
            servo = self._servo
            active = False
            if servo is not None:
                every = max(1, round(servo.program.period_s / dt))
                if self._tick % every == 0:
                    word = self._int_in[servo.program.int_register]
                    if word < 0:
                        self.stop_requests += 1
                        self._end_program(servo.program.stop_deceleration)
                        servo = None
                    else:
                        if word != servo.word_last:
                            servo.word_last, servo.stale, servo.armed = word, 0, True
                        else:
                            servo.stale += 1
                        if servo.armed and servo.stale > servo.program.watchdog_cycles:
                            self.watchdog_stops += 1
                            self._end_program(servo.program.stop_deceleration)
                            servo = None
                        elif servo.armed:
                            regs = servo.program.double_registers
                            self._target = np.array([self._double_in[i] for i in regs])
                active = servo is not None and servo.armed
            qd_old = self._qd.copy()
            if self._robot_mode != RobotMode.RUNNING:
                self._qd[:] = 0.0
            elif active:
                lookahead = servo.program.lookahead_s if servo is not None else 0.1
                want = np.clip((self._target - self._q) / max(lookahead, dt), -lim.velocity, lim.velocity)
                step = lim.acceleration * dt
                self._qd += np.clip(want - self._qd, -step, step)
            else:
                decel = self._stop_decel if self._stop_decel is not None else float(lim.acceleration.max())
                self._qd -= np.clip(self._qd, -decel * dt, decel * dt)
            self._q = np.clip(self._q + self._qd * dt, lim.lower, lim.upper)
            self._qdd = (self._qd - qd_old) / dt
            grip = self._grip
            if grip["GTO"] and grip["STA"] == 3 and grip["POS"] != grip["PRE"]:
                speed = max(1, round((grip["SPE"] + 1) * dt * 2))  # full stroke in ~0.5 s at SPE 255
                delta = max(-speed, min(speed, grip["PRE"] - grip["POS"]))
                grip["POS"] += delta

    def _publish(self) -> None:
        with self._lock:
            out = []
            for client in self._rtde_clients:
                if client.started and client.output is not None and self._tick % client.divisor == 0:
                    values = {n: self._output_value(n) for n in client.output.names}
                    out.append((client, client.output.encode(values)))
        for client, data in out:
            self._reply(client, data)


def _stopj_args(text: str) -> list[str]:
    return re.findall(r"\bstopj\(([0-9.]+)\)", text)
