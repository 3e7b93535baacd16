"""The SpaceMouse device: reads HID reports from a Linux hidraw node (or a FIFO) on its own thread."""

from __future__ import annotations

import errno
import logging
import os
import select
import stat
import threading
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from telerig.devices.base import SampleSink
from telerig.devices.spacemouse.protocol import (
    FULL_SCALE_COUNTS,
    OtherReport,
    SpaceMouseNormalizer,
    parse_report,
    split_stream,
)
from telerig.devices.worker import DeviceWorker
from telerig.errors import DeviceError, WireError
from telerig.ir.types import Handedness, now_ns

__all__ = ["KNOWN_SPACEMICE", "HidrawInfo", "SpaceMouseDevice", "find_spacemouse", "list_hidraw"]

_log = logging.getLogger(__name__)

#: (vendor id, product id) → model name of the 3Dconnexion devices this driver knows.
KNOWN_SPACEMICE: dict[tuple[int, int], str] = {
    (0x046D, 0xC603): "SpaceMouse Plus XT",
    (0x046D, 0xC605): "CADman",
    (0x046D, 0xC606): "SpaceMouse Classic",
    (0x046D, 0xC621): "SpaceBall 5000",
    (0x046D, 0xC623): "SpaceTraveler",
    (0x046D, 0xC625): "SpacePilot",
    (0x046D, 0xC626): "SpaceNavigator",
    (0x046D, 0xC627): "SpaceExplorer",
    (0x046D, 0xC628): "SpaceNavigator for Notebooks",
    (0x046D, 0xC629): "SpacePilot Pro",
    (0x046D, 0xC62B): "SpaceMouse Pro",
    (0x256F, 0xC62E): "SpaceMouse Wireless (cable)",
    (0x256F, 0xC62F): "SpaceMouse Wireless (receiver)",
    (0x256F, 0xC631): "SpaceMouse Pro Wireless (cable)",
    (0x256F, 0xC632): "SpaceMouse Pro Wireless (receiver)",
    (0x256F, 0xC633): "SpaceMouse Enterprise",
    (0x256F, 0xC635): "SpaceMouse Compact",
    (0x256F, 0xC636): "SpaceMouse Module",
    (0x256F, 0xC652): "3Dconnexion Universal Receiver",
}

_POLL_MS = 100
_STAT_KEYS = ("reports", "wire_error", "ignored_report", "open_failed", "disconnected")
_REOPEN_S = 0.5


@dataclass(frozen=True, slots=True)
class HidrawInfo:
    """One hidraw node as described by sysfs.

    Attributes:
        path: Device node, e.g. ``/dev/hidraw3``.
        vendor_id: USB/Bluetooth vendor id.
        product_id: Product id.
        name: ``HID_NAME`` from the uevent file.
    """

    path: str
    vendor_id: int
    product_id: int
    name: str

    def describe(self) -> str:
        """``/dev/hidraw3 (046d:c626 3Dconnexion SpaceNavigator)``."""
        return f"{self.path} ({self.vendor_id:04x}:{self.product_id:04x} {self.name})"


def list_hidraw(
    sys_root: Path | str = "/sys/class/hidraw", dev_root: Path | str = "/dev"
) -> list[HidrawInfo]:
    """Every hidraw node, read from ``<sys_root>/hidrawN/device/uevent`` (``HID_ID=bus:vendor:product``)."""
    out: list[HidrawInfo] = []
    root = Path(sys_root)
    if not root.is_dir():
        return out
    for entry in sorted(root.iterdir(), key=lambda p: (len(p.name), p.name)):
        try:
            text = (entry / "device" / "uevent").read_text(errors="replace")
        except OSError:
            continue
        fields = dict(line.split("=", 1) for line in text.splitlines() if "=" in line)
        parts = fields.get("HID_ID", "").split(":")
        try:
            vendor, product = int(parts[1], 16), int(parts[2], 16)
        except (IndexError, ValueError):
            continue
        out.append(HidrawInfo(str(Path(dev_root) / entry.name), vendor, product, fields.get("HID_NAME", "?")))
    return out


