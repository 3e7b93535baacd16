"""Universal Robots RTDE wire format (protocol 2): framing, messages, recipes and type codes; no sockets."""

from __future__ import annotations

import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any

from telerig.errors import WireError

__all__ = [
    "DEFAULT_PORT",
    "HEADER",
    "INPUT_TYPES",
    "IN_USE",
    "NOT_FOUND",
    "OUTPUT_TYPES",
    "PROTOCOL_VERSION",
    "TYPE_FORMATS",
    "Accepted",
    "Command",
    "ControllerVersion",
    "Frame",
    "FrameReader",
    "InputSetup",
    "MessageLevel",
    "OutputSetup",
    "ProtocolVersionRequest",
    "Recipe",
    "RobotMode",
    "RuntimeState",
    "SafetyMode",
    "SetupReply",
    "TextMessage",
    "Value",
    "pack",
    "recipe_id_of",
]

#: The protocol version telerig speaks (PolyScope >= 3.5 / 5.0); version 1 has no recipe ids.
PROTOCOL_VERSION = 2
#: TCP port of the RTDE server on the controller.
DEFAULT_PORT = 30004
#: Package header: total size in bytes including the header (uint16), package type (uint8). Big-endian.
HEADER = struct.Struct(">HB")

#: Reply type of a setup request for a variable the controller does not know.
NOT_FOUND = "NOT_FOUND"
#: Reply type of an input setup request for a variable another client (or a fieldbus) already writes.
IN_USE = "IN_USE"

#: RTDE type name -> :mod:`struct` format (big-endian, no padding). BOOL is one byte 0/1.
TYPE_FORMATS: Mapping[str, str] = {
    "BOOL": "?",
    "UINT8": "B",
    "UINT32": "I",
    "UINT64": "Q",
    "INT32": "i",
    "DOUBLE": "d",
    "VECTOR3D": "3d",
    "VECTOR6D": "6d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
}

#: One decoded recipe field: a scalar, or a tuple of 3 or 6 for the VECTOR types.
Value = bool | int | float | tuple[float, ...] | tuple[int, ...]


class Command(IntEnum):
    """RTDE package types (the ASCII letter of each)."""

    REQUEST_PROTOCOL_VERSION = ord("V")
    GET_URCONTROL_VERSION = ord("v")
    TEXT_MESSAGE = ord("M")
    DATA_PACKAGE = ord("U")
    CONTROL_PACKAGE_SETUP_OUTPUTS = ord("O")
    CONTROL_PACKAGE_SETUP_INPUTS = ord("I")
    CONTROL_PACKAGE_START = ord("S")
    CONTROL_PACKAGE_PAUSE = ord("P")


class RobotMode(IntEnum):
    """``robot_mode`` output values."""

    NO_CONTROLLER = -1
    DISCONNECTED = 0
    CONFIRM_SAFETY = 1
    BOOTING = 2
    POWER_OFF = 3
    POWER_ON = 4
    IDLE = 5
    BACKDRIVE = 6
    RUNNING = 7
    UPDATING_FIRMWARE = 8


class SafetyMode(IntEnum):
    """``safety_mode`` output values."""

    NORMAL = 1
    REDUCED = 2
    PROTECTIVE_STOP = 3
    RECOVERY = 4
    SAFEGUARD_STOP = 5
    SYSTEM_EMERGENCY_STOP = 6
    ROBOT_EMERGENCY_STOP = 7
    VIOLATION = 8
    FAULT = 9
    VALIDATE_JOINT_ID = 10
    UNDEFINED_SAFETY_MODE = 11
    AUTOMATIC_MODE_SAFEGUARD_STOP = 12
    SYSTEM_THREE_POSITION_ENABLING_STOP = 13


class RuntimeState(IntEnum):
    """``runtime_state`` output values (program state)."""

    STOPPING = 0
    STOPPED = 1
    PLAYING = 2
    PAUSING = 3
    PAUSED = 4
    RESUMING = 5


class MessageLevel(IntEnum):
    """Severity of an RTDE text message."""

    EXCEPTION = 0
    ERROR = 1
    WARNING = 2
    INFO = 3


