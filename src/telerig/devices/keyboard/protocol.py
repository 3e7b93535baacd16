"""Terminal keyboard bytes → key names → a held-key ``Twist`` and a mode/trigger ``ControllerState``.

Wire format: the bytes a terminal in cbreak mode sends for key presses. Printable ASCII is the
key itself (letters lower-cased, so Shift does not matter; space is ``"space"``); ``\\r``/``\\n``
``"enter"``, ``\\t`` ``"tab"``, DEL/BS ``"backspace"``, other C0 controls ``"ctrl+<letter>"``;
UTF-8 characters are themselves. Escape sequences: CSI ``ESC [ params final`` (``A``/``B``/``C``/``D``
arrows ``up``/``down``/``right``/``left``, ``H``/``F`` home/end, ``5~``/``6~`` ``pageup``/
``pagedown``, ``1~``/``7~`` home, ``4~``/``8~`` end, ``2~`` insert, ``3~`` delete; modifier
parameters such as ``1;5A`` are ignored), SS3 ``ESC O A..D/H/F`` (application cursor mode), and
``ESC <char>`` (Alt+char, read as the char). A lone ESC is ``"escape"`` once no byte follows it
within the decoder's escape timeout.

Terminals send no key-up, only the auto-repeat of the key held last. :class:`KeyboardNormalizer`
therefore treats a key as held from its press until ``initial_hold_s`` passes without a repeat
(long enough to span the terminal's repeat delay, ~250-660 ms), and once repeats come, until
``repeat_release_s`` passes without one. Only the last key pressed repeats, so chords (W+D) hold
only briefly: drive one direction at a time, or use the browser page, which sees key-up events.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np

from telerig.errors import ConfigError, WireError
from telerig.ir.types import ControllerState, Handedness, Stamp, Twist

__all__ = [
    "DEFAULT_KEY_MAP",
    "FUZZ_TARGET",
    "TWIST_COMPONENTS",
    "KeyDecoder",
    "KeyboardNormalizer",
    "decode_keys",
]

_CSI_FINAL = {"A": "up", "B": "down", "C": "right", "D": "left", "H": "home", "F": "end"}
_CSI_TILDE = {
    "1": "home",
    "2": "insert",
    "3": "delete",
    "4": "end",
    "5": "pageup",
    "6": "pagedown",
    "7": "home",
    "8": "end",
}
_MAX_SEQ = 32  # bytes in one escape sequence; longer is garbage

#: Twist components a key may drive, with a sign: ``"+linear_x"``, ``"-angular_z"``.
TWIST_COMPONENTS = ("linear_x", "linear_y", "linear_z", "angular_x", "angular_y", "angular_z")

#: Default keys: WASD / arrows translate in the operator frame (x forward, y left), R/PgUp up and
#: F/PgDn down, Q/E yaw left/right; space toggles the trigger, digits select a mode.
DEFAULT_KEY_MAP: dict[str, str] = {
    "w": "+linear_x",
    "up": "+linear_x",
    "s": "-linear_x",
    "down": "-linear_x",
    "a": "+linear_y",
    "left": "+linear_y",
    "d": "-linear_y",
    "right": "-linear_y",
    "r": "+linear_z",
    "pageup": "+linear_z",
    "f": "-linear_z",
    "pagedown": "-linear_z",
    "q": "+angular_z",
    "e": "-angular_z",
    "space": "toggle:trigger",
    **{str(d): f"mode:{d}" for d in range(10)},
}


class KeyDecoder:
    """Incremental decoder of terminal bytes into key names; never raises.

    Bytes that form no key (broken UTF-8, an over-long or unterminated escape sequence) are
    skipped and counted in ``malformed``; well-formed sequences with no name (F5, mouse reports)
    are counted in ``unknown``.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self.malformed = 0
        self.unknown = 0

    @property
    def pending(self) -> bool:
        """Whether bytes of an unfinished sequence are buffered (flush after the escape timeout)."""
        return bool(self._buf)

    def feed(self, data: bytes) -> list[str]:
        """Key names completed by ``data``, in order."""
        self._buf += data
        keys: list[str] = []
        i = self._decode(keys, final=False)
        del self._buf[:i]
        return keys

    def flush(self) -> list[str]:
        """End of input or escape timeout: a lone ESC becomes ``"escape"``, other leftovers are malformed."""
        keys: list[str] = []
        i = self._decode(keys, final=True)
        del self._buf[:i]
        if self._buf:
            self.malformed += 1
            self._buf.clear()
        return keys

    def _decode(self, keys: list[str], *, final: bool) -> int:
        buf = self._buf
        n = len(buf)
        i = 0
        while i < n:
            b = buf[i]
            if b == 0x1B:
                used = self._escape(i, keys, final)
                if used == 0:
                    return i  # wait for more bytes
                i += used
            elif b < 0x80:
                keys.append(_ascii_name(b))
                i += 1
            else:
                size = 2 if 0xC2 <= b <= 0xDF else 3 if 0xE0 <= b <= 0xEF else 4 if 0xF0 <= b <= 0xF4 else 0
                if size == 0:
                    self.malformed += 1
                    i += 1
                    continue
                if i + size > n:
                    if not final:
                        return i
                    self.malformed += 1
                    return n
                try:
                    keys.append(bytes(buf[i : i + size]).decode("utf-8").lower())
                except UnicodeDecodeError:
                    self.malformed += 1
                    i += 1
                    continue
                i += size
        return i

    def _escape(self, i: int, keys: list[str], final: bool) -> int:
        """Bytes used by the escape sequence at ``i``; 0 if it may still be incomplete."""
        buf = self._buf
        n = len(buf)
        if i + 1 >= n:
            if final:
                keys.append("escape")
                return 1
            return 0
        nxt = buf[i + 1]
        if nxt == ord("["):
            j = i + 2
            while j < n and 0x20 <= buf[j] <= 0x3F:
                j += 1
            if j - i > _MAX_SEQ:
                self.malformed += 1
                return j - i
            if j >= n:
                if final:
                    self.malformed += 1
                    return n - i
                return 0
            end = buf[j]
            if not 0x40 <= end <= 0x7E:
                self.malformed += 1
                return j - i  # skip the broken prefix; the byte at j is decoded on its own
            params = bytes(buf[i + 2 : j]).decode("ascii")
            name = _CSI_TILDE.get(params.split(";")[0]) if end == ord("~") else _CSI_FINAL.get(chr(end))
            if name is None:
                self.unknown += 1
            else:
                keys.append(name)
            return j + 1 - i
        if nxt == ord("O"):
            if i + 2 >= n:
                if final:
                    keys.append("alt+o")
                    return 2
                return 0
            name = _CSI_FINAL.get(chr(buf[i + 2]))
            if name is None:
                self.unknown += 1
            else:
                keys.append(name)
            return 3
        if nxt == 0x1B:
            keys.append("escape")
            return 1
        if nxt < 0x80:
            keys.append("alt+" + _ascii_name(nxt))
            return 2
        keys.append("escape")
        return 1


