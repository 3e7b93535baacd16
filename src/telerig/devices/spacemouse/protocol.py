"""3Dconnexion SpaceMouse HID input reports (as read from Linux hidraw) → ``Twist`` and buttons.

Wire format (one HID input report per ``read()`` of ``/dev/hidrawN``, report id first):

* id 1, 7 bytes: translation ``x, y, z`` as int16 little-endian (older devices: SpaceNavigator,
  SpaceExplorer, SpacePilot, vendor 046D).
* id 2, 7 bytes: rotation ``rx, ry, rz`` as int16 little-endian (same older devices; they send
  1 then 2 for every motion update).
* id 1, 13 bytes: all six axes ``x, y, z, rx, ry, rz`` (newer devices: SpaceMouse Wireless, Pro
  Wireless, Compact, Enterprise, vendor 256F).
* id 3, 2 to 64 bytes: button bitmask, little-endian over the bytes after the id (bit k = button k).
* Other ids (e.g. 0x17 battery level on wireless models) carry no motion; they parse as
  :class:`OtherReport` and are ignored.

Device axes, as 3Dconnexion reports them: x right, y toward the user, z down (pushing the cap
down is +z); rotations are right-handed about the same axes. That frame is right-handed, and the
operator frame (x forward, y left, z up) is reached by the proper rotation
``op = (-y_dev, -x_dev, -z_dev)``, applied alike to translation and rotation (angular velocity is a
pseudo-vector, and a proper rotation maps it like a vector). Models that disagree with this are
fixed by ``axis_signs``.

Full deflection is about ±350 counts; counts beyond ``full_scale`` are clamped, so every
``Twist`` component lies within ``±max_linear`` [m/s] or ``±max_angular`` [rad/s].
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from telerig.errors import ConfigError, WireError
from telerig.ir.types import ControllerState, Handedness, Stamp, Twist

__all__ = [
    "FULL_SCALE_COUNTS",
    "FUZZ_TARGET",
    "ButtonReport",
    "MotionReport",
    "OtherReport",
    "Report",
    "SpaceMouseNormalizer",
    "parse_report",
    "split_stream",
]

#: Counts at full deflection of the cap, as 3Dconnexion devices report them.
FULL_SCALE_COUNTS = 350

_MAX_BUTTON_BYTES = 63  # a hidraw report is at most 64 bytes with its id
_I16X3 = struct.Struct("<3h")
_I16X6 = struct.Struct("<6h")
_IDENTITY = (1.0, 0.0, 0.0, 0.0)


@dataclass(frozen=True, slots=True)
class MotionReport:
    """Axis counts from report 1 or 2, in the device frame (x right, y toward user, z down).

    Attributes:
        translation: ``(x, y, z)`` counts, or ``None`` if this report carries no translation.
        rotation: ``(rx, ry, rz)`` counts, or ``None`` if this report carries no rotation.
    """

    translation: tuple[int, int, int] | None
    rotation: tuple[int, int, int] | None


@dataclass(frozen=True, slots=True)
class ButtonReport:
    """Report 3: ``mask`` has bit k set while button k is held."""

    mask: int


@dataclass(frozen=True, slots=True)
class OtherReport:
    """A report without motion or buttons (battery level, vendor reports); ignored."""

    report_id: int


Report = MotionReport | ButtonReport | OtherReport


def parse_report(report: bytes) -> Report:
    """Decode one HID input report (report id first), exactly as one hidraw ``read()`` returns it.

    Raises:
        WireError: Empty report, or a motion/button report of the wrong length.
    """
    n = len(report)
    if n == 0:
        raise WireError("empty HID report; a report starts with its id byte")
    rid = report[0]
    if rid == 1:
        if n == 7:
            return MotionReport(_I16X3.unpack_from(report, 1), None)
        if n == 13:
            x, y, z, rx, ry, rz = _I16X6.unpack_from(report, 1)
            return MotionReport((x, y, z), (rx, ry, rz))
        raise WireError(f"translation report (id 1) must be 7 or 13 bytes, got {n}")
    if rid == 2:
        if n != 7:
            raise WireError(f"rotation report (id 2) must be 7 bytes, got {n}")
        return MotionReport(None, _I16X3.unpack_from(report, 1))
    if rid == 3:
        if not 2 <= n <= _MAX_BUTTON_BYTES + 1:
            raise WireError(f"button report (id 3) must be 2 to 64 bytes, got {n}")
        return ButtonReport(int.from_bytes(report[1:], "little"))
    return OtherReport(rid)


def split_stream(buf: bytes, *, combined: bool) -> tuple[list[bytes], bytes]:
    """Split a byte stream of back-to-back reports (a FIFO, not hidraw) into whole reports.

    hidraw keeps report boundaries; a pipe does not, so the length of report 1 must be known:
    ``combined`` selects the 13-byte six-axis layout, otherwise 7 bytes. Button reports in a
    stream are taken as 3 bytes (id + 16 buttons), other ids as 2 bytes.

    Returns:
        The whole reports, and the incomplete tail to prepend to the next read.
    """
    out: list[bytes] = []
    i = 0
    n = len(buf)
    while i < n:
        rid = buf[i]
        size = (13 if combined else 7) if rid == 1 else 7 if rid == 2 else 3 if rid == 3 else 2
        if i + size > n:
            break
        out.append(buf[i : i + size])
        i += size
    return out, buf[i:]


def _check_axis_signs(signs: Sequence[float]) -> tuple[float, ...]:
    out = tuple(float(s) for s in signs)
    if len(out) != 6 or any(s not in (-1.0, 1.0) for s in out):
        raise ConfigError(
            f"axis_signs must be six values of 1 or -1 (x, y, z, roll, pitch, yaw), got {list(signs)}"
        )
    return out


class SpaceMouseNormalizer:
    """Turns parsed reports into operator-frame ``Twist`` samples and button ``ControllerState`` s.

    Pure state machine, no I/O: the caller passes the stamp fields. Every motion report yields one
    ``Twist`` holding the latest translation and rotation (on split-report devices the half not in
    this report keeps its last value, so such devices give two Twists per update). A button report
    yields a ``ControllerState`` only when the set of held buttons changes; its pose is the origin
    with identity orientation (a SpaceMouse has no pose: bind only its buttons).
    """

    def __init__(
        self,
        source_id: str,
        *,
        max_linear: float = 0.25,
        max_angular: float = 1.0,
        deadband: int = 10,
        full_scale: int = FULL_SCALE_COUNTS,
        axis_signs: Sequence[float] = (1, 1, 1, 1, 1, 1),
        button_names: Sequence[str] = (),
        hand: Handedness = "right",
        frame_id: str = "operator",
    ) -> None:
        """Args:
        source_id: Source id of the ``Twist`` samples; buttons use ``"<source_id>/buttons"``.
        max_linear: Linear speed at full deflection [m/s] (> 0).
        max_angular: Angular speed at full deflection [rad/s] (> 0).
        deadband: Counts around zero read as zero, per axis (0 <= deadband < full_scale).
        full_scale: Counts at full deflection (> 0); larger counts are clamped.
        axis_signs: Sign flips in the operator frame for (x, y, z, roll, pitch, yaw), each ±1.
        button_names: Name of button k; buttons beyond the list are named ``"button<k>"``.
        hand: Hand reported in the button ``ControllerState``.
        frame_id: Frame of the ``Twist`` samples.
        """
        if not (math.isfinite(max_linear) and max_linear > 0):
            raise ConfigError(f"max_linear must be > 0 m/s, got {max_linear}")
        if not (math.isfinite(max_angular) and max_angular > 0):
            raise ConfigError(f"max_angular must be > 0 rad/s, got {max_angular}")
        if full_scale <= 0:
            raise ConfigError(f"full_scale must be > 0 counts, got {full_scale}")
        if not 0 <= deadband < full_scale:
            raise ConfigError(f"deadband must be in [0, full_scale={full_scale}) counts, got {deadband}")
        self.source_id = source_id
        self.buttons_source_id = f"{source_id}/buttons"
        self.max_linear = float(max_linear)
        self.max_angular = float(max_angular)
        self.deadband = int(deadband)
        self.full_scale = int(full_scale)
        self.axis_signs = _check_axis_signs(axis_signs)
        self.button_names = tuple(button_names)
        self.hand: Handedness = hand
        self.frame_id = frame_id
        self._t = (0, 0, 0)
        self._r = (0, 0, 0)
        self._mask = 0
        self._seq = 0
        self._button_seq = 0
        self._zero3 = np.zeros(3)
        self._identity = np.array(_IDENTITY)

    def _unit(self, counts: int) -> float:
        # Deadband with rescale, so the output is continuous at the deadband edge and reaches ±1.
        a = abs(counts)
        if a <= self.deadband:
            return 0.0
        v = min(1.0, (a - self.deadband) / (self.full_scale - self.deadband))
        return v if counts > 0 else -v

    def button_names_of(self, mask: int) -> frozenset[str]:
        """Names of the buttons set in ``mask``."""
        names = []
        k = 0
        while mask:
            if mask & 1:
                names.append(self.button_names[k] if k < len(self.button_names) else f"button{k}")
            mask >>= 1
            k += 1
        return frozenset(names)

    def feed(self, report: Report, device_ns: int, capture_ns: int) -> Twist | ControllerState | None:
        """The sample ``report`` produces, or ``None`` (unchanged buttons, ignored report id)."""
        if isinstance(report, MotionReport):
            if report.translation is not None:
                self._t = report.translation
            if report.rotation is not None:
                self._r = report.rotation
            x, y, z = self._t
            rx, ry, rz = self._r
            s = self.axis_signs
            lin, ang = self.max_linear, self.max_angular
            u = self._unit
            linear = (s[0] * lin * -u(y), s[1] * lin * -u(x), s[2] * lin * -u(z))
            angular = (s[3] * ang * -u(ry), s[4] * ang * -u(rx), s[5] * ang * -u(rz))
            stamp = Stamp(self.source_id, self._seq, device_ns, capture_ns)
            self._seq += 1
            return Twist(stamp, np.array(linear), np.array(angular), self.frame_id)
        if isinstance(report, ButtonReport):
            if report.mask == self._mask:
                return None
            self._mask = report.mask
            stamp = Stamp(self.buttons_source_id, self._button_seq, device_ns, capture_ns)
            self._button_seq += 1
            return ControllerState(
                stamp=stamp,
                hand=self.hand,
                position=self._zero3,
                orientation=self._identity,
                frame_id=self.frame_id,
                buttons=self.button_names_of(report.mask),
            )
        return None


def _fuzz(data: bytes) -> object:
    return SpaceMouseNormalizer("fuzz").feed(parse_report(data), 0, 0)


#: Parses one report and normalizes it; raises only :class:`WireError`.
FUZZ_TARGET: Callable[[bytes], object] = _fuzz