def _registers(prefix: str, type_name: str, first: int = 0, last: int = 47) -> dict[str, str]:
    return {f"{prefix}{i}": type_name for i in range(first, last + 1)}


#: Controller -> client variables (the RTDE guide's output table, the part telerig and the fake know).
OUTPUT_TYPES: Mapping[str, str] = {
    "timestamp": "DOUBLE",
    "target_q": "VECTOR6D",
    "target_qd": "VECTOR6D",
    "target_qdd": "VECTOR6D",
    "target_current": "VECTOR6D",
    "target_moment": "VECTOR6D",
    "actual_q": "VECTOR6D",
    "actual_qd": "VECTOR6D",
    "actual_current": "VECTOR6D",
    "joint_control_output": "VECTOR6D",
    "actual_TCP_pose": "VECTOR6D",
    "actual_TCP_speed": "VECTOR6D",
    "actual_TCP_force": "VECTOR6D",
    "target_TCP_pose": "VECTOR6D",
    "target_TCP_speed": "VECTOR6D",
    "actual_digital_input_bits": "UINT64",
    "joint_temperatures": "VECTOR6D",
    "actual_execution_time": "DOUBLE",
    "robot_mode": "INT32",
    "joint_mode": "VECTOR6INT32",
    "safety_mode": "INT32",
    "safety_status": "INT32",
    "actual_tool_accelerometer": "VECTOR3D",
    "speed_scaling": "DOUBLE",
    "target_speed_fraction": "DOUBLE",
    "actual_momentum": "DOUBLE",
    "actual_main_voltage": "DOUBLE",
    "actual_robot_voltage": "DOUBLE",
    "actual_robot_current": "DOUBLE",
    "actual_joint_voltage": "VECTOR6D",
    "actual_digital_output_bits": "UINT64",
    "runtime_state": "UINT32",
    "elbow_position": "VECTOR3D",
    "elbow_velocity": "VECTOR3D",
    "robot_status_bits": "UINT32",
    "safety_status_bits": "UINT32",
    "analog_io_types": "UINT32",
    "standard_analog_input0": "DOUBLE",
    "standard_analog_input1": "DOUBLE",
    "standard_analog_output0": "DOUBLE",
    "standard_analog_output1": "DOUBLE",
    "io_current": "DOUBLE",
    "euromap67_input_bits": "UINT32",
    "euromap67_output_bits": "UINT32",
    "euromap67_24V_voltage": "DOUBLE",
    "euromap67_24V_current": "DOUBLE",
    "tool_mode": "UINT32",
    "tool_analog_input_types": "UINT32",
    "tool_analog_input0": "DOUBLE",
    "tool_analog_input1": "DOUBLE",
    "tool_output_voltage": "INT32",
    "tool_output_current": "DOUBLE",
    "tool_temperature": "DOUBLE",
    "tcp_force_scalar": "DOUBLE",
    "tool_output_mode": "UINT8",
    "tool_digital_output0_mode": "UINT8",
    "tool_digital_output1_mode": "UINT8",
    "payload": "DOUBLE",
    "payload_cog": "VECTOR3D",
    "payload_inertia": "VECTOR6D",
    "script_control_line": "UINT32",
    "ft_raw_wrench": "VECTOR6D",
    "joint_position_deviation_ratio": "VECTOR6D",
    "collision_detection_ratio": "DOUBLE",
    "time_scale_source": "UINT32",
    "output_bit_registers0_to_31": "UINT32",
    "output_bit_registers32_to_63": "UINT32",
    **_registers("output_bit_register_", "BOOL", 64, 127),
    **_registers("output_int_register_", "INT32"),
    **_registers("output_double_register_", "DOUBLE"),
    # Input registers can be read back as outputs.
    "input_bit_registers0_to_31": "UINT32",
    "input_bit_registers32_to_63": "UINT32",
    **_registers("input_bit_register_", "BOOL", 64, 127),
    **_registers("input_int_register_", "INT32"),
    **_registers("input_double_register_", "DOUBLE"),
}