def _ascii_name(b: int) -> str:
    if b == 0x20:
        return "space"
    if b in (0x0D, 0x0A):
        return "enter"
    if b == 0x09:
        return "tab"
    if b in (0x7F, 0x08):
        return "backspace"
    if b < 0x20:
        return "ctrl+" + chr(b + 0x60) if b else "ctrl+space"
    return chr(b).lower()


def decode_keys(data: bytes) -> list[str]:
    """Strictly decode a complete chunk of terminal bytes into key names.

    Raises:
        WireError: Broken UTF-8 or an unterminated / over-long escape sequence.
    """
    dec = KeyDecoder()
    keys = dec.feed(data) + dec.flush()
    if dec.malformed:
        raise WireError(f"{dec.malformed} malformed key sequence(s) in {len(data)} bytes of terminal input")
    return keys


@dataclass(slots=True)
class _Hold:
    last_ns: int
    repeated: bool


def _parse_action(key: str, action: str) -> tuple[str, str | int | tuple[int, float]]:
    if action[:1] in "+-" and action[1:] in TWIST_COMPONENTS:
        return "axis", (TWIST_COMPONENTS.index(action[1:]), 1.0 if action[0] == "+" else -1.0)
    kind, _, arg = action.partition(":")
    if kind == "toggle" and arg == "trigger":
        return "toggle", arg
    if kind == "mode" and arg.isdigit():
        return "mode", int(arg)
    if kind == "button" and arg:
        return "button", arg
    raise ConfigError(
        f"key_map[{key!r}]: unknown action {action!r}; valid: +/-<component> "
        f"({', '.join(TWIST_COMPONENTS)}), toggle:trigger, mode:<digit>, button:<name>"
    )


