"""A fake SpaceMouse: writes real HID report bytes into a FIFO that the device opens like hidraw."""

from __future__ import annotations

import math
import struct
from pathlib import Path

from telerig.devices.fifo import FifoWriter

__all__ = [
    "FakeSpaceMouse",
    "button_report",
    "rotation_report",
    "six_axis_report",
    "translation_report",
    "typical_payload",
]

_I16 = (-32768, 32767)


def _clamp16(v: int) -> int:
    return max(_I16[0], min(_I16[1], int(v)))


def translation_report(x: int, y: int, z: int) -> bytes:
    """Report 1 of split-report devices: translation counts (device frame), 7 bytes."""
    return struct.pack("<B3h", 1, _clamp16(x), _clamp16(y), _clamp16(z))


def rotation_report(rx: int, ry: int, rz: int) -> bytes:
    """Report 2 of split-report devices: rotation counts (device frame), 7 bytes."""
    return struct.pack("<B3h", 2, _clamp16(rx), _clamp16(ry), _clamp16(rz))


def six_axis_report(x: int, y: int, z: int, rx: int, ry: int, rz: int) -> bytes:
    """Report 1 of newer devices: all six axis counts (device frame), 13 bytes."""
    return struct.pack("<B6h", 1, *(_clamp16(v) for v in (x, y, z, rx, ry, rz)))


def button_report(mask: int, nbytes: int = 2) -> bytes:
    """Report 3: button bitmask (bit k = button k) over ``nbytes`` bytes."""
    return bytes([3]) + int(mask).to_bytes(nbytes, "little")


def typical_payload() -> bytes:
    """One typical report: a six-axis motion report with the cap pushed forward and twisted."""
    return six_axis_report(12, -180, 30, -5, 8, 140)


class FakeSpaceMouse:
    """Writes SpaceMouse reports into a FIFO at ``path`` (created if missing).

    Use as a context manager: ``connect`` waits for the device to open the FIFO for reading,
    then ``send`` writes one report per ``write`` (atomic: reports are far below PIPE_BUF).
    ``play`` sends a smooth motion (sinusoids on every axis, within ±350 counts) at ``rate_hz``
    on a thread, as a real device does while the cap is moved.
    """

    def __init__(self, path: Path | str, *, combined: bool = True) -> None:
        """Args:
        path: FIFO path; created with ``mkfifo`` when it does not exist.
        combined: Send six-axis 13-byte reports (newer devices) instead of report 1 + report 2.
        """
        self._fifo = FifoWriter(path)
        self.path = self._fifo.path
        self.combined = combined

    def __enter__(self) -> FakeSpaceMouse:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def connect(self, timeout_s: float = 5.0) -> None:
        """Open the FIFO for writing once a reader has it open.

        Raises:
            DeviceError: No reader within ``timeout_s``.
        """
        self._fifo.connect(timeout_s)

    def send(self, report: bytes) -> None:
        """Write one report (or any bytes) to the FIFO; connects first if needed."""
        self._fifo.write(report)

    def motion(self, x: int, y: int, z: int, rx: int, ry: int, rz: int) -> None:
        """Send one motion update (device-frame counts) in this fake's report layout."""
        if self.combined:
            self.send(six_axis_report(x, y, z, rx, ry, rz))
        else:
            self.send(translation_report(x, y, z))
            self.send(rotation_report(rx, ry, rz))

    def buttons(self, mask: int) -> None:
        """Send a button report with ``mask`` held."""
        self.send(button_report(mask))

    def play(self, duration_s: float = 1.0, rate_hz: float = 100.0, amplitude: int = 300) -> None:
        """Send smooth motion for ``duration_s`` on a thread (returns at once; see :meth:`wait`)."""

        def step(k: int, n: int) -> None:
            w = 2.0 * math.pi * (k / rate_hz) / max(duration_s, 1e-3)
            axes = [round(amplitude * math.sin(w + 0.7 * i) * math.sin(math.pi * k / n)) for i in range(6)]
            self.motion(*axes)

        self._fifo.play(step, max(1, round(duration_s * rate_hz)), rate_hz)

    def wait(self, timeout_s: float | None = None) -> None:
        """Wait for :meth:`play` to finish."""
        self._fifo.wait(timeout_s)

    def close(self) -> None:
        """Stop playing and close the FIFO (the device sees end of stream). Idempotent."""
        self._fifo.close()