#: Client -> controller variables (registers 0-23 may be taken by a fieldbus; 24-47 are for RTDE clients).
INPUT_TYPES: Mapping[str, str] = {
    "speed_slider_mask": "UINT32",
    "speed_slider_fraction": "DOUBLE",
    "standard_digital_output_mask": "UINT8",
    "standard_digital_output": "UINT8",
    "configurable_digital_output_mask": "UINT8",
    "configurable_digital_output": "UINT8",
    "tool_digital_output_mask": "UINT8",
    "tool_digital_output": "UINT8",
    "standard_analog_output_mask": "UINT8",
    "standard_analog_output_type": "UINT8",
    "standard_analog_output_0": "DOUBLE",
    "standard_analog_output_1": "DOUBLE",
    "external_force_torque": "VECTOR6D",
    "ft_rtde_input_enable": "BOOL",
    "input_bit_registers0_to_31": "UINT32",
    "input_bit_registers32_to_63": "UINT32",
    **_registers("input_bit_register_", "BOOL", 64, 127),
    **_registers("input_int_register_", "INT32"),
    **_registers("input_double_register_", "DOUBLE"),
}


def pack(command: int, payload: bytes = b"") -> bytes:
    """Frame ``payload`` as one RTDE package of type ``command``.

    Raises:
        WireError: the package would exceed 65535 bytes.
    """
    size = HEADER.size + len(payload)
    if size > 0xFFFF:
        raise WireError(f"RTDE package of {size} bytes exceeds 65535; send fewer variables")
    return HEADER.pack(size, command) + payload


@dataclass(frozen=True, slots=True)
class Frame:
    """One RTDE package: its type byte and the payload after the 3-byte header."""

    command: int
    payload: bytes


@dataclass(slots=True)
class FrameReader:
    """Splits a TCP byte stream into :class:`Frame` s; feed it whatever ``recv`` returned."""

    _buffer: bytearray = field(default_factory=bytearray)

    def feed(self, data: bytes) -> list[Frame]:
        """Append ``data`` and return every complete package, in order.

        Raises:
            WireError: a header declares a size below 3 bytes; the stream cannot be re-synchronised.
        """
        buf = self._buffer
        buf += data
        frames: list[Frame] = []
        start = 0
        while len(buf) - start >= HEADER.size:
            size, command = HEADER.unpack_from(buf, start)
            if size < HEADER.size:
                del buf[:]
                raise WireError(f"RTDE header declares {size} bytes (< 3); the stream is corrupt, reconnect")
            if len(buf) - start < size:
                break
            frames.append(Frame(command, bytes(buf[start + HEADER.size : start + size])))
            start += size
        del buf[:start]
        return frames

    @property
    def pending(self) -> int:
        """Bytes received but not yet part of a complete package."""
        return len(self._buffer)


def _unpack(fmt: struct.Struct, payload: bytes, what: str) -> tuple[Any, ...]:
    if len(payload) != fmt.size:
        raise WireError(f"{what}: expected {fmt.size} payload bytes, got {len(payload)}")
    return fmt.unpack(payload)


def _ascii(data: bytes, what: str) -> str:
    try:
        return data.decode("ascii")
    except UnicodeDecodeError:
        raise WireError(f"{what}: text is not ASCII") from None


_U8 = struct.Struct(">B")
_U16 = struct.Struct(">H")
_F64 = struct.Struct(">d")
_VERSION = struct.Struct(">IIII")


@dataclass(frozen=True, slots=True)
class ProtocolVersionRequest:
    """Client asks to speak ``version`` (``V``, uint16). The controller answers with :class:`Accepted`."""

    version: int = PROTOCOL_VERSION

    def encode(self) -> bytes:
        return pack(Command.REQUEST_PROTOCOL_VERSION, _U16.pack(self.version))

    @classmethod
    def decode(cls, payload: bytes) -> ProtocolVersionRequest:
        (version,) = _unpack(_U16, payload, "protocol version request")
        return cls(int(version))


@dataclass(frozen=True, slots=True)
class Accepted:
    """Controller's yes/no answer (uint8) to ``V``, ``S`` and ``P``; ``command`` says which."""

    command: Command
    accepted: bool

    def encode(self) -> bytes:
        return pack(self.command, _U8.pack(int(self.accepted)))

    @classmethod
    def decode(cls, command: Command, payload: bytes) -> Accepted:
        (value,) = _unpack(_U8, payload, f"{command.name} reply")
        return cls(command, bool(value))