class KeyboardNormalizer:
    """Key presses + time → ``Twist`` (held motion keys) and ``ControllerState`` (trigger, mode, buttons).

    Pure, no I/O: the caller passes key names with their receive time [ns] and asks for samples.
    ``Twist`` components are the clamped sum of the held keys' signs times ``max_linear`` [m/s] or
    ``max_angular`` [rad/s]. The ``ControllerState`` (source ``<id>/<hand>``, no pose: origin,
    identity) carries ``trigger`` (toggled 0/1 by ``toggle:trigger``), the held ``button:`` keys
    and the latched mode as button ``"mode<N>"``; it is produced only when one of those changes.
    """

    def __init__(
        self,
        source_id: str,
        *,
        key_map: Mapping[str, str] | None = None,
        max_linear: float = 0.1,
        max_angular: float = 0.5,
        initial_hold_s: float = 0.6,
        repeat_release_s: float = 0.12,
        hand: Handedness = "right",
        frame_id: str = "operator",
        mode: int = 1,
    ) -> None:
        """Args:
        source_id: Source id of the ``Twist``; the ``ControllerState`` uses ``<source_id>/<hand>``.
        key_map: Key name → action (see :data:`DEFAULT_KEY_MAP`); ``None`` uses the default.
        max_linear: Linear speed of one held key [m/s].
        max_angular: Angular speed of one held key [rad/s].
        initial_hold_s: How long a press counts as held before the first repeat arrives [s].
        repeat_release_s: How long after the last repeat a key counts as released [s].
        hand: Hand of the ``ControllerState``.
        frame_id: Frame of both samples.
        mode: Mode before any digit is pressed.
        """
        for name, value in (
            ("max_linear", max_linear),
            ("max_angular", max_angular),
            ("initial_hold_s", initial_hold_s),
            ("repeat_release_s", repeat_release_s),
        ):
            if not (math.isfinite(value) and value > 0.0):
                raise ConfigError(f"{name} must be > 0, got {value}")
        raw = DEFAULT_KEY_MAP if key_map is None else key_map
        self.actions = {k: _parse_action(k, a) for k, a in raw.items()}
        self.source_id = source_id
        self.controller_source_id = f"{source_id}/{hand}"
        self.max_linear = float(max_linear)
        self.max_angular = float(max_angular)
        self.initial_hold_ns = round(initial_hold_s * 1e9)
        self.repeat_release_ns = round(repeat_release_s * 1e9)
        self.hand: Handedness = hand
        self.frame_id = frame_id
        self.mode = mode
        self.trigger = 0.0
        self.unmapped = 0
        self._holds: dict[str, _Hold] = {}
        self._last_key: str | None = None
        self._last_controller: tuple[float, frozenset[str]] | None = None
        self._seq = 0
        self._controller_seq = 0
        self._origin = np.zeros(3)
        self._identity = np.array([1.0, 0.0, 0.0, 0.0])

    def press(self, key: str, t_ns: int) -> None:
        """Register a press (or an auto-repeat) of ``key`` received at ``t_ns`` [ns].

        A byte of the key that arrived last, within its hold time, is an auto-repeat (it extends
        the hold and does not toggle again); otherwise it is a new press.
        """
        action = self.actions.get(key)
        if action is None:
            self.unmapped += 1
            return
        hold = self._holds.get(key)
        # Terminals auto-repeat only the last key pressed: after another key it is a new press.
        repeat = hold is not None and key == self._last_key and self._active(hold, t_ns)
        self._last_key = key
        if hold is not None and repeat:
            hold.last_ns = t_ns
            hold.repeated = True
        else:
            self._holds[key] = _Hold(t_ns, False)
        if repeat:
            return
        kind, arg = action
        if kind == "toggle":
            self.trigger = 0.0 if self.trigger else 1.0
        elif kind == "mode":
            assert isinstance(arg, int)
            self.mode = arg

    def _active(self, hold: _Hold, t_ns: int) -> bool:
        limit = self.repeat_release_ns if hold.repeated else self.initial_hold_ns
        return t_ns - hold.last_ns <= limit

    def held(self, t_ns: int) -> frozenset[str]:
        """Keys counted as held at ``t_ns`` [ns]."""
        return frozenset(k for k, h in self._holds.items() if self._active(h, t_ns))

    def twist(self, t_ns: int, device_ns: int | None = None) -> Twist:
        """The ``Twist`` of the keys held at ``t_ns`` (capture time) [ns]; ``device_ns`` defaults to it."""
        values = [0.0] * 6
        for key in self.held(t_ns):
            kind, arg = self.actions[key]
            if kind == "axis":
                assert isinstance(arg, tuple)
                values[arg[0]] += arg[1]
        values = [max(-1.0, min(1.0, v)) for v in values]
        lin = [v * self.max_linear for v in values[:3]]
        ang = [v * self.max_angular for v in values[3:]]
        stamp = Stamp(self.source_id, self._seq, t_ns if device_ns is None else device_ns, t_ns)
        self._seq += 1
        return Twist(stamp, np.array(lin), np.array(ang), self.frame_id)

    def controller(self, t_ns: int, device_ns: int | None = None) -> ControllerState | None:
        """The ``ControllerState`` at ``t_ns`` [ns] if trigger, mode or held buttons changed, else None."""
        buttons = {f"mode{self.mode}"}
        for key in self.held(t_ns):
            kind, arg = self.actions[key]
            if kind == "button":
                assert isinstance(arg, str)
                buttons.add(arg)
        state = (self.trigger, frozenset(buttons))
        if state == self._last_controller:
            return None
        self._last_controller = state
        stamp = Stamp(
            self.controller_source_id, self._controller_seq, t_ns if device_ns is None else device_ns, t_ns
        )
        self._controller_seq += 1
        return ControllerState(
            stamp=stamp,
            hand=self.hand,
            position=self._origin,
            orientation=self._identity,
            frame_id=self.frame_id,
            buttons=state[1],
            trigger=self.trigger,
        )


def _fuzz(data: bytes) -> object:
    norm = KeyboardNormalizer("fuzz")
    for k, key in enumerate(decode_keys(data)):
        norm.press(key, k * 10_000_000)
    return norm.twist(len(data) * 10_000_000), norm.controller(len(data) * 10_000_000)


#: Strictly decodes one chunk, presses its keys 10 ms apart and samples; raises only :class:`WireError`.
FUZZ_TARGET: Callable[[bytes], object] = _fuzz
