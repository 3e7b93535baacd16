"""A fake gamepad: writes real evdev ``input_event`` records into a FIFO the device opens."""

from __future__ import annotations

import math
import time
from collections.abc import Iterable
from pathlib import Path

from telerig.devices.fifo import FifoWriter
from telerig.devices.gamepad.protocol import (
    ABS_HAT0X,
    ABS_HAT0Y,
    ABS_RX,
    ABS_RY,
    ABS_RZ,
    ABS_X,
    ABS_Y,
    ABS_Z,
    EV_ABS,
    EV_KEY,
    EV_SYN,
    EVENT,
    SYN_DROPPED,
    SYN_REPORT,
)

__all__ = ["FakeGamepad", "encode_event", "report", "typical_payload"]

#: evdev codes the fake's helpers accept by name.
AXES = {
    "x": ABS_X,
    "y": ABS_Y,
    "z": ABS_Z,
    "rx": ABS_RX,
    "ry": ABS_RY,
    "rz": ABS_RZ,
    "hat0x": ABS_HAT0X,
    "hat0y": ABS_HAT0Y,
}
BUTTONS = {
    "a": 0x130,
    "b": 0x131,
    "x": 0x133,
    "y": 0x134,
    "lb": 0x136,
    "rb": 0x137,
    "select": 0x13A,
    "start": 0x13B,
}


def encode_event(time_ns: int, type: int, code: int, value: int) -> bytes:
    """One 24-byte ``struct input_event`` (64-bit Linux) stamped ``time_ns`` [ns]."""
    sec, nsec = divmod(time_ns, 1_000_000_000)
    return EVENT.pack(sec, nsec // 1000, type, code, value)


def report(time_ns: int, axes: dict[str, int] | None = None, buttons: dict[str, int] | None = None) -> bytes:
    """One evdev report: ``EV_ABS`` / ``EV_KEY`` records then ``SYN_REPORT``, all at ``time_ns``.

    ``axes`` maps names in :data:`AXES` to raw values; ``buttons`` maps names in :data:`BUTTONS`
    (xbox codes) to 1 (pressed) or 0.
    """
    out = [encode_event(time_ns, EV_ABS, AXES[k], v) for k, v in (axes or {}).items()]
    out += [encode_event(time_ns, EV_KEY, BUTTONS[k], v) for k, v in (buttons or {}).items()]
    out.append(encode_event(time_ns, EV_SYN, SYN_REPORT, 0))
    return b"".join(out)


def typical_payload() -> bytes:
    """One typical read: both sticks moved, a trigger pulled, then ``SYN_REPORT`` (5 records)."""
    return report(1_700_000_000_123_456_000, {"x": 12000, "y": -20000, "rx": -3000, "rz": 512})


class FakeGamepad:
    """Writes evdev records into a FIFO at ``path`` (created if missing), stamped with the real clock.

    ``connect`` waits for the device to open the FIFO; ``send`` writes one report atomically;
    ``play`` moves both sticks in smooth circles and pulses the triggers at ``rate_hz``.
    """

    def __init__(self, path: Path | str) -> None:
        """Args:
        path: FIFO path; created with ``mkfifo`` when it does not exist.
        """
        self._fifo = FifoWriter(path)
        self.path = self._fifo.path

    def __enter__(self) -> FakeGamepad:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def connect(self, timeout_s: float = 5.0) -> None:
        """Open the FIFO for writing once a reader has it open.

        Raises:
            DeviceError: No reader within ``timeout_s``.
        """
        self._fifo.connect(timeout_s)

    def send_raw(self, data: bytes) -> None:
        """Write bytes to the FIFO as they are (connects first if needed)."""
        self._fifo.write(data)

    def send(
        self,
        axes: dict[str, int] | None = None,
        buttons: dict[str, int] | None = None,
        time_ns: int | None = None,
    ) -> None:
        """Send one report stamped now (``time.time_ns``, like evdev's default CLOCK_REALTIME)."""
        self.send_raw(report(time.time_ns() if time_ns is None else time_ns, axes, buttons))

    def send_events(self, events: Iterable[tuple[int, int, int]]) -> None:
        """Send raw ``(type, code, value)`` records stamped now, without adding ``SYN_REPORT``."""
        t = time.time_ns()
        self.send_raw(b"".join(encode_event(t, *e) for e in events))

    def overflow(self) -> None:
        """Send ``SYN_DROPPED``, as the kernel does when its event buffer overflows."""
        self.send_events([(EV_SYN, SYN_DROPPED, 0)])

    def play(self, duration_s: float = 1.0, rate_hz: float = 100.0) -> None:
        """Move the sticks and triggers smoothly for ``duration_s`` on a thread (see :meth:`wait`)."""

        def step(k: int, n: int) -> None:
            w = 2.0 * math.pi * k / n
            env = math.sin(math.pi * k / n)
            axes = {
                "x": round(30000 * env * math.cos(w)),
                "y": round(30000 * env * math.sin(w)),
                "rx": round(20000 * env * math.sin(w)),
                "ry": round(20000 * env * math.cos(w)),
                "z": round(1023 * env),
                "rz": round(1023 * env * env),
            }
            self.send(axes)

        self._fifo.play(step, max(1, round(duration_s * rate_hz)), rate_hz)

    def wait(self, timeout_s: float | None = None) -> None:
        """Wait for :meth:`play` to finish."""
        self._fifo.wait(timeout_s)

    def close(self) -> None:
        """Stop playing and close the FIFO (the device sees end of stream). Idempotent."""
        self._fifo.close()