@dataclass(frozen=True, slots=True)
class ControllerVersion:
    """URControl version (``v`` reply): major, minor, bugfix, build (uint32 each)."""

    major: int
    minor: int
    bugfix: int
    build: int

    def encode(self) -> bytes:
        return pack(
            Command.GET_URCONTROL_VERSION, _VERSION.pack(self.major, self.minor, self.bugfix, self.build)
        )

    @classmethod
    def decode(cls, payload: bytes) -> ControllerVersion:
        major, minor, bugfix, build = _unpack(_VERSION, payload, "controller version")
        return cls(int(major), int(minor), int(bugfix), int(build))

    def __str__(self) -> str:
        return f"{self.major}.{self.minor}.{self.bugfix}.{self.build}"


@dataclass(frozen=True, slots=True)
class TextMessage:
    """``M`` package (protocol 2): message and source as uint8-length-prefixed ASCII, then the level."""

    message: str
    source: str = "telerig"
    level: MessageLevel = MessageLevel.INFO

    def encode(self) -> bytes:
        msg = self.message.encode("ascii", "replace")[:255]
        src = self.source.encode("ascii", "replace")[:255]
        return pack(
            Command.TEXT_MESSAGE, bytes([len(msg)]) + msg + bytes([len(src)]) + src + bytes([self.level])
        )

    @classmethod
    def decode(cls, payload: bytes) -> TextMessage:
        try:
            n = payload[0]
            message = payload[1 : 1 + n]
            m = payload[1 + n]
            source = payload[2 + n : 2 + n + m]
            level = payload[2 + n + m]
        except IndexError:
            raise WireError(f"text message: truncated ({len(payload)} payload bytes)") from None
        if len(payload) != 3 + n + m:
            raise WireError(f"text message: {len(payload) - 3 - n - m} trailing bytes")
        if level > MessageLevel.INFO:
            raise WireError(f"text message: unknown level {level}")
        return cls(_ascii(message, "text message"), _ascii(source, "text message"), MessageLevel(level))


@dataclass(frozen=True, slots=True)
class OutputSetup:
    """``O`` request: output ``frequency`` [Hz] (double) and comma-separated variable names."""

    frequency: float
    names: tuple[str, ...]

    def encode(self) -> bytes:
        return pack(Command.CONTROL_PACKAGE_SETUP_OUTPUTS, _F64.pack(self.frequency) + _names(self.names))

    @classmethod
    def decode(cls, payload: bytes) -> OutputSetup:
        if len(payload) < _F64.size:
            raise WireError(f"output setup: truncated ({len(payload)} payload bytes)")
        (frequency,) = _F64.unpack_from(payload)
        return cls(float(frequency), _split(payload[_F64.size :], "output setup"))


@dataclass(frozen=True, slots=True)
class InputSetup:
    """``I`` request: comma-separated input variable names."""

    names: tuple[str, ...]

    def encode(self) -> bytes:
        return pack(Command.CONTROL_PACKAGE_SETUP_INPUTS, _names(self.names))

    @classmethod
    def decode(cls, payload: bytes) -> InputSetup:
        return cls(_split(payload, "input setup"))


@dataclass(frozen=True, slots=True)
class SetupReply:
    """Reply to ``O`` or ``I`` (``command``): recipe id (uint8) and one type name per requested variable.

    A type of :data:`NOT_FOUND` or :data:`IN_USE` means the setup failed for that variable.
    """

    command: Command
    recipe_id: int
    types: tuple[str, ...]

    def encode(self) -> bytes:
        return pack(self.command, _U8.pack(self.recipe_id) + _names(self.types))

    @classmethod
    def decode(cls, command: Command, payload: bytes) -> SetupReply:
        if not payload:
            raise WireError(f"{command.name} reply: empty payload")
        return cls(command, payload[0], _split(payload[1:], f"{command.name} reply"))

    def problems(self, names: Sequence[str]) -> list[str]:
        """``"name (NOT_FOUND)"`` for every variable of ``names`` the controller refused."""
        if len(self.types) != len(names):
            return [f"{len(names)} variables requested but {len(self.types)} types returned"]
        return [f"{n} ({t})" for n, t in zip(names, self.types, strict=True) if t not in TYPE_FORMATS]