def find_spacemouse(
    sys_root: Path | str = "/sys/class/hidraw",
    dev_root: Path | str = "/dev",
    *,
    vendor_id: int | None = None,
    product_id: int | None = None,
) -> HidrawInfo:
    """The first hidraw node of a known 3Dconnexion device (or of the given vendor/product id).

    Raises:
        DeviceError: None found; the message lists the hidraw nodes that exist.
    """
    found = list_hidraw(sys_root, dev_root)
    for info in found:
        if vendor_id is not None or product_id is not None:
            if (vendor_id is None or info.vendor_id == vendor_id) and (
                product_id is None or info.product_id == product_id
            ):
                return info
        elif (info.vendor_id, info.product_id) in KNOWN_SPACEMICE:
            return info
    listing = "; ".join(i.describe() for i in found) or "none"
    raise DeviceError(
        "no SpaceMouse found among hidraw devices (found: "
        f"{listing}); plug it in, grant read access to /dev/hidraw* (udev rule), or set path"
    )


class SpaceMouseDevice:
    """A 3Dconnexion SpaceMouse read through Linux hidraw, emitting ``Twist`` and button samples.

    Reads on its own thread with ``poll`` (100 ms timeout, so ``stop`` returns promptly). Each
    motion report gives an operator-frame ``Twist`` (source ``<id>``); a change of held buttons
    gives a ``ControllerState`` (source ``<id>/buttons``); see :class:`SpaceMouseNormalizer`.
    hidraw carries no timestamp, so ``device_ns = capture_ns`` = the common clock right after
    ``read`` returns.

    ``path`` may be a hidraw node (one report per read) or a FIFO (a byte stream, split by
    ``layout``; used by :mod:`telerig.devices.spacemouse.fake`). With ``path=None`` the node is
    found through sysfs at start. On unplug (read error, end of stream) the device counts a
    ``disconnected`` and reopens the path every 0.5 s until stopped. Bad reports are dropped and
    counted in :attr:`stats` by reason; the thread never dies on input.
    """

    def __init__(
        self,
        id: str = "spacemouse0",
        *,
        path: str | None = None,
        vendor_id: int | None = None,
        product_id: int | None = None,
        layout: Literal["auto", "split", "combined"] = "auto",
        max_linear: float = 0.25,
        max_angular: float = 1.0,
        deadband: int = 10,
        full_scale: int = FULL_SCALE_COUNTS,
        axis_signs: Sequence[float] = (1, 1, 1, 1, 1, 1),
        button_names: Sequence[str] = ("left", "right"),
        hand: Handedness = "right",
        frame_id: str = "operator",
        sys_root: Path | str = "/sys/class/hidraw",
        dev_root: Path | str = "/dev",
    ) -> None:
        """Args:
        id: Device id; ``Twist`` source id, and ``<id>/buttons`` for buttons.
        path: hidraw node or FIFO; ``None`` finds the device through ``sys_root``.
        vendor_id: With ``path=None``, match this vendor id instead of the known-model table.
        product_id: With ``path=None``, match this product id.
        layout: Report 1 length in a FIFO stream: ``"split"`` (7 bytes, then report 2),
            ``"combined"`` (13 bytes, six axes) or ``"auto"`` (guessed from the first read: a
            7-byte read, or report 2 at byte 7, means split). hidraw nodes keep boundaries and
            ignore this.
        max_linear: Linear speed at full deflection [m/s].
        max_angular: Angular speed at full deflection [rad/s].
        deadband: Counts around zero read as zero, per axis.
        full_scale: Counts at full deflection.
        axis_signs: ±1 flips in the operator frame for (x, y, z, roll, pitch, yaw).
        button_names: Name of button k (bit k of report 3); others are ``"button<k>"``.
        hand: Hand in the button ``ControllerState``.
        frame_id: Frame of the ``Twist``.
        sys_root: sysfs hidraw class directory (tests point it at a fake tree).
        dev_root: Directory of the device nodes.
        """
        self._id = id
        self.path = path
        self.vendor_id = vendor_id
        self.product_id = product_id
        self.layout = layout
        self.sys_root = sys_root
        self.dev_root = dev_root
        self.normalizer = SpaceMouseNormalizer(
            id,
            max_linear=max_linear,
            max_angular=max_angular,
            deadband=deadband,
            full_scale=full_scale,
            axis_signs=axis_signs,
            button_names=button_names,
            hand=hand,
            frame_id=frame_id,
        )
        # All keys up front: the reading thread never grows the dict while a caller copies it.
        self._stats: Counter[str] = Counter(dict.fromkeys(_STAT_KEYS, 0))
        self._worker = DeviceWorker(id, kind="spacemouse", thread_name=f"telerig-spacemouse-{id}", log=_log)
        #: Set once the device node is open (cleared on disconnect).
        self.connected = threading.Event()

    @property
    def id(self) -> str:
        """Device id."""
        return self._id

    @property
    def on_change_streams(self) -> frozenset[str]:
        """Both (:class:`~telerig.devices.base.ChangeDrivenDevice`): the puck reports only while it
        is moved, the buttons when the held set changes."""
        return frozenset({"twist", f"{self.normalizer.hand}_controller"})

    @property
    def stats(self) -> Mapping[str, int]:
        """Counters: ``reports`` read, ``samples`` emitted, drops (``wire_error``, ``ignored_report``),
        ``sink_error``, ``open_failed``, ``disconnected``."""
        return {**self._stats, "samples": self._worker.samples, "sink_error": self._worker.sink_errors}

    def start(self, sink: SampleSink) -> None:
        """Open the device (finding it through sysfs when ``path`` is None) and read on a new thread.

        Raises:
            DeviceError: Already running, or no SpaceMouse found.
        """
        with self._worker.starting() as launch:
            path = self.path
            if path is None:
                path = find_spacemouse(
                    self.sys_root, self.dev_root, vendor_id=self.vendor_id, product_id=self.product_id
                ).path
            launch(self._run, path, sink)

    def stop(self) -> None:
        """Stop reading, close the node and join the thread. Idempotent."""
        self._worker.stop()

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
            try:
                stream = not stat.S_ISCHR(os.fstat(fd).st_mode)
                self.connected.set()
                self._read_loop(fd, stream, sink, stop)
            finally:
                self.connected.clear()
                os.close(fd)
            if not stop.is_set():
                self._stats["disconnected"] += 1
                stop.wait(_REOPEN_S if not stream else 0.01)

    def _read_loop(self, fd: int, stream: bool, sink: SampleSink, stop: threading.Event) -> None:
        poller = select.poll()
        poller.register(fd, select.POLLIN | select.POLLHUP | select.POLLERR)
        pending = b""
        combined: bool | None = {"split": False, "combined": True}.get(self.layout)
        while not stop.is_set():
            if not poller.poll(_POLL_MS):
                continue
            try:
                data = os.read(fd, 4096 if stream else 64)
            except BlockingIOError:
                continue
            except OSError as exc:
                if exc.errno not in (errno.ENODEV, errno.EIO):
                    _log.warning("%s: read failed: %s", self._id, exc)
                return
            if not data:
                return  # writer closed the FIFO, or the node went away
            capture = now_ns()
            if not stream:
                self._handle(data, capture, sink)
                continue
            if combined is None:
                # A FIFO loses report boundaries; learn the report-1 length from a whole first read.
                # Split devices send 1 then 2: a 7-byte read, or report 2 right after 7 bytes.
                split = data[0] == 1 and (len(data) == 7 or (len(data) >= 14 and data[7] == 2))
                combined = not split
            reports, pending = split_stream(pending + data, combined=combined)
            for report in reports:
                self._handle(report, capture, sink)

    def _handle(self, data: bytes, capture_ns: int, sink: SampleSink) -> None:
        self._stats["reports"] += 1
        try:
            report = parse_report(data)
        except WireError as exc:
            self._stats["wire_error"] += 1
            _log.debug("%s: dropped report: %s", self._id, exc)
            return
        if isinstance(report, OtherReport):
            self._stats["ignored_report"] += 1
            return
        sample = self.normalizer.feed(report, capture_ns, capture_ns)
        if sample is not None:
            self._worker.deliver(sink, sample)
