"""Linux evdev ``input_event`` records from a gamepad → two ``ControllerState`` s and a ``Twist``.

Wire format (64-bit Linux, little-endian): each ``read()`` of ``/dev/input/eventN`` returns whole
24-byte ``struct input_event`` records: ``tv_sec`` int64, ``tv_usec`` int64, ``type`` u16,
``code`` u16, ``value`` s32. An ``EV_SYN``/``SYN_REPORT`` record closes one report (one sample);
``SYN_DROPPED`` means the kernel buffer overflowed and events up to the next ``SYN_REPORT`` are
discarded. The timeval is the kernel's event time (``CLOCK_REALTIME`` unless a reader switched the
clock with ``EVIOCSCLOCKID``); :class:`ClockMapper` maps it into the common clock.

Split into hands (a gamepad is held in both): the **left** ``ControllerState`` has the left stick
as ``joystick``, LT as ``trigger``, LB as ``grip`` (0 or 1) and the buttons on the left half
(``lb``, ``lt``, ``l3``, ``select``, d-pad ``dpad_up``...); the **right** one has the right stick,
RT, RB and ``a``, ``b``, ``x``, ``y``, ``rb``, ``rt``, ``r3``, ``start``, ``mode``. Face buttons are
named by the Xbox label at the same position (PlayStation cross = ``a``, circle = ``b``, square =
``x``, triangle = ``y``). Sticks follow ``ControllerState``: x right, y forward (evdev ``ABS_Y``
grows toward the user, so it is negated). A gamepad has no pose: ``position`` is the origin and
``orientation`` the identity; bind only its inputs. A hand's state is emitted on the report where
it changes (both on the first report); the ``Twist`` when its value changes.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Literal

import numpy as np

from telerig.errors import ConfigError, WireError
from telerig.ir.clock import ClockOffsetEstimator
from telerig.ir.types import ControllerState, Sample, Stamp, Twist

__all__ = [
    "ABS_CODES",
    "DEFAULT_TWIST_MAP",
    "EVENT_SIZE",
    "FUZZ_TARGET",
    "PROFILES",
    "GamepadNormalizer",
    "InputEvent",
    "Profile",
    "TWIST_INPUTS",
    "TWIST_OUTPUTS",
    "parse_events",
]

EVENT = struct.Struct("<qqHHi")
#: Bytes per ``struct input_event`` on 64-bit Linux.
EVENT_SIZE = EVENT.size

EV_SYN, EV_KEY, EV_ABS = 0x00, 0x01, 0x03
SYN_REPORT, SYN_DROPPED = 0, 3
ABS_X, ABS_Y, ABS_Z, ABS_RX, ABS_RY, ABS_RZ = 0x00, 0x01, 0x02, 0x03, 0x04, 0x05
ABS_GAS, ABS_BRAKE, ABS_HAT0X, ABS_HAT0Y = 0x09, 0x0A, 0x10, 0x11

#: evdev axis name → ``ABS_*`` code, for ``axis_ranges``.
ABS_CODES: dict[str, int] = {
    "x": ABS_X,
    "y": ABS_Y,
    "z": ABS_Z,
    "rx": ABS_RX,
    "ry": ABS_RY,
    "rz": ABS_RZ,
    "gas": ABS_GAS,
    "brake": ABS_BRAKE,
    "hat0x": ABS_HAT0X,
    "hat0y": ABS_HAT0Y,
}
_LEFT_TRIGGER = (ABS_Z, ABS_BRAKE)
_RIGHT_TRIGGER = (ABS_RZ, ABS_GAS)

_COMMON_KEYS = {
    0x130: "a",  # BTN_SOUTH
    0x131: "b",  # BTN_EAST
    0x136: "lb",  # BTN_TL
    0x137: "rb",  # BTN_TR
    0x138: "lt",  # BTN_TL2 (digital trigger, some drivers)
    0x139: "rt",  # BTN_TR2
    0x13A: "select",  # BTN_SELECT (Back / View / Create)
    0x13B: "start",  # BTN_START (Menu / Options)
    0x13C: "mode",  # BTN_MODE (Guide / PS)
    0x13D: "l3",  # BTN_THUMBL
    0x13E: "r3",  # BTN_THUMBR
    0x220: "dpad_up",  # BTN_DPAD_UP
    0x221: "dpad_down",
    0x222: "dpad_left",
    0x223: "dpad_right",
}

#: Buttons reported in the left hand's ``ControllerState``; all others go to the right.
LEFT_BUTTONS = frozenset({"lb", "lt", "l3", "select", "dpad_up", "dpad_down", "dpad_left", "dpad_right"})

#: Inputs a twist expression may use, each normalized to [-1, 1] (triggers [0, 1]).
TWIST_INPUTS = (
    "left_x",
    "left_y",
    "right_x",
    "right_y",
    "left_trigger",
    "right_trigger",
    "dpad_x",
    "dpad_y",
)
#: Twist components a twist map may drive.
TWIST_OUTPUTS = ("linear_x", "linear_y", "linear_z", "angular_x", "angular_y", "angular_z")

#: Default mapping: left stick drives x/y (push forward = +x, push left = +y), right stick y
#: drives z, right stick x yaws (push left = counter-clockwise).
DEFAULT_TWIST_MAP: dict[str, str] = {
    "linear_x": "left_y",
    "linear_y": "-left_x",
    "linear_z": "right_y",
    "angular_z": "-right_x",
}


@dataclass(frozen=True, slots=True)
class Profile:
    """Button codes and default axis ranges of a controller family under its Linux driver.

    Attributes:
        buttons: ``BTN_*`` code → button name.
        stick_range: Raw (min, max) of ``ABS_X/Y/RX/RY``.
        trigger_range: Raw (min, max) of ``ABS_Z/RZ/GAS/BRAKE``.
    """

    buttons: Mapping[int, str]
    stick_range: tuple[int, int]
    trigger_range: tuple[int, int]


#: ``xbox``: xpad / xpadneo (X on ``BTN_X`` = 0x133, Y on 0x134; Xbox One triggers 0..1023).
#: ``playstation``: hid-playstation / hid-sony (triangle on ``BTN_NORTH`` = 0x133, square on
#: ``BTN_WEST`` = 0x134; sticks and triggers 0..255).
PROFILES: dict[str, Profile] = {
    "xbox": Profile({**_COMMON_KEYS, 0x133: "x", 0x134: "y"}, (-32768, 32767), (0, 1023)),
    "playstation": Profile({**_COMMON_KEYS, 0x133: "y", 0x134: "x"}, (0, 255), (0, 255)),
}


@dataclass(frozen=True, slots=True)
class InputEvent:
    """One ``struct input_event``: kernel time ``sec`` [s] + ``usec`` [µs], ``type``, ``code``, ``value``."""

    sec: int
    usec: int
    type: int
    code: int
    value: int

    @property
    def time_ns(self) -> int:
        """Event time [ns] in the kernel clock of the event device."""
        return self.sec * 1_000_000_000 + self.usec * 1000


_MAX_SEC = 1 << 36  # ~ year 4147; beyond that a timeval is garbage


def parse_events(data: bytes) -> list[InputEvent]:
    """Decode whole ``input_event`` records.

    Raises:
        WireError: Length not a multiple of 24, or a timeval out of range.
    """
    if len(data) % EVENT_SIZE:
        raise WireError(f"evdev read must be a multiple of {EVENT_SIZE} bytes, got {len(data)}")
    out = []
    for sec, usec, typ, code, value in EVENT.iter_unpack(data):
        if not 0 <= usec < 1_000_000:
            raise WireError(f"input_event tv_usec must be in [0, 999999], got {usec}")
        if not 0 <= sec < _MAX_SEC:
            raise WireError(f"input_event tv_sec must be in [0, 2^36), got {sec}")
        out.append(InputEvent(sec, usec, typ, code, value))
    return out


def _parse_expr(output: str, expr: str) -> tuple[tuple[float, str], ...]:
    text = expr.replace(" ", "")
    if not text:
        return ()
    terms: list[tuple[float, str]] = []
    sign = 1.0
    name = ""
    for ch in text + "+":
        if ch in "+-":
            if name:
                if name not in TWIST_INPUTS:
                    raise ConfigError(
                        f"twist_map.{output}: unknown input {name!r}; valid: {', '.join(TWIST_INPUTS)}"
                    )
                terms.append((sign, name))
                name = ""
            elif terms or sign != 1.0:
                raise ConfigError(
                    f"twist_map.{output}: malformed expression {expr!r}; e.g. 'right_trigger-left_trigger'"
                )
            sign = 1.0 if ch == "+" else -1.0
        else:
            name += ch
    return tuple(terms)


def _check_twist_map(twist_map: Mapping[str, str]) -> dict[str, tuple[tuple[float, str], ...]]:
    out = {}
    for key, expr in twist_map.items():
        if key not in TWIST_OUTPUTS:
            raise ConfigError(f"twist_map: unknown output {key!r}; valid: {', '.join(TWIST_OUTPUTS)}")
        out[key] = _parse_expr(key, expr)
    return out


def _clip(v: float, lo: float, hi: float) -> float:
    return lo if v < lo else hi if v > hi else v


class GamepadNormalizer:
    """Accumulates evdev events and turns each ``SYN_REPORT`` into IR samples (pure, no I/O).

    Sticks: centred and scaled to [-1, 1] from their raw range, then a radial deadzone (the
    magnitude below ``stick_deadzone`` reads 0, above it is rescaled to reach 1). Triggers: [0, 1]
    from their raw range with a linear deadzone. Raw values outside the range are clamped, so no
    value leaves its interval. ``Twist`` components are ``max_linear`` [m/s] / ``max_angular``
    [rad/s] times the clamped sum of their ``twist_map`` expression.

    Source ids: ``<id>/left``, ``<id>/right`` (``ControllerState``) and ``<id>`` (``Twist``).
    """

    def __init__(
        self,
        source_id: str,
        *,
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
        clock_window_s: float = 5.0,
    ) -> None:
        """Args:
        source_id: Device id the source ids derive from.
        profile: Controller family: button codes and default axis ranges.
        axis_ranges: Raw (min, max) per axis name (``x``, ``y``, ``rx``, ``ry``, ``z``, ``rz``,
            ``gas``, ``brake``, ``hat0x``, ``hat0y``), overriding the profile.
        button_map: ``BTN_*`` code → name, added to (and overriding) the profile's.
        stick_deadzone: Radial stick deadzone, fraction of full deflection in [0, 0.9].
        trigger_deadzone: Trigger deadzone, fraction of full travel in [0, 0.9].
        twist_map: Twist component → expression over :data:`TWIST_INPUTS`, e.g.
            ``{"linear_z": "right_trigger-left_trigger"}``; default :data:`DEFAULT_TWIST_MAP`.
        max_linear: Linear speed for a value of 1 [m/s].
        max_angular: Angular speed for a value of 1 [rad/s].
        frame_id: Frame of the ``ControllerState`` s.
        twist_frame_id: Frame of the ``Twist``.
        clock_window_s: Window [s] of the device-clock offset estimate (:class:`ClockOffsetEstimator`).
        """
        if profile not in PROFILES:
            raise ConfigError(f"profile must be one of {', '.join(PROFILES)}, got {profile!r}")
        for name, value in (("stick_deadzone", stick_deadzone), ("trigger_deadzone", trigger_deadzone)):
            if not (math.isfinite(value) and 0.0 <= value <= 0.9):
                raise ConfigError(f"{name} must be in [0, 0.9], got {value}")
        for name, value in (("max_linear", max_linear), ("max_angular", max_angular)):
            if not (math.isfinite(value) and value > 0.0):
                raise ConfigError(f"{name} must be > 0, got {value}")
        prof = PROFILES[profile]
        self.source_id = source_id
        self.profile = profile
        self.buttons: dict[int, str] = {**prof.buttons, **(button_map or {})}
        self.ranges: dict[int, tuple[int, int]] = {
            **dict.fromkeys((ABS_X, ABS_Y, ABS_RX, ABS_RY), prof.stick_range),
            **dict.fromkeys((*_LEFT_TRIGGER, *_RIGHT_TRIGGER), prof.trigger_range),
            ABS_HAT0X: (-1, 1),
            ABS_HAT0Y: (-1, 1),
        }
        for name, rng in (axis_ranges or {}).items():
            if name not in ABS_CODES:
                raise ConfigError(f"axis_ranges: unknown axis {name!r}; valid: {', '.join(ABS_CODES)}")
            self.set_range(ABS_CODES[name], rng)
        self.stick_deadzone = float(stick_deadzone)
        self.trigger_deadzone = float(trigger_deadzone)
        self.twist_map = _check_twist_map(DEFAULT_TWIST_MAP if twist_map is None else twist_map)
        self.max_linear = float(max_linear)
        self.max_angular = float(max_angular)
        self.frame_id = frame_id
        self.twist_frame_id = twist_frame_id
        self.clock = ClockOffsetEstimator(round(clock_window_s * 1e9))
        self.dropped_reports = 0
        self._raw: dict[int, int] = {}
        self._held: set[str] = set()
        self._dropping = False
        self._last: dict[str, tuple[object, ...]] = {}
        self._seq = {"left": 0, "right": 0, "twist": 0}
        self._origin = np.zeros(3)
        self._identity = np.array([1.0, 0.0, 0.0, 0.0])

    def set_range(self, code: int, rng: tuple[int, int]) -> None:
        """Set the raw (min, max) of axis ``code`` (e.g. from ``EVIOCGABS``); min must be < max."""
        lo, hi = int(rng[0]), int(rng[1])
        if lo >= hi:
            raise ConfigError(f"axis range of ABS code {code:#x} must have min < max, got ({lo}, {hi})")
        self.ranges[code] = (lo, hi)

    def _centered(self, code: int) -> float:
        lo, hi = self.ranges[code]
        raw = self._raw.get(code)
        if raw is None:
            return 0.0
        return _clip((2.0 * raw - lo - hi) / (hi - lo), -1.0, 1.0)

    def _stick(self, cx: int, cy: int) -> tuple[float, float]:
        x, y = self._centered(cx), -self._centered(cy)
        r = math.hypot(x, y)
        dz = self.stick_deadzone
        if r <= dz:
            return 0.0, 0.0
        scale = min(1.0, (r - dz) / (1.0 - dz)) / r
        return _clip(x * scale, -1.0, 1.0), _clip(y * scale, -1.0, 1.0)

    def _trigger(self, codes: Iterable[int]) -> float:
        best = 0.0
        for code in codes:
            raw = self._raw.get(code)
            if raw is None:
                continue
            lo, hi = self.ranges[code]
            v = _clip((raw - lo) / (hi - lo), 0.0, 1.0)
            dz = self.trigger_deadzone
            best = max(best, 0.0 if v <= dz else (v - dz) / (1.0 - dz))
        return best

    def feed(self, event: InputEvent, receive_ns: int) -> list[Sample]:
        """Apply one event; on ``SYN_REPORT`` return the samples of the report (else ``[]``).

        ``receive_ns`` is when the record was read, in the common clock [ns].
        """
        typ = event.type
        if typ == EV_SYN:
            if event.code == SYN_DROPPED:
                self._dropping = True
                self.dropped_reports += 1
                return []
            if event.code != SYN_REPORT:
                return []
            if self._dropping:
                # The kernel says the state is inconsistent until this report; skip it.
                self._dropping = False
                return []
            return self._report(event.time_ns, receive_ns)
        if self._dropping:
            return []
        if typ == EV_ABS:
            if event.code in self.ranges:
                self._raw[event.code] = event.value
        elif typ == EV_KEY:
            name = self.buttons.get(event.code)
            if name is not None:
                if event.value:
                    self._held.add(name)
                else:
                    self._held.discard(name)
        return []

    def inputs(self) -> dict[str, float]:
        """Current normalized inputs (:data:`TWIST_INPUTS`): sticks, dpad in [-1, 1], triggers in [0, 1]."""
        lx, ly = self._stick(ABS_X, ABS_Y)
        rx, ry = self._stick(ABS_RX, ABS_RY)
        held = self._held
        hat_x = self._raw.get(ABS_HAT0X, 0)
        hat_y = self._raw.get(ABS_HAT0Y, 0)
        dpad_x = (hat_x > 0 or "dpad_right" in held) - (hat_x < 0 or "dpad_left" in held)
        dpad_y = (hat_y < 0 or "dpad_up" in held) - (hat_y > 0 or "dpad_down" in held)
        return {
            "left_x": lx,
            "left_y": ly,
            "right_x": rx,
            "right_y": ry,
            "left_trigger": self._trigger(_LEFT_TRIGGER),
            "right_trigger": self._trigger(_RIGHT_TRIGGER),
            "dpad_x": float(dpad_x),
            "dpad_y": float(dpad_y),
        }

    def _report(self, device_ns: int, receive_ns: int) -> list[Sample]:
        capture_ns = device_ns + self.clock.update(device_ns, receive_ns)
        inp = self.inputs()
        held = set(self._held)
        hat_x = self._raw.get(ABS_HAT0X, 0)
        hat_y = self._raw.get(ABS_HAT0Y, 0)
        if hat_x:
            held.add("dpad_right" if hat_x > 0 else "dpad_left")
        if hat_y:
            held.add("dpad_down" if hat_y > 0 else "dpad_up")
        out: list[Sample] = []
        for hand in ("left", "right"):
            side = "left" if hand == "left" else "right"
            buttons = frozenset(b for b in held if (b in LEFT_BUTTONS) == (hand == "left"))
            grip = 1.0 if ("lb" if hand == "left" else "rb") in held else 0.0
            key = (inp[f"{side}_x"], inp[f"{side}_y"], inp[f"{side}_trigger"], grip, buttons)
            if self._last.get(hand) == key:
                continue
            self._last[hand] = key
            stamp = Stamp(f"{self.source_id}/{hand}", self._seq[hand], device_ns, capture_ns)
            self._seq[hand] += 1
            out.append(
                ControllerState(
                    stamp=stamp,
                    hand=hand,
                    position=self._origin,
                    orientation=self._identity,
                    frame_id=self.frame_id,
                    buttons=buttons,
                    trigger=key[2],
                    grip=grip,
                    joystick=np.array(key[:2]),
                )
            )
        values = []
        for name in TWIST_OUTPUTS:
            terms = self.twist_map.get(name, ())
            v = _clip(sum(sign * inp[i] for sign, i in terms), -1.0, 1.0)
            values.append(v * (self.max_linear if name.startswith("linear") else self.max_angular))
        twist_key = tuple(values)
        if self._last.get("twist") != twist_key:
            self._last["twist"] = twist_key
            stamp = Stamp(self.source_id, self._seq["twist"], device_ns, capture_ns)
            self._seq["twist"] += 1
            out.append(Twist(stamp, np.array(values[:3]), np.array(values[3:]), self.twist_frame_id))
        return out


def _fuzz(data: bytes) -> object:
    norm = GamepadNormalizer("fuzz")
    return [s for e in parse_events(data) for s in norm.feed(e, 0)]


#: Parses whole records and feeds them to a fresh normalizer; raises only :class:`WireError`.
FUZZ_TARGET: Callable[[bytes], object] = _fuzz