def _names(names: Sequence[str]) -> bytes:
    return ",".join(names).encode("ascii")


def _split(data: bytes, what: str) -> tuple[str, ...]:
    text = _ascii(data, what)
    # One trailing comma ends the list: ur_rtde sends "timestamp,actual_q," and controllers accept it.
    if text.endswith(","):
        text = text[:-1]
    return tuple(text.split(",")) if text else ()


@dataclass(frozen=True, slots=True)
class Recipe:
    """A configured recipe: its id and the variables (with types) every ``U`` package carries, in order."""

    recipe_id: int
    names: tuple[str, ...]
    types: tuple[str, ...]
    _struct: struct.Struct = field(init=False, repr=False, compare=False)
    _widths: tuple[int, ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not 1 <= self.recipe_id <= 255:
            raise WireError(f"recipe id must be in 1..255, got {self.recipe_id}")
        if len(self.names) != len(self.types) or not self.names:
            raise WireError(
                f"recipe needs one type per variable, got {len(self.names)} and {len(self.types)}"
            )
        fmts = []
        for name, type_name in zip(self.names, self.types, strict=True):
            fmt = TYPE_FORMATS.get(type_name)
            if fmt is None:
                raise WireError(f"variable {name!r} has type {type_name!r}. Valid: {', '.join(TYPE_FORMATS)}")
            fmts.append(fmt)
        object.__setattr__(self, "_struct", struct.Struct(">B" + "".join(fmts)))
        object.__setattr__(self, "_widths", tuple(int(f[0]) if f[0].isdigit() else 0 for f in fmts))

    @classmethod
    def from_reply(cls, names: Sequence[str], reply: SetupReply) -> Recipe:
        """Recipe of a successful setup reply for ``names``.

        Raises:
            WireError: the controller refused some variables; the message lists them.
        """
        bad = reply.problems(names)
        if bad:
            raise WireError(f"RTDE {reply.command.name} refused: {', '.join(bad)}")
        return cls(reply.recipe_id, tuple(names), reply.types)

    @property
    def size(self) -> int:
        """Payload bytes of one ``U`` package of this recipe (recipe id included)."""
        return self._struct.size

    def encode(self, values: Mapping[str, Value]) -> bytes:
        """One ``U`` package carrying ``values`` (every recipe variable, any extra ignored).

        Raises:
            WireError: a variable is missing or a value does not fit its type.
        """
        flat: list[object] = [self.recipe_id]
        try:
            for name, width in zip(self.names, self._widths, strict=True):
                value = values[name]
                if width:
                    seq = tuple(value)  # type: ignore[arg-type]
                    if len(seq) != width:
                        raise WireError(f"{name}: expected {width} values, got {len(seq)}")
                    flat.extend(seq)
                else:
                    flat.append(value)
            return pack(Command.DATA_PACKAGE, self._struct.pack(*flat))
        except KeyError as exc:
            raise WireError(f"recipe {self.recipe_id}: no value for {exc.args[0]!r}") from None
        except (struct.error, TypeError) as exc:
            raise WireError(f"recipe {self.recipe_id}: {exc}") from None

    def decode(self, payload: bytes) -> dict[str, Value]:
        """Values of one ``U`` payload of this recipe, by variable name (vectors as tuples).

        Raises:
            WireError: the payload has the wrong size or another recipe id.
        """
        if len(payload) != self._struct.size:
            raise WireError(
                f"data package for recipe {self.recipe_id}: "
                f"expected {self._struct.size} bytes, got {len(payload)}"
            )
        flat = self._struct.unpack(payload)
        if flat[0] != self.recipe_id:
            raise WireError(f"data package has recipe id {flat[0]}, expected {self.recipe_id}")
        out: dict[str, Value] = {}
        i = 1
        for name, width in zip(self.names, self._widths, strict=True):
            if width:
                out[name] = tuple(flat[i : i + width])
                i += width
            else:
                out[name] = flat[i]
                i += 1
        return out


def recipe_id_of(payload: bytes) -> int:
    """The recipe id of a ``U`` payload (its first byte).

    Raises:
        WireError: the payload is empty.
    """
    if not payload:
        raise WireError("data package: empty payload")
    return payload[0]
