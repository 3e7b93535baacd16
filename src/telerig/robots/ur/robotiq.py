"""Robotiq 2F gripper through the Robotiq URCap's text socket on the UR controller (port 63352)."""

from __future__ import annotations

import socket
import time

from telerig.errors import RobotError

__all__ = ["ROBOTIQ_PORT", "RobotiqSocket"]

#: Port of the Robotiq URCap's gripper socket on the controller.
ROBOTIQ_PORT = 63352


class RobotiqSocket:
    """Robotiq URCap line protocol: ``SET POS 128 SPE 255 FOR 150`` -> ``ack``, ``GET POS`` -> ``POS 12``.

    Positions are 0 (open) .. 255 (closed); speed and force are 0..255 of the gripper's range.
    Every call blocks for one request/reply round trip (a LAN round trip, about a millisecond).
    """

    def __init__(
        self, host: str, port: int = ROBOTIQ_PORT, *, timeout_s: float = 1.0, name: str = "robotiq"
    ) -> None:
        self._address = (host, port)
        self._timeout = timeout_s
        self._name = name
        self._sock: socket.socket | None = None
        self._pending = b""

    def connect(self, activate_timeout_s: float = 5.0) -> None:
        """Open the socket and activate the gripper if needed (it then opens and closes once). Idempotent.

        Raises:
            RobotError: the URCap socket is unreachable or activation did not finish in time.
        """
        if self._sock is not None:
            return
        try:
            self._sock = socket.create_connection(self._address, timeout=self._timeout)
        except OSError as exc:
            raise RobotError(
                f"{self._name}: cannot reach the Robotiq URCap socket at "
                f"{self._address[0]}:{self._address[1]} "
                f"({exc}); install and enable the Robotiq URCap on the robot"
            ) from None
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        if self.get("STA") != 3:
            self.set(ACT=1, GTO=1)
            deadline = time.monotonic() + activate_timeout_s
            while self.get("STA") != 3:
                if time.monotonic() > deadline:
                    raise RobotError(
                        f"{self._name}: gripper did not activate within {activate_timeout_s:g} s"
                    )
                time.sleep(0.05)
        elif self.get("GTO") != 1:
            self.set(GTO=1)

    def set(self, **values: int) -> None:
        """Set variables (POS, SPE, FOR, ACT, GTO) in one command; each clipped to 0..255.

        Raises:
            RobotError: the gripper did not answer ``ack``.
        """
        words = " ".join(f"{k} {max(0, min(255, int(v)))}" for k, v in values.items())
        reply = self._request(f"SET {words}")
        if reply != "ack":
            raise RobotError(f"{self._name}: gripper refused 'SET {words}' (replied {reply!r})")

    def get(self, variable: str) -> int:
        """Read one variable, e.g. ``get("POS")``.

        Raises:
            RobotError: the reply is not ``<variable> <int>``.
        """
        reply = self._request(f"GET {variable}")
        key, _, value = reply.partition(" ")
        if key != variable or not value.strip().lstrip("-").isdigit():
            raise RobotError(f"{self._name}: unexpected reply {reply!r} to 'GET {variable}'")
        return int(value)

    def close(self) -> None:
        """Close the socket. Idempotent."""
        sock, self._sock = self._sock, None
        if sock is not None:
            sock.close()

    def _request(self, line: str) -> str:
        if self._sock is None:
            raise RobotError(f"{self._name}: gripper socket is not connected; call connect() first")
        try:
            self._sock.sendall(line.encode("ascii") + b"\n")
            while b"\n" not in self._pending:
                data = self._sock.recv(1024)
                if not data:
                    raise OSError("connection closed by the controller")
                self._pending += data
        except OSError as exc:
            self.close()
            raise RobotError(
                f"{self._name}: lost the Robotiq URCap socket ({exc}); reconnect the robot"
            ) from None
        reply, _, self._pending = self._pending.partition(b"\n")
        return reply.decode("ascii", "replace").strip()
