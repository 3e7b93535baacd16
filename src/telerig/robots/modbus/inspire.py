"""Inspire RH56 dexterous hand driver over Modbus TCP: six actuated DoF in radians, polled on a thread."""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from telerig.errors import RobotError
from telerig.ir.types import FloatArray, GripperCommand, JointCommand, JointState, Stamp
from telerig.robots.base import JointLimits
from telerig.robots.modbus._link import LinkDownError, ModbusLink, PolledDriver, tcp_client
from telerig.robots.modbus.registers import INSPIRE, INSPIRE_JOINTS, InspireError, InspireJoint

__all__ = ["InspireHand", "InspireHealth"]

_log = logging.getLogger("telerig.robots.modbus")


@dataclass(frozen=True, slots=True)
class InspireHealth:
    """Per-finger health registers from the latest poll, in the hand's finger order.

    Attributes:
        errors: ERROR flags per DoF (see :class:`~telerig.robots.modbus.registers.InspireError`). Length 6.
        status: STATUS code per DoF (see :class:`~telerig.robots.modbus.registers.InspireStatus`). Length 6.
        temperatures_c: Actuator temperature per DoF [degC]. Length 6.
        capture_ns: When the read request went out, common clock [ns].
    """

    errors: tuple[int, ...]
    status: tuple[int, ...]
    temperatures_c: tuple[int, ...]
    capture_ns: int

    @property
    def faulted(self) -> bool:
        """True when any DoF reports an error flag."""
        return any(self.errors)

    def describe(self, names: Sequence[str]) -> str:
        """One line naming each faulted DoF and its flags, e.g. ``index: OVER_CURRENT``."""
        parts = [
            f"{name}: {'|'.join(f.name or '?' for f in InspireError(code))}"
            for name, code in zip(names, self.errors, strict=True)
            if code
        ]
        return "; ".join(parts) if parts else "no errors"


def _unpack_bytes(registers: Sequence[int]) -> tuple[int, ...]:
    # Two 8-bit values per register, low byte first (finger 2k in the low byte).
    out: list[int] = []
    for reg in registers:
        out.extend((reg & 0xFF, (reg >> 8) & 0xFF))
    return tuple(out)


def _int16(values: Sequence[int]) -> FloatArray:
    arr = np.asarray(values, dtype=np.int64)
    return np.where(arr >= 0x8000, arr - 0x10000, arr).astype(np.float64)


