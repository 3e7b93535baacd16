"""The gamepad device: reads evdev ``input_event`` records from ``/dev/input/eventN`` (or a FIFO)."""

from __future__ import annotations

import errno
import fcntl
import logging
import os
import select
import stat
import struct
import threading
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from telerig.devices.base import SampleSink
from telerig.devices.gamepad.protocol import (
    ABS_CODES,
    EVENT_SIZE,
    GamepadNormalizer,
    InputEvent,
    parse_events,
)
from telerig.devices.worker import DeviceWorker
from telerig.errors import DeviceError, WireError
from telerig.ir.types import now_ns

__all__ = ["EventDeviceInfo", "GamepadDevice", "find_gamepad", "list_event_devices"]

_log = logging.getLogger(__name__)

_POLL_MS = 100
_REOPEN_S = 0.5
_BTN_SOUTH = 0x130
_ABSINFO = struct.Struct("<6i")  # value, minimum, maximum, fuzz, flat, resolution
_STAT_KEYS = ("events", "wire_error", "open_failed", "disconnected")


def _eviocgabs(code: int) -> int:
    # _IOR('E', 0x40 + code, struct input_absinfo)
    return (2 << 30) | (_ABSINFO.size << 16) | (ord("E") << 8) | (0x40 + code)


@dataclass(frozen=True, slots=True)
class EventDeviceInfo:
    """One evdev node: ``path`` (``/dev/input/eventN``), ``name``, and whether it has gamepad buttons."""

    path: str
    name: str
    gamepad: bool


def _has_key(bitmap: str, code: int) -> bool:
    # sysfs prints the key bitmap as hex longs, most significant first.
    words = bitmap.split()[::-1]
    i, bit = divmod(code, 64)
    try:
        return i < len(words) and bool(int(words[i], 16) >> bit & 1)
    except ValueError:
        return False


def list_event_devices(
    sys_root: Path | str = "/sys/class/input", dev_root: Path | str = "/dev/input"
) -> list[EventDeviceInfo]:
    """Every ``eventN`` node from sysfs; ``gamepad`` is set when it reports ``BTN_SOUTH`` (BTN_GAMEPAD)."""
    root = Path(sys_root)
    out: list[EventDeviceInfo] = []
    if not root.is_dir():
        return out
    for entry in sorted(root.glob("event*"), key=lambda p: (len(p.name), p.name)):
        dev = entry / "device"
        try:
            name = (dev / "name").read_text(errors="replace").strip()
            keys = (dev / "capabilities" / "key").read_text()
        except OSError:
            continue
        out.append(EventDeviceInfo(str(Path(dev_root) / entry.name), name, _has_key(keys, _BTN_SOUTH)))
    return out


def find_gamepad(
    sys_root: Path | str = "/sys/class/input", dev_root: Path | str = "/dev/input", *, name: str | None = None
) -> EventDeviceInfo:
    """The first evdev node with gamepad buttons (and ``name`` in its name, if given).

    Raises:
        DeviceError: None found; the message lists the event devices that exist.
    """
    found = list_event_devices(sys_root, dev_root)
    for info in found:
        if info.gamepad and (name is None or name.lower() in info.name.lower()):
            return info
    listing = "; ".join(f"{i.path} ({i.name})" for i in found) or "none"
    raise DeviceError(
        f"no gamepad found among event devices (found: {listing}); plug it in, add the user to the "
        "'input' group, or set path"
    )


