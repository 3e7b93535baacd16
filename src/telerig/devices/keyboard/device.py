"""The terminal keyboard device: cbreak-mode reads of a tty on its own thread (no global hook)."""

from __future__ import annotations

import atexit
import contextlib
import logging
import os
import select
import sys
import termios
import threading
from collections import Counter
from collections.abc import Mapping
from typing import Any

from telerig.devices.base import SampleSink
from telerig.devices.keyboard.protocol import KeyboardNormalizer, KeyDecoder
from telerig.devices.worker import DeviceWorker
from telerig.errors import DeviceError
from telerig.ir.types import Handedness, Sample, now_ns

__all__ = ["KeyboardDevice"]

_log = logging.getLogger(__name__)

_STAT_KEYS = ("bytes", "keys", "malformed", "unknown_sequence", "unmapped_key")
_LFLAG = 3


class KeyboardDevice:
    """Reads key presses from a terminal in cbreak mode and emits ``Twist`` + ``ControllerState``.

    Only the terminal the device reads sees the keys (stdin by default, or ``path`` /
    ``fd``): no X11/Wayland hook, so it works over SSH and on macOS. ``start`` switches the
    terminal to cbreak mode (no line buffering, no echo; Ctrl+C still interrupts) and the reading
    thread restores the saved mode when it ends, by ``stop``, by an exception, or at interpreter
    exit. A ``Twist`` is emitted every ``1 / rate_hz`` s (zero when no key is held, so consumers
    see a live stream), and a ``ControllerState`` whenever trigger, mode or held buttons change;
    see :class:`KeyboardNormalizer`. Keyboards carry no timestamp: ``device_ns = capture_ns`` =
    the common clock when the bytes were read (Twist: when it was sampled).
    """

    def __init__(
        self,
        id: str = "keyboard0",
        *,
        fd: int | None = None,
        path: str | None = None,
        rate_hz: float = 50.0,
        key_map: Mapping[str, str] | None = None,
        max_linear: float = 0.1,
        max_angular: float = 0.5,
        initial_hold_s: float = 0.6,
        repeat_release_s: float = 0.12,
        escape_timeout_s: float = 0.05,
        hand: Handedness = "right",
        frame_id: str = "operator",
    ) -> None:
        """Args:
        id: Device id (``Twist`` source ``<id>``, ``ControllerState`` source ``<id>/<hand>``).
        fd: Terminal file descriptor to read (not closed by the device); default stdin.
        path: Terminal device to open instead, e.g. ``/dev/pts/3``.
        rate_hz: ``Twist`` rate [Hz] (0 < rate <= 1000).
        key_map, max_linear, max_angular, initial_hold_s, repeat_release_s, hand, frame_id:
            See :class:`KeyboardNormalizer`.
        escape_timeout_s: Silence after a lone ESC that makes it the Escape key [s].
        """
        if not 0.0 < rate_hz <= 1000.0:
            raise DeviceError(f"rate_hz must be in (0, 1000], got {rate_hz}")
        self._id = id
        self.fd = fd
        self.path = path
        self.rate_hz = float(rate_hz)
        self.escape_timeout_s = float(escape_timeout_s)
        self.normalizer = KeyboardNormalizer(
            id,
            key_map=key_map,
            max_linear=max_linear,
            max_angular=max_angular,
            initial_hold_s=initial_hold_s,
            repeat_release_s=repeat_release_s,
            hand=hand,
            frame_id=frame_id,
        )
        self._stats: Counter[str] = Counter(dict.fromkeys(_STAT_KEYS, 0))
        self._worker = DeviceWorker(id, kind="keyboard", thread_name=f"telerig-keyboard-{id}", log=_log)
        self._restore: tuple[int, list[Any]] | None = None

    @property
    def id(self) -> str:
        """Device id."""
        return self._id

    @property
    def on_change_streams(self) -> frozenset[str]:
        """The buttons, trigger and mode (:class:`~telerig.devices.base.ChangeDrivenDevice`): sent
        when one of them changes; the twist streams at ``rate_hz``."""
        return frozenset({f"{self.normalizer.hand}_controller"})

    @property
    def stats(self) -> Mapping[str, int]:
        """Counters: ``bytes``, ``keys``, ``samples``; drops ``malformed`` (broken sequences),
        ``unknown_sequence`` (well-formed, unnamed), ``unmapped_key``; ``sink_error``."""
        return {**self._stats, "samples": self._worker.samples, "sink_error": self._worker.sink_errors}

    def start(self, sink: SampleSink) -> None:
        """Put the terminal in cbreak mode and read it on a new thread.

        Raises:
            DeviceError: Already running, or the input is not a terminal.
        """
        with self._worker.starting() as launch:
            owned = False
            if self.path is not None:
                try:
                    fd = os.open(self.path, os.O_RDWR | os.O_NOCTTY)
                except OSError as exc:
                    raise DeviceError(
                        f"cannot open terminal {self.path}: {exc.strerror}; check path"
                    ) from None
                owned = True
            else:
                fd = sys.stdin.fileno() if self.fd is None else self.fd
            if not os.isatty(fd):
                if owned:
                    os.close(fd)
                raise DeviceError(
                    f"keyboard '{self._id}': input (fd {fd}) is not a terminal; run telerig in a terminal "
                    "or set path to a tty, e.g. /dev/pts/3"
                )
            saved = termios.tcgetattr(fd)
            mode = termios.tcgetattr(fd)
            mode[_LFLAG] &= ~(termios.ICANON | termios.ECHO)
            mode[6][termios.VMIN] = 1
            mode[6][termios.VTIME] = 0
            termios.tcsetattr(fd, termios.TCSANOW, mode)
            self._restore = (fd, saved)
            atexit.register(self._restore_terminal)
            launch(self._run, fd, owned, sink)

    def stop(self) -> None:
        """Stop reading, restore the terminal mode and join the thread. Idempotent."""
        self._worker.stop()
        self._restore_terminal()

    def _restore_terminal(self) -> None:
        restore, self._restore = self._restore, None
        if restore is not None:
            atexit.unregister(self._restore_terminal)
            # If the terminal is gone there is nothing to restore.
            with contextlib.suppress(termios.error, OSError):
                termios.tcsetattr(restore[0], termios.TCSANOW, restore[1])

    def _emit(self, sink: SampleSink, sample: Sample | None) -> None:
        if sample is not None:
            self._worker.deliver(sink, sample)

    def _run(self, fd: int, owned: bool, sink: SampleSink, stop: threading.Event) -> None:
        decoder = KeyDecoder()
        norm = self.normalizer
        period_ns = round(1e9 / self.rate_hz)
        escape_ns = round(self.escape_timeout_s * 1e9)
        next_tick = now_ns()
        pending_since = 0  # when the bytes that left a lone ESC pending arrived [ns]
        try:
            while not stop.is_set():
                t = now_ns()
                if t >= next_tick:
                    self._emit(sink, norm.twist(t))
                    self._emit(sink, norm.controller(t))
                    next_tick += period_ns * max(1, (t - next_tick) // period_ns + 1)
                wait_s = (next_tick - t) / 1e9
                if decoder.pending:
                    # A lone ESC is the Escape key once no sequence byte followed for escape_timeout_s,
                    # counted from its arrival (ticks shorter than the timeout must not restart it).
                    wait_s = min(wait_s, (pending_since + escape_ns - t) / 1e9)
                ready, _, _ = select.select([fd], [], [], max(0.0, wait_s))
                if not ready:
                    if decoder.pending and now_ns() - pending_since >= escape_ns:
                        self._keys(decoder.flush(), now_ns(), sink)
                    continue
                try:
                    data = os.read(fd, 1024)
                except OSError:
                    _log.warning("%s: terminal closed", self._id)
                    return
                if not data:
                    return
                self._stats["bytes"] += len(data)
                pending_since = now_ns()
                self._keys(decoder.feed(data), pending_since, sink)
                self._stats["malformed"] = decoder.malformed
                self._stats["unknown_sequence"] = decoder.unknown
        finally:
            self._restore_terminal()
            if owned:
                os.close(fd)

    def _keys(self, keys: list[str], t: int, sink: SampleSink) -> None:
        if not keys:
            return
        norm = self.normalizer
        self._stats["keys"] += len(keys)
        for key in keys:
            norm.press(key, t)
        self._stats["unmapped_key"] = norm.unmapped
        self._emit(sink, norm.controller(t))
