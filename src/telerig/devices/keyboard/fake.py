"""A fake terminal: a pseudo-terminal pair whose slave the keyboard device reads, fed key bytes."""

from __future__ import annotations

import os
import pty
import threading
import time

__all__ = ["KEY_BYTES", "FakeTerminal", "typical_payload"]

#: Bytes a VT100/xterm-style terminal sends for named keys (normal cursor mode).
KEY_BYTES: dict[str, bytes] = {
    "up": b"\x1b[A",
    "down": b"\x1b[B",
    "right": b"\x1b[C",
    "left": b"\x1b[D",
    "home": b"\x1b[H",
    "end": b"\x1b[F",
    "pageup": b"\x1b[5~",
    "pagedown": b"\x1b[6~",
    "delete": b"\x1b[3~",
    "escape": b"\x1b",
    "space": b" ",
    "enter": b"\r",
    "tab": b"\t",
    "backspace": b"\x7f",
}


def typical_payload() -> bytes:
    """One typical read: an auto-repeat of the up arrow."""
    return KEY_BYTES["up"]


def key_bytes(key: str) -> bytes:
    """The bytes of a named key (:data:`KEY_BYTES`) or of a single character."""
    return KEY_BYTES.get(key, key.encode())


class FakeTerminal:
    """A pty pair: the device reads ``slave_fd`` (a real terminal, so termios works on it).

    ``type`` writes key bytes as a user typing would; ``hold`` emulates a held key with the
    terminal's auto-repeat (a press, ``repeat_delay_s`` of silence, then repeats at
    ``repeat_hz``) on a thread.
    """

    def __init__(self) -> None:
        self.master_fd, self.slave_fd = pty.openpty()
        self.slave_name = os.ttyname(self.slave_fd)
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._closed = False

    def __enter__(self) -> FakeTerminal:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def write(self, data: bytes) -> None:
        """Write raw bytes, as the terminal emulator would."""
        os.write(self.master_fd, data)

    def type(self, *keys: str) -> None:
        """Press each named key (or character) once."""
        self.write(b"".join(key_bytes(k) for k in keys))

    def hold(
        self, key: str, duration_s: float, *, repeat_delay_s: float = 0.25, repeat_hz: float = 30.0
    ) -> None:
        """Hold ``key`` for ``duration_s`` with auto-repeat, on a thread (see :meth:`wait`)."""
        self._stop = threading.Event()
        self._thread = threading.Thread(
            target=self._hold,
            args=(key_bytes(key), duration_s, repeat_delay_s, repeat_hz, self._stop),
            daemon=True,
        )
        self._thread.start()

    def wait(self, timeout_s: float | None = None) -> None:
        """Wait for :meth:`hold` to finish."""
        if self._thread is not None:
            self._thread.join(timeout_s)

    def _hold(self, data: bytes, duration_s: float, delay_s: float, hz: float, stop: threading.Event) -> None:
        end = time.monotonic() + duration_s
        self.write(data)
        if stop.wait(delay_s):
            return
        while time.monotonic() < end and not stop.is_set():
            self.write(data)
            stop.wait(1.0 / hz)

    def close(self) -> None:
        """Stop any hold and close both ends. Idempotent."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        if not self._closed:
            self._closed = True
            os.close(self.master_fd)
            os.close(self.slave_fd)
