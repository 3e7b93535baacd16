"""DH-Robotics parallel gripper driver over Modbus RTU: one prismatic DoF, the finger opening in metres."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Literal

import numpy as np

from telerig.errors import RobotError
from telerig.ir.types import GripperCommand, JointCommand, JointState, Stamp
from telerig.robots.base import JointLimits
from telerig.robots.modbus._link import LinkDownError, ModbusLink, PolledDriver, serial_client, tcp_client
from telerig.robots.modbus.registers import DH, DH_STATUS_BLOCK, DHGripState, DHInitState

__all__ = ["DHGripper", "DHStatus"]

_log = logging.getLogger("telerig.robots.modbus")


@dataclass(frozen=True, slots=True)
class DHStatus:
    """The gripper's state registers from the latest poll.

    Attributes:
        init_state: 0x0200, see :class:`~telerig.robots.modbus.registers.DHInitState`.
        grip_state: 0x0201, see :class:`~telerig.robots.modbus.registers.DHGripState`.
        position_permille: 0x0202, finger position 0 (closed) .. 1000 (open).
        capture_ns: When the read request went out, common clock [ns].
    """

    init_state: int
    grip_state: int
    position_permille: int
    capture_ns: int

    @property
    def object_caught(self) -> bool:
        """True when the fingers stopped on an object."""
        return self.grip_state == DHGripState.OBJECT_CAUGHT


class DHGripper(PolledDriver):
    """A DH-Robotics AG / PGE / PGC / CGC gripper on Modbus RTU, modelled as a 1-DoF robot.

    The one joint (``<prefix>finger``) is the opening between the fingers in [m], 0 (closed)
    to ``stroke_m`` (open); the POSITION register holds it in permille of the stroke, so
    commands are quantised to stroke/1000. :meth:`send` (a :class:`JointCommand` in metres)
    and :meth:`send_gripper` (an opening in 0..1) both write that register, so the gripper
    sits behind the same safety chain (limits, e-stop) as any robot and its state carries
    the measured opening.

    Transport: a serial RS-485 device (``/dev/ttyUSB0``, 115200 8N1 by default) or RTU frames
    over TCP for an RS-485-to-Ethernet gateway. Both go through one pymodbus sync client
    owned by the driver thread; each poll is one read of 0x0200..0x0202.

    E-stop: the gripper has no stop register; :meth:`estop` writes the measured position as
    the target (it holds what it grips, at the configured force) and ignores commands until
    :meth:`reset_estop`.
    """

    def __init__(
        self,
        *,
        transport: Literal["serial", "rtu_over_tcp"] = "serial",
        device: str = "/dev/ttyUSB0",
        baudrate: int = 115200,
        parity: Literal["N", "E", "O"] = "N",
        stopbits: Literal[1, 2] = 1,
        host: str = "127.0.0.1",
        port: int = 502,
        device_id: int = 1,
        name: str = "dh_gripper",
        joint_prefix: str = "",
        stroke_m: float = 0.095,
        rated_force_n: float = 160.0,
        full_stroke_s: float = 0.7,
        force_percent: int = 50,
        speed_percent: int = 100,
        initialize: bool = True,
        init_timeout_s: float = 10.0,
        poll_rate_hz: float = 50.0,
        timeout_s: float = 0.1,
        stale_after_s: float = 0.5,
    ) -> None:
        """Configure the driver (no I/O until :meth:`connect`).

        Args:
            transport: ``"serial"`` (``device``, ``baudrate``, ``parity``, ``stopbits``) or
                ``"rtu_over_tcp"`` (``host``, ``port``).
            device_id: Modbus slave address (DH default 1).
            name: Driver name, the stamps' ``source_id``.
            joint_prefix: Prefix of the joint name.
            stroke_m: Full opening of the model [m] (AG-95: 0.095).
            rated_force_n: Force at 100 % [N] (AG-95: 160); scales ``max_force``.
            full_stroke_s: Time of a full stroke at 100 % speed [s]; sets the velocity limit.
            force_percent: Force written on connect, 20..100 [%].
            speed_percent: Speed written on connect, 1..100 [%].
            initialize: Write 1 to the initialization register on connect if the gripper is
                not initialized (the fingers move to find their end stop); :meth:`connect` then
                returns once it is, so the first state read is the gripper's real opening.
            init_timeout_s: Longest wait for that initialization to finish [s].
            poll_rate_hz: State polling rate [Hz].
            timeout_s: Per-request answer timeout [s].
            stale_after_s: Declare the gripper gone after this long without a valid answer [s].
        """
        if stroke_m <= 0 or rated_force_n <= 0 or full_stroke_s <= 0 or init_timeout_s <= 0:
            raise ValueError("stroke_m, rated_force_n, full_stroke_s and init_timeout_s must be positive")
        if not DH.FORCE_MIN <= force_percent <= DH.FORCE_MAX:
            raise ValueError(f"force_percent must be in {DH.FORCE_MIN}..{DH.FORCE_MAX}, got {force_percent}")
        if not DH.SPEED_MIN <= speed_percent <= DH.SPEED_MAX:
            raise ValueError(f"speed_percent must be in {DH.SPEED_MIN}..{DH.SPEED_MAX}, got {speed_percent}")
        if transport == "serial":
            where = f"DH gripper {device_id} on {device}"

            def make() -> ModbusLink:
                client = serial_client(
                    device, baudrate=baudrate, parity=parity, stopbits=stopbits, timeout_s=timeout_s
                )
                return ModbusLink(client, device_id, where)
        elif transport == "rtu_over_tcp":
            where = f"DH gripper {device_id} via {host}:{port}"

            def make() -> ModbusLink:
                client = tcp_client(host, port, timeout_s=timeout_s, rtu_framing=True)
                return ModbusLink(client, device_id, where)
        else:
            raise ValueError(f"transport must be 'serial' or 'rtu_over_tcp', got {transport!r}")
        super().__init__(name, make, poll_rate_hz=poll_rate_hz, stale_after_s=stale_after_s)
        self._names = (joint_prefix + "finger",)
        self._stroke = stroke_m
        self._rated_force = rated_force_n
        self._force_pct = force_percent
        self._speed_pct = speed_percent
        self._initialize = initialize
        self._init_timeout_s = init_timeout_s
        v = stroke_m / full_stroke_s
        # No acceleration figure in the manual: assume full speed is reached in 0.1 s.
        self._limits = JointLimits(
            self._names, np.array([0.0]), np.array([stroke_m]), np.array([v]), np.array([v / 0.1])
        )
        self._permille = 0
        self._target = 0
        self._velocity = 0.0
        self._capture_ns = 0
        self._arrival_ns = 0
        self._status = DHStatus(0, 0, 0, 0)
        self._grip_state_seq = 0

    # -- RobotDriver ---------------------------------------------------------------------------

    @property
    def joint_names(self) -> tuple[str, ...]:
        """One prismatic joint: the opening between the fingers [m]."""
        return self._names

    @property
    def limits(self) -> JointLimits:
        """0..stroke [m]; velocity from ``full_stroke_s`` [m/s]."""
        return self._limits

    def read_state(self) -> JointState:
        """Latest polled opening [m] and finite-difference velocity [m/s]; no efforts.

        ``capture_ns`` is when the read request went out; ``arrival_ns`` when the answer came.
        Does no I/O.

        Raises:
            RobotError: the driver is not connected or the gripper stopped answering.
        """
        self._require_connected()
        with self._lock:
            position = self._permille / DH.POSITION_MAX * self._stroke
            velocity = self._velocity
            capture, arrival = self._capture_ns, self._arrival_ns
            seq = self._next_state_seq()
        stamp = Stamp(self._name, seq, device_ns=capture, capture_ns=capture, arrival_ns=arrival)
        return JointState(stamp, self._names, np.array([position]), np.array([velocity]))

    def read_gripper(self) -> GripperCommand:
        """Latest polled opening (0 closed, 1 open: the POSITION feedback in permille); no I/O.

        Stamped like :meth:`read_state` (capture: the read request; arrival: its answer).

        Raises:
            RobotError: the driver is not connected or the gripper stopped answering.
        """
        self._require_connected()
        with self._lock:
            opening = self._permille / DH.POSITION_MAX
            capture, arrival = self._capture_ns, self._arrival_ns
            seq = self._grip_state_seq
            self._grip_state_seq += 1
        return GripperCommand(Stamp(self._name, seq, capture, capture, arrival), opening)

    def status(self) -> DHStatus:
        """Initialization state, grip state and position feedback from the latest poll."""
        self._require_connected()
        with self._lock:
            return self._status

    def send(self, command: JointCommand) -> JointCommand:
        """Queue an opening target [m] for the finger joint; no I/O.

        Clipped to 0..stroke and quantised to permille. Ignored while the e-stop is latched.

        Returns:
            The target in force [m], stamped now.

        Raises:
            RobotError: a joint name other than the finger joint, or the gripper not connected / gone.
        """
        self._require_connected()
        for n in command.names:
            if n != self._names[0]:
                raise RobotError(f"{self._name}: joint {n!r} not found. Available: {self._names[0]}")
        if not command.names:
            return self._stamp_joint(command.names, [])
        permille = self._queue_position(float(command.positions[-1]) / self._stroke)
        opening = permille / DH.POSITION_MAX * self._stroke
        return self._stamp_joint(command.names, [opening] * len(command.names))

    @property
    def has_gripper(self) -> bool:
        """Always: this robot is a gripper (or a hand with an open/close synergy)."""
        return True

    def send_gripper(self, command: GripperCommand) -> GripperCommand:
        """Queue an opening (0 closed, 1 open; clipped, quantised to permille); no I/O.

        ``max_force`` [N] > 0 also sets the force register (as a percentage of ``rated_force_n``,
        clipped to 20..100 %). Ignored while the e-stop is latched.

        Returns:
            The opening in force and the force limit in force [N] (0 if not requested).
        """
        self._require_connected()
        if command.max_force > 0 and not self._estopped:
            pct = int(np.clip(round(100 * command.max_force / self._rated_force), DH.FORCE_MIN, DH.FORCE_MAX))
            self._force_pct = pct
            self._queue_write("force", DH.FORCE, [pct])
        permille = self._queue_position(float(command.opening))
        force = self._force_pct / 100 * self._rated_force if command.max_force > 0 else 0.0
        with self._lock:
            seq = self._next_cmd_seq()
        t = time.time_ns()
        return GripperCommand(Stamp(self._name, seq, t, t), permille / DH.POSITION_MAX, force)

    def estop(self) -> None:
        """Latch the e-stop: write the measured position as the target, then ignore commands.

        Waits up to 0.3 s for the gripper to acknowledge the hold write (RS-485 is slower).
        """
        with self._lock:
            self._estopped = True
            self._target = self._permille
            hold = self._target
        if not self.connected:
            _log.warning("%s: emergency stop latched while disconnected; nothing written", self._name)
            return
        ticket = self._queue_write("position", DH.POSITION, [hold])
        if self._wait_written(ticket, 0.3):
            _log.warning("%s: emergency stop latched, holding %d permille", self._name, hold)
        else:
            _log.error("%s: emergency stop latched but the hold write was not acknowledged", self._name)

    # -- internals ----------------------------------------------------------------------------

    def _queue_position(self, fraction: float) -> int:
        permille = int(np.clip(round(fraction * DH.POSITION_MAX), 0, DH.POSITION_MAX))
        with self._lock:
            if self._estopped:
                return self._target
            self._target = permille
        self._queue_write("position", DH.POSITION, [permille])
        return permille

    def _stamp_joint(self, names: tuple[str, ...], positions: list[float]) -> JointCommand:
        with self._lock:
            seq = self._next_cmd_seq()
        t = time.time_ns()
        return JointCommand(Stamp(self._name, seq, t, t), names, np.asarray(positions, dtype=np.float64))

    def _on_connect(self, link: ModbusLink) -> None:
        state = link.read(*DH_STATUS_BLOCK)
        if state is None:
            raise LinkDownError(f"{link.where} rejected the read of the state registers")
        if (
            self._initialize
            and state[0] == DHInitState.NOT_INITIALIZED
            and not link.write(DH.INIT, [DH.INIT_CMD])
        ):
            raise LinkDownError(f"{link.where} rejected the initialization command")
        if self._initialize and state[0] != DHInitState.INITIALIZED:
            # Until it is initialized the gripper reads closed and ignores targets, then opens
            # fully: a state read or an e-stop hold taken before then would be wrong.
            self._wait_initialized(link)
        for address, value in ((DH.FORCE, self._force_pct), (DH.SPEED, self._speed_pct)):
            if not link.write(address, [value]):
                raise LinkDownError(f"{link.where} rejected the write to register 0x{address:04X}")
        target = link.read(DH.POSITION, 1)
        if target is None:
            raise LinkDownError(f"{link.where} rejected the read of the position target")
        with self._lock:
            self._target = target[0]

    def _wait_initialized(self, link: ModbusLink) -> None:
        deadline = time.monotonic() + self._init_timeout_s
        while True:
            state = link.read(DH.INIT_STATE, 1)
            if state is not None and state[0] == DHInitState.INITIALIZED:
                return
            if time.monotonic() > deadline:
                raise LinkDownError(
                    f"{link.where} did not finish initializing within {self._init_timeout_s:g} s "
                    "(is something blocking the fingers?)"
                )
            time.sleep(0.02)

    def _poll(self, link: ModbusLink, sent_ns: int) -> None:
        regs = link.read(*DH_STATUS_BLOCK)
        arrival = time.time_ns()
        if regs is None:
            return
        with self._lock:
            permille = regs[2]
            if self._capture_ns:
                dt = (sent_ns - self._capture_ns) / 1e9
                if dt > 0:
                    self._velocity = (permille - self._permille) / DH.POSITION_MAX * self._stroke / dt
            self._permille = permille
            self._capture_ns = sent_ns
            self._arrival_ns = arrival
            self._status = DHStatus(regs[0], regs[1], permille, sent_ns)
