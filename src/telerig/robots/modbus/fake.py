"""Fake Modbus peers for dry runs and tests: an Inspire hand on Modbus TCP and a DH gripper on Modbus RTU.

Both are real pymodbus servers on this host, so a driver talks to them exactly as to the
hardware. The Inspire fake listens on 127.0.0.1 (a free port by default). The DH fake speaks
RTU over a pseudo-terminal pair bridged like a null-modem cable (the real gripper is RS-485
serial, so the driver's serial stack, framing and timeouts are exercised end to end), or,
with ``transport="tcp"``, RTU frames over TCP like an RS-485-to-Ethernet gateway.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import select
import threading
import time
import tty
from collections.abc import Callable
from types import TracebackType
from typing import Any, Literal, Self

from telerig.bus.peer_loop import PeerLoop
from telerig.errors import DependencyError, RobotError
from telerig.robots.modbus.registers import DH, INSPIRE, DHGripState, DHInitState, InspireStatus

__all__ = ["FakeDHGripper", "FakeInspireHand"]


def _pymodbus() -> Any:
    try:
        import pymodbus.constants
        import pymodbus.framer
        import pymodbus.server
        import pymodbus.simulator
    except ImportError:  # pragma: no cover - depends on the environment
        raise DependencyError(
            "the Modbus fakes need pymodbus; pip install 'pymodbus>=3.16,<4' pyserial"
        ) from None
    return pymodbus


class _FakePeer:
    """A pymodbus server on its own thread and event loop, with fault injection."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        name = type(self).__name__
        self._peer = PeerLoop(self._main, what=name, thread_name=name, error=RobotError)
        self._fail_next = 0
        self._garble_next = 0
        self.requests = 0

    # -- fault injection -------------------------------------------------------------------------

    def fail_next(self, n: int = 1) -> None:
        """Answer the next ``n`` requests with a Modbus exception response (device busy)."""
        with self._lock:
            self._fail_next += n

    def garble_next(self, n: int = 1) -> None:
        """Corrupt the next ``n`` response frames on the wire (the driver sees malformed frames)."""
        with self._lock:
            self._garble_next += n

    # -- lifecycle --------------------------------------------------------------------------------

    def start(self) -> Self:
        """Start serving; returns when the server listens. Idempotent.

        Raises:
            RobotError: the server failed to start (e.g. its port is taken).
        """
        self._peer.start()
        return self

    def stop(self) -> None:
        """Stop serving and drop every connection (the peer "dies"). Idempotent."""
        self._peer.stop()
        self._after_stop()

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()

    # -- internals --------------------------------------------------------------------------------

    async def _main(self, ready: Callable[[], None], done: asyncio.Event) -> None:
        server = self._make_server(_pymodbus())
        await server.serve_forever(background=True)
        self._on_listening(server)
        ready()
        await done.wait()
        await server.shutdown()
        # Let requests the server scheduled before it stopped finish, so none is left un-awaited.
        for _ in range(5):
            await asyncio.sleep(0)

    def _trace_packet(self, sending: bool, data: bytes) -> bytes:
        if not sending:
            return data
        with self._lock:
            if self._garble_next <= 0:
                return data
            self._garble_next -= 1
        # Drop the last byte: an RTU frame fails its CRC, a TCP frame falls short of its header's length.
        return data[:-1]

    async def _action(
        self,
        function_code: int,
        start_address: int,
        address: int,
        count: int,
        registers: list[int],
        set_values: list[int] | list[bool] | None,
    ) -> Any:
        with self._lock:
            self.requests += 1
            if self._fail_next > 0:
                self._fail_next -= 1
                return _pymodbus().constants.ExcCodes.DEVICE_BUSY
            now = time.monotonic()

            def reg(addr: int) -> int:
                return registers[addr - start_address]

            def put(addr: int, value: int) -> None:
                registers[addr - start_address] = int(value) & 0xFFFF

            self._step(now, reg, put)
            if set_values is not None:
                self._on_write(address, [int(v) for v in set_values], reg, put, set_values)
        return None

    def _make_server(self, pm: Any) -> Any:
        raise NotImplementedError

    def _on_listening(self, server: Any) -> None:
        """Called on the server thread once listening."""

    def _after_stop(self) -> None:
        """Called after the server thread ended."""

    def _step(self, now: float, reg: Any, put: Any) -> None:
        raise NotImplementedError

    def _on_write(self, address: int, values: list[int], reg: Any, put: Any, set_values: list[Any]) -> None:
        """Hook for writes (may edit ``set_values`` in place before they are stored)."""


