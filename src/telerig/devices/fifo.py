"""The writing end of a FIFO that a fake device feeds and the real driver opens like its device node."""

from __future__ import annotations

import errno
import os
import stat
import threading
import time
from collections.abc import Callable
from pathlib import Path

from telerig.errors import DeviceError

__all__ = ["FifoWriter"]


class FifoWriter:
    """Writes bytes into a FIFO at ``path`` (created if missing), directly or paced on a thread.

    ``connect`` waits for the reader to open the FIFO; ``write`` sends bytes in one ``write``
    (atomic below PIPE_BUF, so a report never interleaves with another); ``play`` calls a step
    function at a fixed rate on a thread; ``close`` stops it and closes the FIFO, which the reader
    sees as end of stream.
    """

    def __init__(self, path: Path | str) -> None:
        """Args:
        path: FIFO path; created with ``mkfifo`` when it does not exist.

        Raises:
            DeviceError: ``path`` exists and is not a FIFO.
        """
        self.path = Path(path)
        if not self.path.exists():
            os.mkfifo(self.path)
        elif not stat.S_ISFIFO(self.path.stat().st_mode):
            raise DeviceError(f"{self.path} exists and is not a FIFO; remove it or pick another path")
        self._fd: int | None = None
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    def connect(self, timeout_s: float = 5.0) -> None:
        """Open the FIFO for writing once a reader has it open.

        Raises:
            DeviceError: No reader within ``timeout_s``.
        """
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                fd = os.open(self.path, os.O_WRONLY | os.O_NONBLOCK)
            except OSError as exc:
                if exc.errno != errno.ENXIO or time.monotonic() > deadline:
                    raise DeviceError(f"no reader opened {self.path} within {timeout_s} s") from None
                time.sleep(0.005)
                continue
            os.set_blocking(fd, True)
            with self._lock:
                self._fd = fd
            return

    def write(self, data: bytes) -> None:
        """Write ``data`` in one ``write``; connects first if needed."""
        if self._fd is None:
            self.connect()
        with self._lock:
            assert self._fd is not None
            os.write(self._fd, data)

    def play(self, step: Callable[[int, int], None], steps: int, rate_hz: float) -> None:
        """Call ``step(k, steps)`` for k = 0..``steps`` at ``rate_hz`` [Hz] on a thread (see :meth:`wait`).

        It ends early on :meth:`close` or when ``step`` raises ``OSError`` (the reader went away).
        """
        self._stop = threading.Event()
        self._thread = threading.Thread(
            target=self._play, args=(step, steps, rate_hz, self._stop), name="telerig-fake-fifo", daemon=True
        )
        self._thread.start()

    def wait(self, timeout_s: float | None = None) -> None:
        """Wait for :meth:`play` to finish."""
        if self._thread is not None:
            self._thread.join(timeout_s)

    def close(self) -> None:
        """Stop playing and close the FIFO. Idempotent."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join()
        with self._lock:
            fd, self._fd = self._fd, None
        if fd is not None:
            os.close(fd)

    @staticmethod
    def _play(step: Callable[[int, int], None], steps: int, rate_hz: float, stop: threading.Event) -> None:
        for k in range(steps + 1):
            if stop.is_set():
                return
            try:
                step(k, steps)
            except OSError:
                return
            stop.wait(1.0 / rate_hz)
