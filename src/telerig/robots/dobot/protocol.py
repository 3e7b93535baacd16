"""Dobot CR-series TCP/IP protocol (V3/V4): text commands and replies, and the 1440-byte feedback packet.

Text side (dashboard port 29999, motion port 30003): a command is ASCII
``Name(p1,p2,...,key=value)`` ending at its closing parenthesis (no newline); the
controller answers ``ErrorID,{v1,...,vn},Name(p1,...);`` where ``ErrorID`` 0 means
accepted. Joint angles are degrees on the wire.

Binary side (real-time feedback port 30004): every 8 ms the controller sends one
1440-byte little-endian packet; byte 0-1 hold its length (1440) and bytes 48-55 the
test value ``0x0123456789ABCDEF``, which this module uses to re-synchronise on a
stream that lost bytes. The layout follows Dobot's "TCP/IP Remote Control Interface"
(CR V3 README, section "Real-time feedback"; the V4 ``dobot_api.py`` ``MyType`` agrees
on every field used here).
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from telerig.errors import WireError
from telerig.ir.types import FloatArray

__all__ = [
    "FEEDBACK_DTYPE",
    "FEEDBACK_SIZE",
    "TEST_VALUE",
    "Command",
    "FeedbackFramer",
    "FeedbackPacket",
    "Reply",
    "RobotMode",
    "decode_feedback",
    "encode_feedback",
    "format_command",
    "format_reply",
    "parse_command",
    "parse_reply",
    "split_commands",
    "split_replies",
]

#: Size of one real-time feedback packet [bytes].
FEEDBACK_SIZE = 1440
#: Value of the ``TestValue`` field (bytes 48-55) in every genuine packet.
TEST_VALUE = 0x0123456789ABCDEF
_TEST_BYTES = TEST_VALUE.to_bytes(8, "little")
_LEN_BYTES = FEEDBACK_SIZE.to_bytes(2, "little")

# (name, numpy format, byte offset) of the fields telerig reads; the rest is reserved or unused.
_FIELDS: tuple[tuple[str, str, int], ...] = (
    ("len", "<u2", 0),
    ("digital_inputs", "<u8", 8),
    ("digital_outputs", "<u8", 16),
    ("robot_mode", "<u8", 24),
    ("timestamp_ms", "<u8", 32),
    ("test_value", "<u8", 48),
    ("speed_scaling", "<f8", 64),
    ("q_target", "(6,)<f8", 192),
    ("qd_target", "(6,)<f8", 240),
    ("qdd_target", "(6,)<f8", 288),
    ("i_target", "(6,)<f8", 336),
    ("m_target", "(6,)<f8", 384),
    ("q_actual", "(6,)<f8", 432),
    ("qd_actual", "(6,)<f8", 480),
    ("i_actual", "(6,)<f8", 528),
    ("actual_tcp_force", "(6,)<f8", 576),
    ("tool_vector_actual", "(6,)<f8", 624),
    ("tcp_speed_actual", "(6,)<f8", 672),
    ("tool_vector_target", "(6,)<f8", 768),
    ("motor_temperatures", "(6,)<f8", 864),
    ("velocity_ratio", "u1", 1016),
    ("brake_status", "u1", 1025),
    ("enable_status", "u1", 1026),
    ("running_status", "u1", 1028),
    ("error_status", "u1", 1029),
    ("m_actual", "(6,)<f8", 1120),
)

#: NumPy structured dtype of one feedback packet (only the fields telerig uses are named).
FEEDBACK_DTYPE = np.dtype(
    {
        "names": [f[0] for f in _FIELDS],
        "formats": [f[1] for f in _FIELDS],
        "offsets": [f[2] for f in _FIELDS],
        "itemsize": FEEDBACK_SIZE,
    }
)


class RobotMode(IntEnum):
    """``RobotMode`` values reported by ``RobotMode()`` and the feedback packet."""

    INIT = 1
    BRAKE_OPEN = 2
    DISABLED = 4
    ENABLE = 5
    BACKDRIVE = 6
    RUNNING = 7
    RECORDING = 8
    ERROR = 9
    PAUSE = 10
    JOG = 11


# -- text commands ------------------------------------------------------------------------------


def _fmt(value: float | int | str | Sequence[float]) -> str:
    if isinstance(value, str):
        if any(c in value for c in "(),;"):
            raise ValueError(f"command argument {value!r} must not contain ( ) , or ;")
        return value
    if isinstance(value, bool):
        return str(int(value))
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f"command argument must be finite, got {value}")
        return f"{value:.6f}"
    return "{" + ",".join(_fmt(float(v)) for v in value) + "}"


def format_command(
    name: str, *args: float | int | str | Sequence[float], **kwargs: float | int | str | Sequence[float]
) -> str:
    """``Name(a1,a2,key=value)``: floats with 6 decimals, sequences as ``{v1,...}`` (V4 style).

    Raises:
        ValueError: a name that is not an identifier, a non-finite number, or a string with
            protocol punctuation.
    """
    if not name.isidentifier():
        raise ValueError(f"command name must be an identifier, got {name!r}")
    parts = [_fmt(a) for a in args] + [f"{k}={_fmt(v)}" for k, v in kwargs.items()]
    return f"{name}({','.join(parts)})"


@dataclass(frozen=True, slots=True)
class Command:
    """A parsed text command: ``name``, positional ``args`` and ``key=value`` ``kwargs`` (raw strings)."""

    name: str
    args: tuple[str, ...]
    kwargs: Mapping[str, str]
    text: str


def _split_top(body: str) -> list[str]:
    parts, depth, start = [], 0, 0
    for i, c in enumerate(body):
        if c in "{[":
            depth += 1
        elif c in "}]":
            depth -= 1
            if depth < 0:
                raise WireError(f"unbalanced braces in {body!r}")
        elif c == "," and depth == 0:
            parts.append(body[start:i].strip())
            start = i + 1
    if depth:
        raise WireError(f"unbalanced braces in {body!r}")
    tail = body[start:].strip()
    if tail or parts:
        parts.append(tail)
    return parts


_COMMAND = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_]*)\((.*)\)\s*$", re.S)


def parse_command(text: str) -> Command:
    """Parse ``Name(args)``; commands are case-insensitive, so callers compare ``name.lower()``.

    Raises:
        WireError: not of the form ``Name(...)`` or with unbalanced braces.
    """
    m = _COMMAND.match(text)
    if m is None:
        raise WireError(f"not a Dobot command: {text[:80]!r}")
    args: list[str] = []
    kwargs: dict[str, str] = {}
    for part in _split_top(m.group(2)):
        key, sep, value = part.partition("=")
        if sep and key.strip().isidentifier() and not part.startswith("{"):
            kwargs[key.strip()] = value.strip()
        else:
            args.append(part)
    return Command(m.group(1), tuple(args), kwargs, text.strip())


def split_commands(buffer: str) -> tuple[list[str], str]:
    """Split a received stream into complete commands (each ends at its top-level ``)``) and the rest."""
    out: list[str] = []
    depth, start = 0, 0
    for i, c in enumerate(buffer):
        if c == "(":
            depth += 1
        elif c == ")":
            depth -= 1
            if depth <= 0:
                out.append(buffer[start : i + 1].strip())
                start, depth = i + 1, 0
    return [c for c in out if c], buffer[start:]


# -- text replies --------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Reply:
    """A controller reply ``ErrorID,{values},Command;``.

    Attributes:
        error_id: 0 when the command was accepted; negative codes per Dobot's error table
            (-10000 unknown command, -20000 wrong parameter count, -3000n/-4000n bad type/range).
        values: Return values as raw strings (``{}`` gives an empty tuple).
        command: The echoed command text.
    """

    error_id: int
    values: tuple[str, ...]
    command: str

    @property
    def ok(self) -> bool:
        """Whether ``error_id`` is 0."""
        return self.error_id == 0

    def floats(self) -> FloatArray:
        """The return values as float64. Shape (len(values),).

        Raises:
            WireError: a value is not a finite number.
        """
        try:
            arr = np.array([float(v) for v in self.values], dtype=np.float64)
        except ValueError:
            raise WireError(f"reply values are not numbers: {self.values!r}") from None
        if not np.all(np.isfinite(arr)):
            raise WireError(f"reply values are not finite: {self.values!r}")
        return arr


def parse_reply(text: str) -> Reply:
    """Parse one reply (with or without its trailing ``;``).

    Raises:
        WireError: the text is not ``int,{...},Command(...)``.
    """
    s = text.strip().removesuffix(";")
    head, sep, rest = s.partition(",")
    try:
        error_id = int(head)
    except ValueError:
        raise WireError(f"reply does not start with an error id: {text[:80]!r}") from None
    if not sep or not rest.startswith("{"):
        raise WireError(f"reply has no {{values}} block: {text[:80]!r}")
    depth, end = 0, -1
    for i, c in enumerate(rest):
        depth += c in "{["
        depth -= c in "}]"
        if depth == 0:
            end = i
            break
    if end < 0:
        raise WireError(f"reply values are not closed: {text[:80]!r}")
    body, after = rest[1:end], rest[end + 1 :]
    if not after.startswith(","):
        raise WireError(f"reply has no command echo: {text[:80]!r}")
    return Reply(error_id, tuple(_split_top(body)), after[1:].strip())


def format_reply(error_id: int, values: Sequence[float | int | str], command: str) -> str:
    """``ErrorID,{v1,...},Command;`` as the controller sends it (floats with 6 decimals)."""
    vals = ",".join(_fmt(v) if not isinstance(v, str) else v for v in values)
    return f"{error_id},{{{vals}}},{command};"


def split_replies(buffer: str) -> tuple[list[str], str]:
    """Split a received stream into complete replies (each ends with ``;``) and the rest."""
    *done, rest = buffer.split(";")
    return [d.strip() + ";" for d in done if d.strip()], rest


# -- binary feedback -----------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class FeedbackPacket:
    """The fields of one real-time feedback packet telerig uses, in wire units.

    Attributes:
        robot_mode: ``RobotMode`` value (int; unknown modes are kept as is).
        timestamp_ms: Controller clock [ms].
        q_target: Target joint positions [deg]. Shape (6,).
        q_actual: Measured joint positions [deg]. Shape (6,).
        qd_actual: Measured joint velocities [deg/s]. Shape (6,).
        m_actual: Measured joint torques [N m]. Shape (6,).
        tool_vector_actual: Tool pose (x, y, z [mm], rx, ry, rz [deg]). Shape (6,).
        speed_scaling: Speed scaling of the trajectory limiter.
        enable_status: 1 when the robot is enabled.
        error_status: 1 when the robot is in alarm.
        digital_inputs: Controller digital inputs, bit i = DI(i+1).
        digital_outputs: Controller digital outputs, bit i = DO(i+1).
    """

    robot_mode: int
    timestamp_ms: int
    q_target: FloatArray
    q_actual: FloatArray
    qd_actual: FloatArray
    m_actual: FloatArray
    tool_vector_actual: FloatArray
    speed_scaling: float
    enable_status: int
    error_status: int
    digital_inputs: int
    digital_outputs: int


def decode_feedback(data: bytes) -> FeedbackPacket:
    """Decode one 1440-byte packet.

    Raises:
        WireError: wrong size, length field or test value, or non-finite joint values.
    """
    if len(data) != FEEDBACK_SIZE:
        raise WireError(f"feedback packet must be {FEEDBACK_SIZE} bytes, got {len(data)}")
    rec = np.frombuffer(data, dtype=FEEDBACK_DTYPE, count=1)[0]
    if int(rec["len"]) != FEEDBACK_SIZE:
        raise WireError(f"feedback length field is {int(rec['len'])}, expected {FEEDBACK_SIZE}")
    if int(rec["test_value"]) != TEST_VALUE:
        raise WireError(f"feedback test value is {int(rec['test_value']):#x}, expected {TEST_VALUE:#x}")

    def vec(name: str) -> FloatArray:
        arr = np.array(rec[name], dtype=np.float64)
        arr.flags.writeable = False
        return arr

    q, qd = vec("q_actual"), vec("qd_actual")
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(qd))):
        raise WireError("feedback joint positions or velocities are not finite")
    return FeedbackPacket(
        robot_mode=int(rec["robot_mode"]),
        timestamp_ms=int(rec["timestamp_ms"]),
        q_target=vec("q_target"),
        q_actual=q,
        qd_actual=qd,
        m_actual=vec("m_actual"),
        tool_vector_actual=vec("tool_vector_actual"),
        speed_scaling=float(rec["speed_scaling"]),
        enable_status=int(rec["enable_status"]),
        error_status=int(rec["error_status"]),
        digital_inputs=int(rec["digital_inputs"]),
        digital_outputs=int(rec["digital_outputs"]),
    )


def encode_feedback(
    *,
    robot_mode: int,
    timestamp_ms: int,
    q_actual: Sequence[float] | FloatArray,
    qd_actual: Sequence[float] | FloatArray = (0.0,) * 6,
    q_target: Sequence[float] | FloatArray | None = None,
    m_actual: Sequence[float] | FloatArray = (0.0,) * 6,
    speed_scaling: float = 1.0,
    velocity_ratio: int = 100,
    digital_outputs: int = 0,
) -> bytes:
    """Build one 1440-byte packet (what the controller sends); joint values in [deg], [deg/s], [N m]."""
    rec = np.zeros(1, dtype=FEEDBACK_DTYPE)
    rec["len"] = FEEDBACK_SIZE
    rec["test_value"] = TEST_VALUE
    rec["robot_mode"] = robot_mode
    rec["timestamp_ms"] = timestamp_ms
    rec["q_actual"] = q_actual
    rec["qd_actual"] = qd_actual
    rec["q_target"] = q_actual if q_target is None else q_target
    rec["m_actual"] = m_actual
    rec["speed_scaling"] = speed_scaling
    rec["velocity_ratio"] = velocity_ratio
    rec["digital_outputs"] = digital_outputs
    enabled = robot_mode in (RobotMode.ENABLE, RobotMode.RUNNING, RobotMode.JOG, RobotMode.PAUSE)
    rec["enable_status"] = int(enabled)
    rec["running_status"] = int(robot_mode == RobotMode.RUNNING)
    rec["error_status"] = int(robot_mode == RobotMode.ERROR)
    return rec.tobytes()


class FeedbackFramer:
    """Cuts a TCP byte stream into feedback packets, re-synchronising after lost or garbage bytes.

    A packet starts where the length field reads 1440 and bytes 48-55 hold the test value.
    Bytes that do not start a packet are skipped (one ``resyncs`` per skipped run). A packet
    with another header inside it (the sender cut it short) and a well-framed packet that fails
    to decode count in ``malformed`` and are dropped. A packet is decoded as soon as its 1440
    bytes are in, so a cut is only seen when the next header is already buffered; TCP never
    drops bytes, so this guards against a misbehaving sender, not the network.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self.packets = 0
        self.malformed = 0
        self.resyncs = 0
        self.skipped_bytes = 0

    def feed(self, data: bytes) -> Iterator[FeedbackPacket]:
        """Add received bytes; yield every complete, valid packet in order."""
        buf = self._buf
        buf += data
        while len(buf) >= FEEDBACK_SIZE:
            if buf[0:2] != _LEN_BYTES or buf[48:56] != _TEST_BYTES:
                start = self._find_start(buf)
                # No start found: only the last 55 bytes may still begin one whose test value
                # has not fully arrived.
                skip = start if start >= 0 else len(buf) - 55
                self.resyncs += 1
                self.skipped_bytes += skip
                del buf[:skip]
                continue
            inner = self._find_start(buf, limit=FEEDBACK_SIZE + 55)
            if 0 < inner < FEEDBACK_SIZE:
                # A packet starts inside this one: the sender cut this one short.
                self.malformed += 1
                self.skipped_bytes += inner
                del buf[:inner]
                continue
            chunk = bytes(buf[:FEEDBACK_SIZE])
            del buf[:FEEDBACK_SIZE]
            try:
                packet = decode_feedback(chunk)
            except WireError:
                self.malformed += 1
                continue
            self.packets += 1
            yield packet

    @staticmethod
    def _find_start(buf: bytearray, limit: int | None = None) -> int:
        """Offset > 0 of the first packet header in ``buf[:limit]``, or -1."""
        pos = buf.find(_TEST_BYTES, 49, limit)
        while pos >= 0:
            start = pos - 48
            if buf[start : start + 2] == _LEN_BYTES:
                return start
            pos = buf.find(_TEST_BYTES, pos + 1, limit)
        return -1
