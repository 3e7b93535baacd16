"""Shared Modbus I/O: one sync pymodbus client owned by one driver thread, a write mailbox and a poll loop."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from types import TracebackType
from typing import Any, Self

from telerig.errors import DependencyError, RobotError

__all__ = ["LinkDownError", "LinkStats", "ModbusLink", "PolledDriver", "serial_client", "tcp_client"]

_log = logging.getLogger("telerig.robots.modbus")


def _pymodbus() -> Any:
    try:
        import pymodbus.client
        import pymodbus.exceptions
        import pymodbus.framer
    except ImportError:  # pragma: no cover - depends on the environment
        raise DependencyError(
            "the Modbus drivers need pymodbus; pip install 'pymodbus>=3.16,<4' pyserial"
        ) from None
    return pymodbus


def tcp_client(host: str, port: int, *, timeout_s: float, rtu_framing: bool = False) -> Any:
    """A pymodbus sync TCP client (Modbus TCP framing, or RTU frames over TCP for serial gateways)."""
    pm = _pymodbus()
    framer = pm.framer.FramerType.RTU if rtu_framing else pm.framer.FramerType.SOCKET
    return pm.client.ModbusTcpClient(
        host, port=port, framer=framer, timeout=timeout_s, retries=0, reconnect_delay=0.0
    )


def serial_client(device: str, *, baudrate: int, parity: str, stopbits: int, timeout_s: float) -> Any:
    """A pymodbus sync RTU client on a serial device (RS-485 adapter, or a pty in tests)."""
    pm = _pymodbus()
    return pm.client.ModbusSerialClient(
        device,
        framer=pm.framer.FramerType.RTU,
        baudrate=baudrate,
        bytesize=8,
        parity=parity,
        stopbits=stopbits,
        timeout=timeout_s,
        retries=0,
        reconnect_delay=0.0,
    )


class LinkDownError(Exception):
    """The peer did not answer (timeout, refused, closed); carries a one-line reason."""


@dataclass(frozen=True, slots=True)
class LinkStats:
    """Counters of one driver's Modbus traffic since :meth:`PolledDriver.connect`.

    Attributes:
        polls: Completed state polls.
        writes: Completed register writes (acknowledged by the peer).
        superseded: Queued writes replaced by a newer one before they went out.
        exception_responses: Modbus exception responses received (counted, not fatal).
        failures: Requests that got no valid answer (timeouts, malformed frames, refused).
        last_poll_rtt_ns: Duration of the last poll, request out to last response in [ns].
        last_write_rtt_ns: Duration of the last write, request out to acknowledgement in [ns].
    """

    polls: int
    writes: int
    superseded: int
    exception_responses: int
    failures: int
    last_poll_rtt_ns: int
    last_write_rtt_ns: int


class ModbusLink:
    """A pymodbus sync client with errors sorted: exception responses counted, silence raised.

    Not thread-safe: one driver thread owns it.
    """

    def __init__(self, client: Any, device_id: int, where: str) -> None:
        self._client = client
        self._device_id = device_id
        self.where = where
        self.exception_responses = 0

    def open(self) -> None:
        """Open the socket / serial port. Raises :class:`LinkDownError`."""
        try:
            ok = self._client.connect()
        except Exception as exc:
            raise LinkDownError(f"cannot open {self.where} ({exc})") from None
        if not ok:
            raise LinkDownError(f"cannot open {self.where} (connection refused or no such device)")

    def read(self, address: int, count: int) -> list[int] | None:
        """Read ``count`` holding registers (fc 0x03); ``None`` on a Modbus exception response."""
        response = self._call("read_holding_registers", address, count=count, device_id=self._device_id)
        if response.isError():
            self.exception_responses += 1
            return None
        registers = list(response.registers)
        if len(registers) != count:
            self.exception_responses += 1
            return None
        return registers

    def write(self, address: int, values: list[int]) -> bool:
        """Write registers (fc 0x06 for one value, 0x10 for several); ``False`` on an exception response."""
        if len(values) == 1:
            response = self._call("write_register", address, values[0], device_id=self._device_id)
        else:
            response = self._call("write_registers", address, values, device_id=self._device_id)
        if response.isError():
            self.exception_responses += 1
            return False
        return True

    def close(self) -> None:
        """Close the socket / serial port. Idempotent."""
        try:
            self._client.close()
        except Exception:  # pragma: no cover - closing a dead transport
            _log.debug("%s: close failed", self.where, exc_info=True)

    def _call(self, method: str, *args: Any, **kwargs: Any) -> Any:
        pm = _pymodbus()
        try:
            response = getattr(self._client, method)(*args, **kwargs)
        except pm.exceptions.ConnectionException as exc:
            raise LinkDownError(
                f"{self.where} refused or closed the connection ({_first_line(exc)})"
            ) from None
        except pm.exceptions.ModbusException as exc:
            raise LinkDownError(f"no valid answer from {self.where} ({_first_line(exc)})") from None
        except OSError as exc:
            raise LinkDownError(f"{self.where}: {exc}") from None
        if response is None:
            raise LinkDownError(f"no answer from {self.where}")
        return response


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


class PolledDriver:
    """Base of the Modbus drivers: a thread that writes queued commands first, then polls state.

    ``send`` never does I/O: it queues the register values in a mailbox keyed by register
    block (a newer command for the same block replaces an older one not yet written, counted
    as superseded) and wakes the thread, which writes them at once and polls right after. A peer that
    gives no valid answer for ``stale_after_s`` is declared gone: the thread stops and every
    call raises a one-line :class:`RobotError`.
    """

    def __init__(
        self,
        name: str,
        make_link: Callable[[], ModbusLink],
        *,
        poll_rate_hz: float,
        stale_after_s: float,
    ) -> None:
        if poll_rate_hz <= 0:
            raise ValueError(f"poll_rate_hz must be positive, got {poll_rate_hz}")
        if stale_after_s <= 0:
            raise ValueError(f"stale_after_s must be positive, got {stale_after_s}")
        self._name = name
        self._make_link = make_link
        self._period_ns = round(1e9 / poll_rate_hz)
        self._stale_ns = round(stale_after_s * 1e9)
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._written = threading.Condition(self._lock)
        self._thread: threading.Thread | None = None
        self._link: ModbusLink | None = None
        self._pending: dict[str, tuple[int, list[int], int]] = {}
        self._ticket = 0
        self._done_ticket = 0
        self._fault: str | None = None
        self._connected = False
        self._closed = False
        self._estopped = False
        self._counts = {"polls": 0, "writes": 0, "superseded": 0, "failures": 0}
        self._poll_rtt_ns = 0
        self._write_rtt_ns = 0
        self._state_seq = 0
        self._cmd_seq = 0

    # -- lifecycle -----------------------------------------------------------------------------

    @property
    def name(self) -> str:
        """Driver name, used as the stamps' ``source_id``."""
        return self._name

    @property
    def connected(self) -> bool:
        """True between a successful :meth:`connect` and :meth:`close` or the peer going away."""
        return self._connected and self._fault is None

    @property
    def estopped(self) -> bool:
        """True while the emergency stop is latched."""
        return self._estopped

    def connect(self) -> None:
        """Open the link, read the state once (so :meth:`read_state` has data) and start polling.

        Idempotent. Raises:
            RobotError: the peer cannot be reached or does not answer; the message says where.
        """
        if self._connected and self._fault is None:
            return
        if self._thread is not None:
            self.close()
        link = self._make_link()
        try:
            link.open()
            self._on_connect(link)
            self._timed_poll(link)
        except LinkDownError as exc:
            link.close()
            raise RobotError(f"{self._name}: {exc}; check power, cabling and the address") from None
        self._link = link
        self._fault = None
        self._closed = False
        self._stop.clear()
        self._connected = True
        self._thread = threading.Thread(target=self._run, name=f"{self._name}-modbus", daemon=True)
        self._thread.start()
        _log.info("%s: connected to %s", self._name, link.where)

    def close(self) -> None:
        """Stop polling and close the link. Idempotent; queued writes not yet sent are dropped."""
        self._closed = True
        self._stop.set()
        self._wake.set()
        thread, self._thread = self._thread, None
        if thread is not None and thread is not threading.current_thread():
            thread.join()
        link, self._link = self._link, None
        if link is not None:
            link.close()
            _log.info("%s: closed (%s)", self._name, self.stats())
        self._connected = False
        with self._lock:
            self._pending.clear()
            self._written.notify_all()

    def __enter__(self) -> Self:
        self.connect()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def stats(self) -> LinkStats:
        """Traffic counters since :meth:`connect`."""
        link = self._link
        with self._lock:
            return LinkStats(
                polls=self._counts["polls"],
                writes=self._counts["writes"],
                superseded=self._counts["superseded"],
                exception_responses=link.exception_responses if link is not None else 0,
                failures=self._counts["failures"],
                last_poll_rtt_ns=self._poll_rtt_ns,
                last_write_rtt_ns=self._write_rtt_ns,
            )

    def reset_estop(self) -> None:
        """Release the emergency stop; the device keeps holding until the next command."""
        self._estopped = False
        _log.info("%s: emergency stop released", self._name)

    # -- for subclasses -------------------------------------------------------------------------

    def _require_connected(self) -> None:
        if self._fault is not None:
            raise RobotError(f"{self._name}: {self._fault}; check the device, then connect() again")
        if not self._connected:
            state = "closed" if self._closed else "not connected; call connect() first"
            raise RobotError(f"{self._name}: driver is {state}")

    def _queue_write(self, key: str, address: int, values: list[int]) -> int:
        """Queue a register write (replacing one queued under ``key``); return its ticket."""
        with self._lock:
            if key in self._pending:
                self._counts["superseded"] += 1
            self._ticket += 1
            self._pending[key] = (address, values, self._ticket)
            ticket = self._ticket
        self._wake.set()
        return ticket

    def _wait_written(self, ticket: int, timeout_s: float) -> bool:
        """Block until the write with ``ticket`` (and every earlier one) went out, or timeout."""
        deadline = time.monotonic() + timeout_s
        with self._lock:
            while self._done_ticket < ticket and self._fault is None and not self._closed:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._written.wait(left)
            return self._done_ticket >= ticket

    def _next_state_seq(self) -> int:
        self._state_seq += 1
        return self._state_seq - 1

    def _next_cmd_seq(self) -> int:
        self._cmd_seq += 1
        return self._cmd_seq - 1

    def _on_connect(self, link: ModbusLink) -> None:
        """Called once on the connecting thread after the link opened (e.g. read set-points)."""

    def _poll(self, link: ModbusLink, sent_ns: int) -> None:
        """Read the state registers and store a snapshot. Raise :class:`LinkDownError` on silence."""
        raise NotImplementedError

    # -- the thread -----------------------------------------------------------------------------

    def _timed_poll(self, link: ModbusLink) -> None:
        sent_ns = time.time_ns()
        t0 = time.perf_counter_ns()
        self._poll(link, sent_ns)
        rtt = time.perf_counter_ns() - t0
        with self._lock:
            self._counts["polls"] += 1
            self._poll_rtt_ns = rtt

    def _flush_writes(self, link: ModbusLink) -> int:
        flushed = 0
        while True:
            with self._lock:
                if not self._pending:
                    return flushed
                key = next(iter(self._pending))
                address, values, ticket = self._pending.pop(key)
            t0 = time.perf_counter_ns()
            ok = link.write(address, values)
            rtt = time.perf_counter_ns() - t0
            flushed += 1
            with self._lock:
                if ok:
                    self._counts["writes"] += 1
                self._write_rtt_ns = rtt
                self._done_ticket = max(self._done_ticket, ticket)
                self._written.notify_all()

    def _run(self) -> None:
        link = self._link
        assert link is not None
        last_ok = time.monotonic_ns()
        deadline = time.monotonic_ns()
        while not self._stop.is_set():
            try:
                if self._flush_writes(link):
                    # Read back right after a command so the state reflects it one poll later, not
                    # up to a period later; polls stay at most max(poll rate, command rate).
                    deadline = min(deadline, time.monotonic_ns())
                now = time.monotonic_ns()
                if now >= deadline:
                    self._timed_poll(link)
                    deadline = max(deadline + self._period_ns, now)
                last_ok = time.monotonic_ns()
            except LinkDownError as exc:
                with self._lock:
                    self._counts["failures"] += 1
                silent_ns = time.monotonic_ns() - last_ok
                if silent_ns >= self._stale_ns:
                    self._declare_gone(f"{exc}; no valid answer for {silent_ns / 1e9:.2f} s")
                    return
                deadline = time.monotonic_ns() + self._period_ns // 2
            wait_ns = deadline - time.monotonic_ns()
            if wait_ns > 0 and not self._pending:
                self._wake.wait(wait_ns / 1e9)
            self._wake.clear()

    def _declare_gone(self, reason: str) -> None:
        _log.error("%s: device gone: %s", self._name, reason)
        with self._lock:
            self._fault = f"device gone: {reason}"
            self._pending.clear()
            self._written.notify_all()