class InspireHand(PolledDriver):
    """An Inspire RH56 hand (DFX / DFTP) on Modbus TCP, six actuated DoF.

    Joint angles are the manual's angle of each DoF in [rad] (see
    :data:`~telerig.robots.modbus.registers.INSPIRE_JOINTS`); register units 0..1000 map
    linearly onto each range, so commands are quantised to range/1000 (about 2.75 mrad for a
    finger). Mimic joints (distal phalanges) are driven by the hand's linkage and not exposed.

    I/O: one pymodbus sync client owned by the driver thread. Each poll reads ANGLE_ACT,
    FORCE_ACT and ERROR..TEMP (three requests). :meth:`send` queues an ANGLE_SET write and
    returns at once; the thread writes it at once and reads the state back right after.

    E-stop: the hand has no stop register, so :meth:`estop` writes the measured angles as the
    targets (the fingers hold where they are, at the configured force threshold) and ignores
    commands until :meth:`reset_estop`.
    """

    def __init__(
        self,
        host: str,
        port: int = 6000,
        *,
        device_id: int = 1,
        name: str = "inspire_hand",
        joint_prefix: str = "",
        joints: Sequence[InspireJoint] = INSPIRE_JOINTS,
        poll_rate_hz: float = 100.0,
        timeout_s: float = 0.1,
        stale_after_s: float = 0.5,
        speed: int = 1000,
        force: int = 500,
        full_stroke_s: float = 0.8,
    ) -> None:
        """Configure the driver (no I/O until :meth:`connect`).

        Args:
            host: Hand IP address (factory default 192.168.11.210).
            port: Modbus TCP port (factory default 6000).
            device_id: Modbus unit id.
            name: Driver name, the stamps' ``source_id``.
            joint_prefix: Prefix of every joint name, e.g. ``"right_"``.
            joints: The six DoF and their angle ranges, in the hand's finger order.
            poll_rate_hz: State polling rate [Hz].
            timeout_s: Per-request answer timeout [s].
            stale_after_s: Declare the hand gone after this long without a valid answer [s].
            speed: SPEED_SET written on connect, 0..1000 for every DoF.
            force: FORCE_SET written on connect, 0..1000 [g] for every DoF.
            full_stroke_s: Time of a full 0..1000 travel at speed 1000 [s]; sets the velocity
                limits. An estimate; measure it on your hand.
        """
        if len(joints) != INSPIRE.N:
            raise ValueError(f"joints must list the hand's {INSPIRE.N} DoF, got {len(joints)}")
        if not 0 <= speed <= INSPIRE.UNIT_MAX or not 0 <= force <= INSPIRE.UNIT_MAX:
            raise ValueError(f"speed and force must be in 0..{INSPIRE.UNIT_MAX}, got {speed} and {force}")
        if full_stroke_s <= 0:
            raise ValueError(f"full_stroke_s must be positive, got {full_stroke_s}")
        where = f"Inspire hand at {host}:{port}"
        super().__init__(
            name,
            lambda: ModbusLink(tcp_client(host, port, timeout_s=timeout_s), device_id, where),
            poll_rate_hz=poll_rate_hz,
            stale_after_s=stale_after_s,
        )
        self._joints = tuple(joints)
        self._names = tuple(joint_prefix + j.name for j in self._joints)
        self._index = {n: i for i, n in enumerate(self._names)}
        self._a0 = np.array([j.angle_at_0 for j in self._joints])
        self._a1000 = np.array([j.angle_at_1000 for j in self._joints])
        lower = np.minimum(self._a0, self._a1000)
        upper = np.maximum(self._a0, self._a1000)
        velocity = (upper - lower) / full_stroke_s
        # No acceleration figure in the manual: assume full speed is reached in 0.1 s.
        self._limits = JointLimits(self._names, lower, upper, velocity, velocity / 0.1)
        self._speed = speed
        self._force = force
        self._units = np.zeros(INSPIRE.N, dtype=np.int64)  # measured ANGLE_ACT
        self._target = np.zeros(INSPIRE.N, dtype=np.int64)  # ANGLE_SET as last queued
        self._force_g = np.zeros(INSPIRE.N)
        self._velocity = np.zeros(INSPIRE.N)
        self._capture_ns = 0
        self._arrival_ns = 0
        self._health = InspireHealth((0,) * 6, (0,) * 6, (0,) * 6, 0)

    # -- conversions --------------------------------------------------------------------------

    def to_units(self, angles: FloatArray) -> np.ndarray:
        """Joint angles [rad], shape (6,) → register units 0..1000 (clipped, rounded). Shape (6,)."""
        frac = (np.asarray(angles, dtype=np.float64) - self._a0) / (self._a1000 - self._a0)
        units: np.ndarray = np.clip(np.rint(frac * INSPIRE.UNIT_MAX), 0, INSPIRE.UNIT_MAX).astype(np.int64)
        return units

    def to_angles(self, units: np.ndarray) -> FloatArray:
        """Register units 0..1000, shape (6,) → joint angles [rad]. Shape (6,)."""
        frac = np.asarray(units, dtype=np.float64) / INSPIRE.UNIT_MAX
        return np.asarray(self._a0 + frac * (self._a1000 - self._a0), dtype=np.float64)

    # -- RobotDriver ---------------------------------------------------------------------------

    @property
    def joint_names(self) -> tuple[str, ...]:
        """The six actuated DoF: little, ring, middle, index, thumb bend, thumb rotation."""
        return self._names

    @property
    def limits(self) -> JointLimits:
        """Angle ranges of the manual [rad]; velocity from ``full_stroke_s`` [rad/s]."""
        return self._limits

    def read_state(self) -> JointState:
        """Latest polled angles [rad], finite-difference velocities [rad/s], finger forces [N].

        ``capture_ns`` is when the ANGLE_ACT read request went out; ``arrival_ns`` when the
        poll's last response came back. Does no I/O.

        Raises:
            RobotError: the driver is not connected or the hand stopped answering.
        """
        self._require_connected()
        with self._lock:
            positions = self.to_angles(self._units)
            velocities = self._velocity.copy()
            efforts = self._force_g * INSPIRE.FORCE_UNIT_N
            capture, arrival = self._capture_ns, self._arrival_ns
            seq = self._next_state_seq()
        stamp = Stamp(self._name, seq, device_ns=capture, capture_ns=capture, arrival_ns=arrival)
        return JointState(stamp, self._names, positions, velocities, efforts)

    def health(self) -> InspireHealth:
        """ERROR, STATUS and TEMP registers from the latest poll."""
        self._require_connected()
        with self._lock:
            return self._health

    def send(self, command: JointCommand) -> JointCommand:
        """Queue angle targets [rad] for the named DoF (any subset, any order); no I/O.

        Targets are clipped to the ranges and quantised to register units; DoF not named keep
        their current target. While the e-stop is latched nothing is queued.

        Returns:
            The targets in force for ``command.names`` [rad] (quantised), stamped now.

        Raises:
            RobotError: a joint name is unknown, or the hand is not connected / gone.
        """
        self._require_connected()
        idx = self._indices(command.names)
        with self._lock:
            target = self._target.copy()
            if not self._estopped:
                full = self.to_angles(target)
                full[idx] = command.positions
                target = self.to_units(full)
                self._target = target
            seq = self._next_cmd_seq()
        if not self._estopped:
            self._queue_write("angle", INSPIRE.ANGLE_SET, [int(u) for u in target])
        t = time.time_ns()
        applied = self.to_angles(target)[idx]
        return JointCommand(Stamp(self._name, seq, device_ns=t, capture_ns=t), command.names, applied)

    @property
    def has_gripper(self) -> bool:
        """Always: this robot is a gripper (or a hand with an open/close synergy)."""
        return True

    def send_gripper(self, command: GripperCommand) -> GripperCommand:
        """Open/close synergy: the four fingers and the thumb bend go to ``opening`` of their range.

        ``opening`` 0 closes, 1 opens (clipped); the thumb rotation keeps its target.
        ``max_force`` [N] > 0 also sets every finger's force threshold (clipped to 0..1000 g).

        Returns:
            The applied opening (mean over the five DoF, quantised) and force threshold [N].
        """
        self._require_connected()
        opening = float(np.clip(command.opening, 0.0, 1.0))
        unit = round(opening * INSPIRE.UNIT_MAX)
        force_n = 0.0
        with self._lock:
            if not self._estopped:
                self._target[:5] = unit
            target = self._target.copy()
            seq = self._next_cmd_seq()
        if not self._estopped:
            if command.max_force > 0:
                grams = int(np.clip(round(command.max_force / INSPIRE.FORCE_UNIT_N), 0, INSPIRE.UNIT_MAX))
                self._force = grams
                self._queue_write("force", INSPIRE.FORCE_SET, [grams] * INSPIRE.N)
            self._queue_write("angle", INSPIRE.ANGLE_SET, [int(u) for u in target])
        if command.max_force > 0:
            force_n = self._force * INSPIRE.FORCE_UNIT_N
        t = time.time_ns()
        applied = float(np.mean(target[:5])) / INSPIRE.UNIT_MAX
        return GripperCommand(Stamp(self._name, seq, device_ns=t, capture_ns=t), applied, force_n)

    def estop(self) -> None:
        """Latch the e-stop: write the measured angles as targets, then ignore commands.

        Waits up to 0.2 s for the hand to acknowledge the hold write; if it does not (hand gone),
        the latch still holds and a warning is logged.
        """
        with self._lock:
            self._estopped = True
            self._target = self._units.copy()
            hold = [int(u) for u in self._target]
        if not self.connected:
            _log.warning("%s: emergency stop latched while disconnected; nothing written", self._name)
            return
        ticket = self._queue_write("angle", INSPIRE.ANGLE_SET, hold)
        if self._wait_written(ticket, 0.2):
            _log.warning("%s: emergency stop latched, holding %s", self._name, hold)
        else:
            _log.error("%s: emergency stop latched but the hold write was not acknowledged", self._name)

    def clear_errors(self) -> None:
        """Queue a write of 1 to CLEAR_ERROR (clears the hand's error flags)."""
        self._require_connected()
        self._queue_write("clear_error", INSPIRE.CLEAR_ERROR, [1])

    # -- internals ----------------------------------------------------------------------------

    def _indices(self, names: tuple[str, ...]) -> list[int]:
        try:
            return [self._index[n] for n in names]
        except KeyError as exc:
            raise RobotError(
                f"{self._name}: joint {exc.args[0]!r} not found. Available: {', '.join(self._names)}"
            ) from None

    def _on_connect(self, link: ModbusLink) -> None:
        for address, values in (
            (INSPIRE.SPEED_SET, [self._speed] * INSPIRE.N),
            (INSPIRE.FORCE_SET, [self._force] * INSPIRE.N),
        ):
            if not link.write(address, values):
                raise LinkDownError(f"{link.where} rejected the write to register {address}")
        current = link.read(INSPIRE.ANGLE_SET, INSPIRE.N)
        if current is None:
            raise LinkDownError(f"{link.where} rejected the read of ANGLE_SET ({INSPIRE.ANGLE_SET})")
        with self._lock:
            self._target = np.asarray(current, dtype=np.int64)

    def _poll(self, link: ModbusLink, sent_ns: int) -> None:
        angles = link.read(INSPIRE.ANGLE_ACT, INSPIRE.N)
        forces = link.read(INSPIRE.FORCE_ACT, INSPIRE.N)
        health = link.read(INSPIRE.ERROR, INSPIRE.TEMP + INSPIRE.N_PACKED - INSPIRE.ERROR)
        arrival = time.time_ns()
        with self._lock:
            if angles is not None:
                units = np.asarray(angles, dtype=np.int64)
                if self._capture_ns:
                    dt = (sent_ns - self._capture_ns) / 1e9
                    if dt > 0:
                        self._velocity = (self.to_angles(units) - self.to_angles(self._units)) / dt
                self._units = units
                self._capture_ns = sent_ns
                self._arrival_ns = arrival
            if forces is not None:
                self._force_g = _int16(forces)
            if health is not None:
                off_s = INSPIRE.STATUS - INSPIRE.ERROR
                off_t = INSPIRE.TEMP - INSPIRE.ERROR
                errors = _unpack_bytes(health[: INSPIRE.N_PACKED])
                new = InspireHealth(
                    errors,
                    _unpack_bytes(health[off_s : off_s + INSPIRE.N_PACKED]),
                    _unpack_bytes(health[off_t : off_t + INSPIRE.N_PACKED]),
                    sent_ns,
                )
                if new.faulted and not self._health.faulted:
                    _log.error("%s: hand reports %s", self._name, new.describe(self._names))
                self._health = new