class FakeInspireHand(_FakePeer):
    """A simulated Inspire RH56 hand on Modbus TCP at 127.0.0.1.

    Each DoF moves from ANGLE_ACT toward ANGLE_SET at SPEED_SET/1000 of full speed (a full
    0..1000 travel takes ``full_stroke_s`` at speed 1000), stops against an object placed
    with :meth:`block` (FORCE_ACT then reads FORCE_SET, STATUS "force reached"), freezes
    while it has an error flag (:meth:`inject_error`), and clears its flags when 1 is written
    to CLEAR_ERROR. A target of 0xFFFF (the manual's -1) leaves that DoF's target unchanged.
    The simulation advances on each request, from the elapsed wall time.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 0, *, full_stroke_s: float = 0.8) -> None:
        super().__init__()
        self.host = host
        self._requested_port = port
        self._port = 0
        self._full_stroke_s = full_stroke_s
        self._pos = [float(INSPIRE.UNIT_MAX)] * INSPIRE.N
        self._blocked: list[int | None] = [None] * INSPIRE.N
        self._errors = [0] * INSPIRE.N
        self._last = time.monotonic()

    @property
    def port(self) -> int:
        """The TCP port the fake listens on (valid after :meth:`start`)."""
        return self._port

    @property
    def angles(self) -> list[int]:
        """Current simulated angles, register units 0..1000, finger order."""
        with self._lock:
            return [round(p) for p in self._pos]

    def inject_error(self, finger: int, flags: int) -> None:
        """Set ERROR flags on DoF ``finger`` (0..5); it stops moving until the flags are cleared."""
        with self._lock:
            self._errors[finger] = flags & 0xFF

    def block(self, finger: int, at_units: int | None) -> None:
        """Place an object that stops DoF ``finger`` closing below ``at_units`` (None removes it)."""
        with self._lock:
            self._blocked[finger] = at_units

    def _make_server(self, pm: Any) -> Any:
        sim = pm.simulator
        regs = sim.SimData(address=1000, count=701, values=0, datatype=sim.DataType.REGISTERS)
        device = sim.SimDevice(id=0, simdata=[regs], action=self._action)
        server = pm.server.ModbusTcpServer(
            device, address=(self.host, self._requested_port), trace_packet=self._trace_packet
        )
        return server

    def _on_listening(self, server: Any) -> None:
        self._port = int(server.transport.sockets[0].getsockname()[1])
        # Power-on register contents.
        with self._lock:
            self._init_regs = True
            self._last = time.monotonic()

    def _step(self, now: float, reg: Any, put: Any) -> None:
        n = INSPIRE.N
        if getattr(self, "_init_regs", False):
            self._init_regs = False
            for i in range(n):
                put(INSPIRE.ANGLE_SET + i, INSPIRE.UNIT_MAX)
                put(INSPIRE.SPEED_SET + i, INSPIRE.UNIT_MAX)
                put(INSPIRE.FORCE_SET + i, INSPIRE.UNIT_MAX)
        dt = max(0.0, now - self._last)
        self._last = now
        if reg(INSPIRE.CLEAR_ERROR) == 1:
            self._errors = [0] * n
            put(INSPIRE.CLEAR_ERROR, 0)
        status = [0] * n
        forces = [0] * n
        for i in range(n):
            target = reg(INSPIRE.ANGLE_SET + i)
            rate = reg(INSPIRE.SPEED_SET + i) / INSPIRE.UNIT_MAX * INSPIRE.UNIT_MAX / self._full_stroke_s
            if self._errors[i]:
                status[i] = InspireStatus.FAULT_STOP
                continue
            floor = self._blocked[i]
            goal = float(target) if floor is None else max(float(target), float(floor))
            step = rate * dt
            pos = self._pos[i]
            pos = min(goal, pos + step) if goal > pos else max(goal, pos - step)
            self._pos[i] = pos
            if abs(pos - goal) < 1e-9:
                if floor is not None and target < floor:
                    status[i] = InspireStatus.FORCE_REACHED
                    forces[i] = reg(INSPIRE.FORCE_SET + i)
                else:
                    status[i] = InspireStatus.POSITION_REACHED
            else:
                status[i] = InspireStatus.GRASPING if goal < pos else InspireStatus.RELEASING
        for i in range(n):
            put(INSPIRE.ANGLE_ACT + i, round(self._pos[i]))
            put(INSPIRE.FORCE_ACT + i, forces[i])
        for k in range(INSPIRE.N_PACKED):
            put(INSPIRE.ERROR + k, self._errors[2 * k] | self._errors[2 * k + 1] << 8)
            put(INSPIRE.STATUS + k, status[2 * k] | status[2 * k + 1] << 8)
            put(INSPIRE.TEMP + k, 35 | 35 << 8)

    def _on_write(self, address: int, values: list[int], reg: Any, put: Any, set_values: list[Any]) -> None:
        for i, value in enumerate(values):
            addr = address + i
            if INSPIRE.ANGLE_SET <= addr < INSPIRE.ANGLE_SET + INSPIRE.N and value == 0xFFFF:
                set_values[i] = reg(addr)
            elif INSPIRE.ANGLE_SET <= addr < INSPIRE.ANGLE_SET + INSPIRE.N:
                set_values[i] = min(value, INSPIRE.UNIT_MAX)


class FakeDHGripper(_FakePeer):
    """A simulated DH-Robotics gripper speaking Modbus RTU (slave address ``device_id``).

    Needs initialization (write 1 or 0xA5 to 0x0100) before it moves: it then opens fully
    within ``init_s``. The fingers move toward the POSITION target at SPEED % of full speed
    (a full stroke takes ``full_stroke_s`` at 100 %); an object placed with
    :meth:`place_object` stops them (grip state "object caught"), removing it while held
    gives "object dropped". Registers outside the manual's map answer "illegal address".

    Args:
        transport: ``"pty"``: serve on one end of a bridged pseudo-terminal pair and give
            the driver the other end (:attr:`device`); ``"tcp"``: RTU frames over TCP at
            127.0.0.1 (:attr:`port`).
    """

    def __init__(
        self,
        *,
        transport: Literal["pty", "tcp"] = "pty",
        device_id: int = 1,
        baudrate: int = 115200,
        full_stroke_s: float = 0.7,
        init_s: float = 0.1,
    ) -> None:
        super().__init__()
        if transport not in ("pty", "tcp"):
            raise ValueError(f"transport must be 'pty' or 'tcp', got {transport!r}")
        self.transport = transport
        self.device_id = device_id
        self.baudrate = baudrate
        self._full_stroke_s = full_stroke_s
        self._init_s = init_s
        self._pos = 0.0
        self._init_state = DHInitState.NOT_INITIALIZED
        self._init_done_at = 0.0
        self._object: int | None = None
        self._caught = False
        self._last = time.monotonic()
        self._port = 0
        self._bridge: _PtyBridge | None = None

    @property
    def device(self) -> str:
        """The serial device the driver should open (``transport="pty"``, after :meth:`start`)."""
        if self._bridge is None:
            raise RuntimeError("FakeDHGripper: device exists only with transport='pty' after start()")
        return self._bridge.client_path

    @property
    def port(self) -> int:
        """The TCP port (``transport="tcp"``, after :meth:`start`)."""
        return self._port

    @property
    def position(self) -> int:
        """Simulated finger position, permille (0 closed, 1000 open)."""
        with self._lock:
            return round(self._pos)

    def place_object(self, width_permille: int | None) -> None:
        """Put an object of this width between the fingers (None removes it)."""
        with self._lock:
            self._object = width_permille

    def _make_server(self, pm: Any) -> Any:
        sim = pm.simulator
        reg = sim.DataType.REGISTERS
        blocks = [
            sim.SimData(address=DH.INIT, count=5, values=0, datatype=reg),
            sim.SimData(address=DH.INIT_STATE, count=3, values=0, datatype=reg, readonly=True),
            sim.SimData(address=DH.SAVE, count=4, values=0, datatype=reg),
        ]
        device = sim.SimDevice(id=self.device_id, simdata=blocks, action=self._action)
        if self.transport == "tcp":
            return pm.server.ModbusTcpServer(
                device,
                framer=pm.framer.FramerType.RTU,
                address=("127.0.0.1", 0),
                trace_packet=self._trace_packet,
            )
        self._bridge = _PtyBridge()
        return pm.server.ModbusSerialServer(
            device,
            framer=pm.framer.FramerType.RTU,
            port=self._bridge.server_path,
            baudrate=self.baudrate,
            trace_packet=self._trace_packet,
        )

    def _on_listening(self, server: Any) -> None:
        if self.transport == "tcp":
            self._port = int(server.transport.sockets[0].getsockname()[1])
        with self._lock:
            self._init_regs = True
            self._last = time.monotonic()

    def _after_stop(self) -> None:
        bridge, self._bridge = self._bridge, None
        if bridge is not None:
            bridge.close()

    def _step(self, now: float, reg: Any, put: Any) -> None:
        if getattr(self, "_init_regs", False):
            self._init_regs = False
            put(DH.FORCE, 50)
            put(DH.SPEED, 100)
            put(DH.SLAVE_ADDRESS, self.device_id)
        dt = max(0.0, now - self._last)
        self._last = now
        if self._init_state == DHInitState.INITIALIZING and now >= self._init_done_at:
            self._init_state = DHInitState.INITIALIZED
            self._pos = float(DH.POSITION_MAX)
            put(DH.POSITION, DH.POSITION_MAX)
            put(DH.INIT, 0)
        grip = DHGripState.REACHED
        if self._init_state == DHInitState.INITIALIZED:
            target = float(reg(DH.POSITION))
            rate = reg(DH.SPEED) / 100 * DH.POSITION_MAX / self._full_stroke_s
            goal = target
            if self._object is not None and target < self._object <= self._pos + 1e-9:
                goal = float(self._object)
            pos = self._pos
            pos = min(goal, pos + rate * dt) if goal > pos else max(goal, pos - rate * dt)
            self._pos = pos
            if abs(pos - goal) > 1e-9:
                grip = DHGripState.MOVING
            elif goal != target:
                grip = DHGripState.OBJECT_CAUGHT
                self._caught = True
            elif self._caught:
                grip = DHGripState.OBJECT_DROPPED
            if grip != DHGripState.OBJECT_CAUGHT and self._object is None:
                self._caught = self._caught and grip == DHGripState.OBJECT_DROPPED
        put(DH.INIT_STATE, self._init_state)
        put(DH.GRIP_STATE, grip)
        put(DH.POSITION_ACT, round(self._pos))

    def _on_write(self, address: int, values: list[int], reg: Any, put: Any, set_values: list[Any]) -> None:
        for i, value in enumerate(values):
            addr = address + i
            if addr == DH.INIT and value in (DH.INIT_CMD, DH.FULL_INIT_CMD):
                self._init_state = DHInitState.INITIALIZING
                self._init_done_at = time.monotonic() + self._init_s
            elif addr == DH.POSITION:
                set_values[i] = min(value, DH.POSITION_MAX)
            elif addr == DH.FORCE:
                set_values[i] = min(max(value, DH.FORCE_MIN), DH.FORCE_MAX)
            elif addr == DH.SPEED:
                set_values[i] = min(max(value, DH.SPEED_MIN), DH.SPEED_MAX)


class _PtyBridge:
    """Two pseudo-terminals joined like a null-modem cable: bytes written on one end arrive at the other."""

    def __init__(self) -> None:
        self._m1, s1 = os.openpty()
        self._m2, s2 = os.openpty()
        for fd in (s1, s2):
            tty.setraw(fd)
        self.server_path = os.ttyname(s1)
        self.client_path = os.ttyname(s2)
        # Keep the slave ends open so the masters do not read EIO while no one has them open.
        self._slaves = (s1, s2)
        self._stop_r, self._stop_w = os.pipe()
        self._thread = threading.Thread(target=self._run, name="pty-bridge", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        peers = {self._m1: self._m2, self._m2: self._m1}
        while True:
            ready, _, _ = select.select([self._m1, self._m2, self._stop_r], [], [])
            if self._stop_r in ready:
                return
            for fd in ready:
                try:
                    data = os.read(fd, 4096)
                    os.write(peers[fd], data)
                except OSError:
                    continue

    def close(self) -> None:
        os.write(self._stop_w, b"x")
        self._thread.join(5.0)
        for fd in (self._m1, self._m2, *self._slaves, self._stop_r, self._stop_w):
            with contextlib.suppress(OSError):
                os.close(fd)