class GamepadDevice:
    """A gamepad read through Linux evdev, emitting left/right ``ControllerState`` s and a ``Twist``.

    Reads 24-byte records on its own thread (``poll`` with a 100 ms timeout, so ``stop`` returns
    promptly) and feeds them to a :class:`GamepadNormalizer`. ``device_ns`` is the kernel event time
    (timeval of the ``SYN_REPORT``); ``capture_ns`` maps it into the common clock with
    :class:`~telerig.ir.clock.ClockOffsetEstimator` (min of receive - device over a window).

    On a real evdev node the axis ranges are read with ``EVIOCGABS`` at open, overriding the
    profile (not ``axis_ranges`` given explicitly); a FIFO (the fake) keeps the configured ranges.
    On unplug or end of stream it counts ``disconnected`` and reopens until stopped. Bad records
    are dropped and counted in :attr:`stats`; the thread never dies on input.
    """

    def __init__(
        self,
        id: str = "gamepad0",
        *,
        path: str | None = None,
        name: str | None = None,
        profile: Literal["xbox", "playstation"] = "xbox",
        axis_ranges: Mapping[str, tuple[int, int]] | None = None,
        button_map: Mapping[int, str] | None = None,
        stick_deadzone: float = 0.1,
        trigger_deadzone: float = 0.02,
        twist_map: Mapping[str, str] | None = None,
        max_linear: float = 0.25,
        max_angular: float = 1.0,
        frame_id: str = "operator",
        twist_frame_id: str = "operator",
        sys_root: Path | str = "/sys/class/input",
        dev_root: Path | str = "/dev/input",
    ) -> None:
        """Args:
        id: Device id (sources ``<id>/left``, ``<id>/right``, ``<id>``).
        path: evdev node or FIFO; ``None`` finds the first gamepad through ``sys_root``.
        name: With ``path=None``, pick the first gamepad whose name contains this.
        profile, axis_ranges, button_map, stick_deadzone, trigger_deadzone, twist_map,
        max_linear, max_angular, frame_id, twist_frame_id: See :class:`GamepadNormalizer`.
        sys_root: sysfs input class directory (tests point it at a fake tree).
        dev_root: Directory of the event nodes.
        """
        self._id = id
        self.path = path
        self.name = name
        self.sys_root = sys_root
        self.dev_root = dev_root
        self._explicit_ranges = set(axis_ranges or {})
        self.normalizer = GamepadNormalizer(
            id,
            profile=profile,
            axis_ranges=axis_ranges,
            button_map=button_map,
            stick_deadzone=stick_deadzone,
            trigger_deadzone=trigger_deadzone,
            twist_map=twist_map,
            max_linear=max_linear,
            max_angular=max_angular,
            frame_id=frame_id,
            twist_frame_id=twist_frame_id,
        )
        self._stats: Counter[str] = Counter(dict.fromkeys(_STAT_KEYS, 0))
        self._worker = DeviceWorker(id, kind="gamepad", thread_name=f"telerig-gamepad-{id}", log=_log)
        #: Set while the node is open.
        self.connected = threading.Event()

    @property
    def id(self) -> str:
        """Device id."""
        return self._id

    @property
    def on_change_streams(self) -> frozenset[str]:
        """All three (:class:`~telerig.devices.base.ChangeDrivenDevice`): each hand's state and the
        twist are sent on the report where they change."""
        return frozenset({"left_controller", "right_controller", "twist"})

    @property
    def stats(self) -> Mapping[str, int]:
        """Counters: ``events`` read, ``samples`` emitted, ``wire_error`` (bad records dropped),
        ``sync_dropped`` (kernel overflow reports skipped), ``sink_error``, ``open_failed``,
        ``disconnected``."""
        return {
            **self._stats,
            "samples": self._worker.samples,
            "sync_dropped": self.normalizer.dropped_reports,
            "sink_error": self._worker.sink_errors,
        }

    def start(self, sink: SampleSink) -> None:
        """Open the node (finding it through sysfs when ``path`` is None) and read on a new thread.

        Raises:
            DeviceError: Already running, or no gamepad found.
        """
        with self._worker.starting() as launch:
            path = self.path or find_gamepad(self.sys_root, self.dev_root, name=self.name).path
            launch(self._run, path, sink)

    def stop(self) -> None:
        """Stop reading, close the node and join the thread. Idempotent."""
        self._worker.stop()

    def _read_ranges(self, fd: int) -> None:
        for axis, code in ABS_CODES.items():
            if axis in self._explicit_ranges:
                continue
            buf = bytearray(_ABSINFO.size)
            try:
                fcntl.ioctl(fd, _eviocgabs(code), buf)
            except OSError:
                continue  # the device lacks this axis
            _, lo, hi, *_ = _ABSINFO.unpack(buf)
            if lo < hi:
                self.normalizer.set_range(code, (lo, hi))

    def _run(self, path: str, sink: SampleSink, stop: threading.Event) -> None:
        warned = False
        while not stop.is_set():
            try:
                fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
            except OSError as exc:
                self._stats["open_failed"] += 1
                if not warned:
                    _log.warning("%s: cannot open %s (%s); retrying", self._id, path, exc.strerror)
                    warned = True
                stop.wait(_REOPEN_S)
                continue
            warned = False
            stream = True
            try:
                stream = not stat.S_ISCHR(os.fstat(fd).st_mode)
                if not stream:
                    self._read_ranges(fd)
                self.connected.set()
                self._read_loop(fd, sink, stop)
            finally:
                self.connected.clear()
                os.close(fd)
            if not stop.is_set():
                self._stats["disconnected"] += 1
                stop.wait(0.01 if stream else _REOPEN_S)

    def _parse_each(self, buf: bytes) -> list[InputEvent]:
        # Slow path: drop only the bad records of a read, keep the good ones.
        events: list[InputEvent] = []
        for i in range(0, len(buf), EVENT_SIZE):
            try:
                events += parse_events(buf[i : i + EVENT_SIZE])
            except WireError as exc:
                self._stats["wire_error"] += 1
                _log.debug("%s: dropped record: %s", self._id, exc)
        return events

    def _read_loop(self, fd: int, sink: SampleSink, stop: threading.Event) -> None:
        poller = select.poll()
        poller.register(fd, select.POLLIN | select.POLLHUP | select.POLLERR)
        pending = b""
        while not stop.is_set():
            if not poller.poll(_POLL_MS):
                continue
            try:
                data = os.read(fd, 64 * EVENT_SIZE)
            except BlockingIOError:
                continue
            except OSError as exc:
                if exc.errno not in (errno.ENODEV, errno.EIO):
                    _log.warning("%s: read failed: %s", self._id, exc)
                return
            if not data:
                return
            receive_ns = now_ns()
            # evdev returns whole records; a FIFO may split them, so keep the tail.
            buf = pending + data
            cut = len(buf) - len(buf) % EVENT_SIZE
            buf, pending = buf[:cut], buf[cut:]
            try:
                events = parse_events(buf)
            except WireError:
                events = self._parse_each(buf)
            self._stats["events"] += len(events)
            for event in events:
                for sample in self.normalizer.feed(event, receive_ns):
                    self._worker.deliver(sink, sample)
