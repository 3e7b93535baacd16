"""OptiTrack NatNet 3.x/4.x packets (little-endian UDP): parse, encode, and normalize into IR samples."""

from __future__ import annotations

import math
import struct
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from telerig.devices.mocap._axes import MountTransform
from telerig.errors import WireError
from telerig.ir.frames import cross3, quat_multiply
from telerig.ir.types import BodySkeleton, FloatArray, Pose, Sample, Stamp

__all__ = [
    "FUZZ_TARGET",
    "MULTICAST_GROUP",
    "NAT_CONNECT",
    "NAT_DISCONNECT",
    "NAT_FRAMEOFDATA",
    "NAT_KEEPALIVE",
    "NAT_MESSAGESTRING",
    "NAT_MODELDEF",
    "NAT_REQUEST",
    "NAT_REQUEST_FRAMEOFDATA",
    "NAT_REQUEST_MODELDEF",
    "NAT_RESPONSE",
    "NAT_SERVERINFO",
    "NAT_UNRECOGNIZED_REQUEST",
    "PORT_COMMAND",
    "PORT_DATA",
    "AnalogData",
    "AssetData",
    "ConnectRequest",
    "FrameNormalizer",
    "LabeledMarker",
    "MarkerSetData",
    "MarkerSetDescription",
    "MocapFrame",
    "ModelDefinitions",
    "NatNetVersion",
    "OtherMessage",
    "RigidBodyData",
    "RigidBodyDescription",
    "ServerInfo",
    "SkeletonData",
    "SkeletonDescription",
    "encode_connect",
    "encode_frame",
    "encode_model_definitions",
    "encode_packet",
    "encode_server_info",
    "parse_frame",
    "parse_message",
    "parse_model_definitions",
    "parse_server_info",
    "split_packet",
]

NAT_CONNECT = 0
NAT_SERVERINFO = 1
NAT_REQUEST = 2
NAT_RESPONSE = 3
NAT_REQUEST_MODELDEF = 4
NAT_MODELDEF = 5
NAT_REQUEST_FRAMEOFDATA = 6
NAT_FRAMEOFDATA = 7
NAT_MESSAGESTRING = 8
NAT_DISCONNECT = 9
NAT_KEEPALIVE = 10
NAT_UNRECOGNIZED_REQUEST = 100

#: Motive's default multicast group, command port and data port.
MULTICAST_GROUP = "239.255.42.99"
PORT_COMMAND = 1510
PORT_DATA = 1511

_MAX_NAME = 256  # bytes, sSender.szName and NatNet's MAX_NAMELENGTH
_HEADER = struct.Struct("<HH")  # message id, payload bytes
_I32 = struct.Struct("<i")
_U32 = struct.Struct("<I")
_F32 = struct.Struct("<f")
_V3 = struct.Struct("<3f")
_Q4 = struct.Struct("<4f")
_RB = struct.Struct("<i3f4ffh")  # id, x y z, qx qy qz qw, mean marker error, params: 38 bytes
_MARKER = struct.Struct("<i3ffhf")  # id, x y z, size, params, residual: 26 bytes
_SUFFIX3 = struct.Struct("<IIdQQQ")  # timecode, subframe, timestamp, mid-exposure, received, transmit
_PRECISION = struct.Struct("<II")
_PARAMS = struct.Struct("<h")
_SENDER = struct.Struct("<256s4B4B")
_SERVER_EXT = struct.Struct("<QH?4B")  # clock frequency, data port, multicast, group address

Vec3 = tuple[float, float, float]
Quat4 = tuple[float, float, float, float]


@dataclass(frozen=True, slots=True, order=True)
class NatNetVersion:
    """NatNet bitstream version; the layout of frames and model definitions depends on it."""

    major: int
    minor: int

    @classmethod
    def parse(cls, text: str) -> NatNetVersion:
        """``"4.1"`` -> ``NatNetVersion(4, 1)``; WireError unless a supported version (3.x or 4.x)."""
        try:
            major, minor = (int(p) for p in text.strip().split(".")[:2])
        except ValueError:
            raise WireError(f"NatNet version must look like '4.1'; got {text!r}") from None
        return cls(major, minor).checked()

    def checked(self) -> NatNetVersion:
        """Self if supported; WireError naming the supported range otherwise."""
        if self.major not in (3, 4) or not 0 <= self.minor <= 255:
            raise WireError(f"NatNet version {self} is not supported; valid: 3.0 to 4.x (Motive 2.x and 3.x)")
        return self

    @property
    def byte_counts(self) -> bool:
        """Whether each frame section and model definition carries its size in bytes (4.1+)."""
        return (self.major, self.minor) >= (4, 1)

    def __str__(self) -> str:
        return f"{self.major}.{self.minor}"


@dataclass(frozen=True, slots=True)
class RigidBodyData:
    """One rigid body (or skeleton bone) in a frame, as sent: Motive world frame, metres.

    Attributes:
        id: Streaming id (for a skeleton bone: skeleton id << 16 | bone id).
        position: x, y, z [m], Motive world (Y up by default).
        orientation: qx, qy, qz, qw as on the wire (scalar last).
        mean_error: Mean marker residual [m].
        params: Bit flags; bit 0 = tracked in this frame.
    """

    id: int
    position: Vec3
    orientation: Quat4
    mean_error: float = 0.0
    params: int = 1

    @property
    def tracking_valid(self) -> bool:
        """Whether Motive tracked the body in this frame."""
        return bool(self.params & 0x01)


@dataclass(frozen=True, slots=True)
class SkeletonData:
    """A skeleton in a frame: its id and one rigid body per bone."""

    id: int
    bones: tuple[RigidBodyData, ...]


@dataclass(frozen=True, slots=True)
class LabeledMarker:
    """A labeled marker: id (model id << 16 | marker id), position [m], size [m], params, residual [m]."""

    id: int
    position: Vec3
    size: float = 0.014
    params: int = 0
    residual: float = 0.0


@dataclass(frozen=True, slots=True)
class MarkerSetData:
    """Named marker set positions [m]."""

    name: str
    positions: tuple[Vec3, ...]


@dataclass(frozen=True, slots=True)
class AnalogData:
    """A force plate or analog device: id and, per channel, the sub-frame samples."""

    id: int
    channels: tuple[tuple[float, ...], ...]


@dataclass(frozen=True, slots=True)
class AssetData:
    """A trained markerset asset (NatNet 4.1+): its rigid bodies and markers."""

    id: int
    rigid_bodies: tuple[RigidBodyData, ...]
    markers: tuple[LabeledMarker, ...]


@dataclass(frozen=True, slots=True)
class MocapFrame:
    """A NAT_FRAMEOFDATA payload.

    Timestamps: ``timestamp`` is seconds since Motive started; ``stamp_*`` are ticks of the
    server's high-resolution clock (frequency in :class:`ServerInfo`), NatNet 3.0+.
    """

    frame_number: int
    marker_sets: tuple[MarkerSetData, ...] = ()
    unlabeled_markers: tuple[Vec3, ...] = ()
    rigid_bodies: tuple[RigidBodyData, ...] = ()
    skeletons: tuple[SkeletonData, ...] = ()
    assets: tuple[AssetData, ...] = ()
    labeled_markers: tuple[LabeledMarker, ...] = ()
    force_plates: tuple[AnalogData, ...] = ()
    devices: tuple[AnalogData, ...] = ()
    timecode: int = 0
    timecode_sub: int = 0
    timestamp: float = 0.0
    stamp_camera_mid_exposure: int = 0
    stamp_data_received: int = 0
    stamp_transmit: int = 0
    precision_timestamp_secs: int = 0
    precision_timestamp_frac_secs: int = 0
    params: int = 0

    @property
    def tracked_models_changed(self) -> bool:
        """Motive's asset list changed: model definitions must be requested again."""
        return bool(self.params & 0x02)


@dataclass(frozen=True, slots=True)
class RigidBodyDescription:
    """A rigid body (or bone) definition: name, id, parent id (-1 or 0: none), offset to parent [m]."""

    name: str
    id: int
    parent_id: int = -1
    offset: Vec3 = (0.0, 0.0, 0.0)
    orientation: Quat4 = (0.0, 0.0, 0.0, 1.0)
    marker_offsets: tuple[Vec3, ...] = ()
    marker_labels: tuple[int, ...] = ()
    marker_names: tuple[str, ...] = ()


@dataclass(frozen=True, slots=True)
class SkeletonDescription:
    """A skeleton definition: name, id and its bones (parents before children in Motive's order)."""

    name: str
    id: int
    bones: tuple[RigidBodyDescription, ...]


@dataclass(frozen=True, slots=True)
class MarkerSetDescription:
    """A marker set definition: name and marker names."""

    name: str
    marker_names: tuple[str, ...]


@dataclass(frozen=True, slots=True)
class ModelDefinitions:
    """A NAT_MODELDEF payload (force plate, device, camera and asset definitions are skipped)."""

    rigid_bodies: tuple[RigidBodyDescription, ...] = ()
    skeletons: tuple[SkeletonDescription, ...] = ()
    marker_sets: tuple[MarkerSetDescription, ...] = ()
    skipped: int = 0


@dataclass(frozen=True, slots=True)
class ServerInfo:
    """A NAT_SERVERINFO payload: application, versions and (NatNet 3+) clock and data channel."""

    app_name: str
    app_version: tuple[int, int, int, int]
    natnet_version: tuple[int, int, int, int]
    high_res_clock_hz: int = 0
    data_port: int = 0
    multicast: bool = False
    multicast_group: str = ""

    @property
    def version(self) -> NatNetVersion:
        """The bitstream version the server streams (WireError if unsupported)."""
        return NatNetVersion(self.natnet_version[0], self.natnet_version[1]).checked()


@dataclass(frozen=True, slots=True)
class ConnectRequest:
    """A NAT_CONNECT payload: client name and the NatNet version it asks for (0.0 = server's)."""

    app_name: str
    natnet_version: tuple[int, int, int, int] = (0, 0, 0, 0)


@dataclass(frozen=True, slots=True)
class OtherMessage:
    """Any other message: id and raw payload (keep-alive, requests, responses, strings)."""

    message_id: int
    payload: bytes


Message = MocapFrame | ModelDefinitions | ServerInfo | ConnectRequest | OtherMessage


# ---------------------------------------------------------------------------------------- parsing


class _Reader:
    __slots__ = ("buf", "end", "pos")

    def __init__(self, buf: memoryview, pos: int = 0, end: int | None = None) -> None:
        self.buf = buf
        self.pos = pos
        self.end = len(buf) if end is None else end

    def take(self, st: struct.Struct) -> tuple[Any, ...]:
        if self.pos + st.size > self.end:
            raise WireError(f"truncated at byte {self.pos}: need {st.size} more bytes, {self.left} left")
        out = st.unpack_from(self.buf, self.pos)
        self.pos += st.size
        return out

    def i32(self) -> int:
        return int(self.take(_I32)[0])

    @property
    def left(self) -> int:
        return self.end - self.pos

    def count(self, item_min: int, what: str) -> int:
        n = self.i32()
        if n < 0 or n * item_min > self.left:
            raise WireError(
                f"{what} count {n} at byte {self.pos - 4} does not fit the {self.left} bytes left"
            )
        return n

    def string(self, what: str) -> str:
        end = bytes(self.buf[self.pos : min(self.end, self.pos + _MAX_NAME)]).find(b"\0")
        if end < 0:
            raise WireError(
                f"{what} at byte {self.pos} is not a NUL-terminated string of < {_MAX_NAME} bytes"
            )
        text = bytes(self.buf[self.pos : self.pos + end]).decode("utf-8", errors="replace")
        self.pos += end + 1
        return text

    def section_size(self, version: NatNetVersion) -> int | None:
        if not version.byte_counts:
            return None
        n = self.i32()
        if n < 0 or n > self.left:
            raise WireError(f"section size {n} at byte {self.pos - 4} exceeds the {self.left} bytes left")
        return n

    def bodies(self, n: int) -> tuple[RigidBodyData, ...]:
        size = n * _RB.size
        if size > self.left:
            raise WireError(f"{n} rigid bodies at byte {self.pos} need {size} bytes, {self.left} left")
        chunk = self.buf[self.pos : self.pos + size]
        self.pos += size
        return tuple(
            RigidBodyData(i, (x, y, z), (qx, qy, qz, qw), err, p)
            for i, x, y, z, qx, qy, qz, qw, err, p in _RB.iter_unpack(chunk)
        )

    def markers(self, n: int) -> tuple[LabeledMarker, ...]:
        size = n * _MARKER.size
        if size > self.left:
            raise WireError(f"{n} markers at byte {self.pos} need {size} bytes, {self.left} left")
        chunk = self.buf[self.pos : self.pos + size]
        self.pos += size
        return tuple(
            LabeledMarker(i, (x, y, z), s, p, r) for i, x, y, z, s, p, r in _MARKER.iter_unpack(chunk)
        )

    def vec3s(self, n: int) -> tuple[Vec3, ...]:
        return tuple(self.take(_V3) for _ in range(n))


def split_packet(data: bytes | bytearray | memoryview) -> tuple[int, memoryview]:
    """Header of one NatNet datagram: (message id, payload view of exactly the declared size)."""
    buf = memoryview(data)
    if len(buf) < _HEADER.size:
        raise WireError(f"NatNet packet of {len(buf)} bytes is shorter than its 4-byte header")
    message_id, size = _HEADER.unpack_from(buf)
    if size > len(buf) - _HEADER.size:
        raise WireError(f"NatNet packet declares {size} payload bytes but carries {len(buf) - _HEADER.size}")
    return int(message_id), buf[_HEADER.size : _HEADER.size + size]


def _analog(r: _Reader, version: NatNetVersion, what: str) -> tuple[AnalogData, ...]:
    n = r.count(8, what)
    size = r.section_size(version)
    start = r.pos
    out = []
    for _ in range(n):
        ident = r.i32()
        channels = []
        for _ in range(r.count(4, f"{what} channel")):
            frames = r.count(4, f"{what} sample")
            channels.append(struct.unpack_from(f"<{frames}f", r.buf, r.pos))
            r.pos += 4 * frames
        out.append(AnalogData(ident, tuple(channels)))
    _check_size(r, start, size, what, strict=False)
    return tuple(out)


def _check_size(r: _Reader, start: int, size: int | None, what: str, *, strict: bool) -> None:
    if size is None or r.pos - start == size:
        return
    if strict:
        raise WireError(f"{what} section declares {size} bytes but its content takes {r.pos - start}")
    r.pos = start + size  # trust the declared size for sections that are not turned into IR


def parse_frame(payload: bytes | memoryview, version: NatNetVersion) -> MocapFrame:
    """Parse a NAT_FRAMEOFDATA payload (after the 4-byte header) in the given bitstream version."""
    r = _Reader(memoryview(payload))
    try:
        frame_number = r.i32()
        # Marker sets
        n = r.count(5, "marker set")
        size = r.section_size(version)
        start = r.pos
        sets = []
        for _ in range(n):
            name = r.string("marker set name")
            sets.append(MarkerSetData(name, r.vec3s(r.count(12, "marker"))))
        _check_size(r, start, size, "marker set", strict=False)
        # Unlabeled ("other") markers
        n = r.count(12, "unlabeled marker")
        size = r.section_size(version)
        start = r.pos
        unlabeled = r.vec3s(n)
        _check_size(r, start, size, "unlabeled marker", strict=False)
        # Rigid bodies
        n = r.count(_RB.size, "rigid body")
        size = r.section_size(version)
        start = r.pos
        bodies = r.bodies(n)
        _check_size(r, start, size, "rigid body", strict=True)
        # Skeletons
        n = r.count(8, "skeleton")
        size = r.section_size(version)
        start = r.pos
        skeletons = []
        for _ in range(n):
            ident = r.i32()
            skeletons.append(SkeletonData(ident, r.bodies(r.count(_RB.size, "skeleton bone"))))
        _check_size(r, start, size, "skeleton", strict=True)
        # Assets (4.1+)
        assets = []
        if version.byte_counts:
            n = r.count(12, "asset")
            size = r.section_size(version)
            start = r.pos
            for _ in range(n):
                ident = r.i32()
                rbs = r.bodies(r.count(_RB.size, "asset rigid body"))
                assets.append(AssetData(ident, rbs, r.markers(r.count(_MARKER.size, "asset marker"))))
            _check_size(r, start, size, "asset", strict=False)
        # Labeled markers
        n = r.count(_MARKER.size, "labeled marker")
        size = r.section_size(version)
        start = r.pos
        labeled = r.markers(n)
        _check_size(r, start, size, "labeled marker", strict=False)
        plates = _analog(r, version, "force plate")
        devices = _analog(r, version, "device")
        tc, tc_sub, timestamp, mid, received, transmit = r.take(_SUFFIX3)
        prec_s = prec_frac = 0
        if version.byte_counts:
            prec_s, prec_frac = r.take(_PRECISION)
        (params,) = r.take(_PARAMS)
        # A 4-byte end-of-data tag may follow; it carries nothing.
    except struct.error as exc:
        raise WireError(f"NatNet {version} frame malformed at byte {r.pos}: {exc}") from None
    if not math.isfinite(float(timestamp)):
        timestamp = 0.0
    return MocapFrame(
        frame_number=frame_number,
        marker_sets=tuple(sets),
        unlabeled_markers=unlabeled,
        rigid_bodies=bodies,
        skeletons=tuple(skeletons),
        assets=tuple(assets),
        labeled_markers=labeled,
        force_plates=plates,
        devices=devices,
        timecode=int(tc),
        timecode_sub=int(tc_sub),
        timestamp=float(timestamp),
        stamp_camera_mid_exposure=int(mid),
        stamp_data_received=int(received),
        stamp_transmit=int(transmit),
        precision_timestamp_secs=int(prec_s),
        precision_timestamp_frac_secs=int(prec_frac),
        params=int(params),
    )


def _rb_description(r: _Reader, version: NatNetVersion) -> RigidBodyDescription:
    name = r.string("rigid body name")
    ident, parent = r.i32(), r.i32()
    offset: Vec3 = r.take(_V3)
    orientation: Quat4 = (0.0, 0.0, 0.0, 1.0)
    if (version.major, version.minor) >= (4, 2):
        orientation = r.take(_Q4)
    n = r.count(16, "rigid body marker")
    offsets = r.vec3s(n)
    labels = tuple(r.i32() for _ in range(n))
    names: tuple[str, ...] = ()
    if version.major >= 4:
        names = tuple(r.string("rigid body marker name") for _ in range(n))
    return RigidBodyDescription(name, ident, parent, offset, orientation, offsets, labels, names)


def _skip_description(r: _Reader, kind: int, version: NatNetVersion) -> None:
    if kind == 3:  # force plate: id, serial, width, length, origin, 12x12 calibration, corners, types
        r.i32()
        r.string("force plate serial")
        r.pos += 4 + 4 + 12 + 144 * 4 + 12 * 4 + 4 + 4
        if r.pos > r.end:
            raise WireError("force plate description truncated")
        for _ in range(r.count(1, "force plate channel")):
            r.string("force plate channel name")
    elif kind == 4:  # device: id, name, serial, type, channel data type, channel names
        r.i32()
        r.string("device name")
        r.string("device serial")
        r.pos += 8
        for _ in range(r.count(1, "device channel")):
            r.string("device channel name")
    elif kind == 5:  # camera: name, position, orientation
        r.string("camera name")
        r.pos += 28
    else:
        raise WireError(f"model definition type {kind} is unknown; valid: 0 to 6")
    if r.pos > r.end:
        raise WireError(f"model definition of type {kind} truncated")


def parse_model_definitions(payload: bytes | memoryview, version: NatNetVersion) -> ModelDefinitions:
    """Parse a NAT_MODELDEF payload: rigid body, skeleton and marker set names and ids."""
    r = _Reader(memoryview(payload))
    bodies: list[RigidBodyDescription] = []
    skeletons: list[SkeletonDescription] = []
    sets: list[MarkerSetDescription] = []
    skipped = 0
    try:
        for _ in range(r.count(4, "model definition")):
            kind = r.i32()
            size = r.section_size(version)
            start = r.pos
            if kind == 0:
                name = r.string("marker set name")
                n = r.count(1, "marker set marker")
                sets.append(MarkerSetDescription(name, tuple(r.string("marker name") for _ in range(n))))
            elif kind == 1:
                bodies.append(_rb_description(r, version))
            elif kind == 2:
                name = r.string("skeleton name")
                ident = r.i32()
                n = r.count(20, "skeleton bone")
                bones = tuple(_rb_description(r, version) for _ in range(n))
                skeletons.append(SkeletonDescription(name, ident, bones))
            elif size is not None:  # 4.1+: anything else is skipped by its declared size
                r.pos = start + size
                skipped += 1
            else:
                _skip_description(r, kind, version)
                skipped += 1
            _check_size(r, start, size, f"model definition type {kind}", strict=kind in (1, 2))
    except struct.error as exc:
        raise WireError(f"NatNet {version} model definitions malformed at byte {r.pos}: {exc}") from None
    return ModelDefinitions(tuple(bodies), tuple(skeletons), tuple(sets), skipped)


def parse_server_info(payload: bytes | memoryview) -> ServerInfo:
    """Parse a NAT_SERVERINFO payload (sSender, then clock and data channel when present)."""
    r = _Reader(memoryview(payload))
    try:
        raw_name, a0, a1, a2, a3, n0, n1, n2, n3 = r.take(_SENDER)
        name = bytes(raw_name).split(b"\0", 1)[0].decode("utf-8", errors="replace")
        app = (int(a0), int(a1), int(a2), int(a3))
        natnet = (int(n0), int(n1), int(n2), int(n3))
        if r.left >= _SERVER_EXT.size:
            freq, port, multicast, *group = r.take(_SERVER_EXT)
            return ServerInfo(
                name,
                app,
                natnet,
                int(freq),
                int(port),
                bool(multicast),
                ".".join(str(int(g)) for g in group),
            )
    except struct.error as exc:
        raise WireError(f"NatNet server info malformed: {exc}") from None
    return ServerInfo(name, app, natnet)


def parse_message(data: bytes | bytearray | memoryview, version: NatNetVersion) -> Message:
    """Parse one datagram into its typed message; frames and model definitions use ``version``."""
    message_id, payload = split_packet(data)
    if message_id == NAT_FRAMEOFDATA:
        return parse_frame(payload, version)
    if message_id == NAT_MODELDEF:
        return parse_model_definitions(payload, version)
    if message_id == NAT_SERVERINFO:
        return parse_server_info(payload)
    if message_id == NAT_CONNECT:
        r = _Reader(payload)
        if r.left < _SENDER.size:
            return ConnectRequest(bytes(payload).split(b"\0", 1)[0].decode("utf-8", errors="replace"))
        raw_name, _, _, _, _, n0, n1, n2, n3 = r.take(_SENDER)
        name = bytes(raw_name).split(b"\0", 1)[0].decode("utf-8", errors="replace")
        return ConnectRequest(name, (int(n0), int(n1), int(n2), int(n3)))
    return OtherMessage(message_id, bytes(payload))


# --------------------------------------------------------------------------------------- encoding


def encode_packet(message_id: int, payload: bytes = b"") -> bytes:
    """One datagram: header (message id, payload size) + payload (< 65536 bytes)."""
    if len(payload) > 0xFFFF:
        raise WireError(f"NatNet payload of {len(payload)} bytes exceeds 65535")
    return _HEADER.pack(message_id, len(payload)) + payload


def _cstr(text: str) -> bytes:
    raw = text.encode("utf-8")[: _MAX_NAME - 1]
    return raw + b"\0"


def _sized(body: bytes, version: NatNetVersion) -> bytes:
    return (_I32.pack(len(body)) if version.byte_counts else b"") + body


def _pack_bodies(bodies: Iterable[RigidBodyData]) -> bytes:
    return b"".join(_RB.pack(b.id, *b.position, *b.orientation, b.mean_error, b.params) for b in bodies)


def _pack_markers(markers: Iterable[LabeledMarker]) -> bytes:
    return b"".join(_MARKER.pack(m.id, *m.position, m.size, m.params, m.residual) for m in markers)


def _pack_analog(items: tuple[AnalogData, ...], version: NatNetVersion) -> bytes:
    body = b"".join(
        _I32.pack(a.id)
        + _I32.pack(len(a.channels))
        + b"".join(_I32.pack(len(c)) + struct.pack(f"<{len(c)}f", *c) for c in a.channels)
        for a in items
    )
    return _I32.pack(len(items)) + _sized(body, version)


def encode_frame(frame: MocapFrame, version: NatNetVersion) -> bytes:
    """A complete NAT_FRAMEOFDATA datagram for ``frame`` in the given bitstream version."""
    parts = [_I32.pack(frame.frame_number)]
    body = b"".join(
        _cstr(s.name) + _I32.pack(len(s.positions)) + b"".join(_V3.pack(*p) for p in s.positions)
        for s in frame.marker_sets
    )
    parts += [_I32.pack(len(frame.marker_sets)), _sized(body, version)]
    body = b"".join(_V3.pack(*p) for p in frame.unlabeled_markers)
    parts += [_I32.pack(len(frame.unlabeled_markers)), _sized(body, version)]
    parts += [_I32.pack(len(frame.rigid_bodies)), _sized(_pack_bodies(frame.rigid_bodies), version)]
    body = b"".join(
        _I32.pack(s.id) + _I32.pack(len(s.bones)) + _pack_bodies(s.bones) for s in frame.skeletons
    )
    parts += [_I32.pack(len(frame.skeletons)), _sized(body, version)]
    if version.byte_counts:
        body = b"".join(
            _I32.pack(a.id)
            + _I32.pack(len(a.rigid_bodies))
            + _pack_bodies(a.rigid_bodies)
            + _I32.pack(len(a.markers))
            + _pack_markers(a.markers)
            for a in frame.assets
        )
        parts += [_I32.pack(len(frame.assets)), _sized(body, version)]
    parts += [_I32.pack(len(frame.labeled_markers)), _sized(_pack_markers(frame.labeled_markers), version)]
    parts += [_pack_analog(frame.force_plates, version), _pack_analog(frame.devices, version)]
    parts.append(
        _SUFFIX3.pack(
            frame.timecode,
            frame.timecode_sub,
            frame.timestamp,
            frame.stamp_camera_mid_exposure,
            frame.stamp_data_received,
            frame.stamp_transmit,
        )
    )
    if version.byte_counts:
        parts.append(_PRECISION.pack(frame.precision_timestamp_secs, frame.precision_timestamp_frac_secs))
    parts += [_PARAMS.pack(frame.params), _I32.pack(0)]  # params, end-of-data tag
    return encode_packet(NAT_FRAMEOFDATA, b"".join(parts))


def _pack_rb_description(d: RigidBodyDescription, version: NatNetVersion) -> bytes:
    out = [_cstr(d.name), _I32.pack(d.id), _I32.pack(d.parent_id), _V3.pack(*d.offset)]
    if (version.major, version.minor) >= (4, 2):
        out.append(_Q4.pack(*d.orientation))
    n = len(d.marker_offsets)
    out.append(_I32.pack(n))
    out += [_V3.pack(*p) for p in d.marker_offsets]
    labels = d.marker_labels or (0,) * n
    out += [_I32.pack(v) for v in labels]
    if version.major >= 4:
        names = d.marker_names or tuple(f"Marker{i + 1}" for i in range(n))
        out += [_cstr(s) for s in names]
    return b"".join(out)


def encode_model_definitions(defs: ModelDefinitions, version: NatNetVersion) -> bytes:
    """A complete NAT_MODELDEF datagram (marker sets, rigid bodies, skeletons) in ``version``."""
    items: list[tuple[int, bytes]] = []
    for s in defs.marker_sets:
        items.append(
            (0, _cstr(s.name) + _I32.pack(len(s.marker_names)) + b"".join(map(_cstr, s.marker_names)))
        )
    for b in defs.rigid_bodies:
        items.append((1, _pack_rb_description(b, version)))
    for sk in defs.skeletons:
        body = _cstr(sk.name) + _I32.pack(sk.id) + _I32.pack(len(sk.bones))
        body += b"".join(_pack_rb_description(b, version) for b in sk.bones)
        items.append((2, body))
    payload = _I32.pack(len(items)) + b"".join(_I32.pack(k) + _sized(body, version) for k, body in items)
    return encode_packet(NAT_MODELDEF, payload)


def encode_server_info(info: ServerInfo) -> bytes:
    """A complete NAT_SERVERINFO datagram (sSender_Server layout)."""
    group = [int(g) for g in info.multicast_group.split(".")] if info.multicast_group else [0, 0, 0, 0]
    payload = _SENDER.pack(_cstr(info.app_name), *info.app_version, *info.natnet_version)
    payload += _SERVER_EXT.pack(info.high_res_clock_hz, info.data_port, info.multicast, *group)
    return encode_packet(NAT_SERVERINFO, payload)


def encode_connect(
    app_name: str = "telerig", natnet_version: tuple[int, int, int, int] = (0, 0, 0, 0)
) -> bytes:
    """A complete NAT_CONNECT datagram; version 0.0.0.0 asks for the server's own bitstream."""
    return encode_packet(NAT_CONNECT, _SENDER.pack(_cstr(app_name), 0, 1, 0, 0, *natnet_version))


# ------------------------------------------------------------------------------------ normalizing


@dataclass(slots=True)
class _Names:
    bodies: dict[int, str] = field(default_factory=dict)
    skeletons: dict[int, tuple[str, tuple[str, ...], dict[int, int], tuple[int, ...]]] = field(
        default_factory=dict
    )


def _bone_id(rb_id: int) -> int:
    return rb_id & 0xFFFF


class FrameNormalizer:
    """Turns :class:`MocapFrame` into IR samples: ``Pose`` per rigid body, ``BodySkeleton`` per skeleton.

    Output frame ``frame_id`` (default ``"mocap"``) has the operator axes (x forward, y left,
    z up, metres) via ``mount``; source ids are ``"<device_id>/<name>"`` with names from the
    model definitions (``rb<id>`` / ``skeleton<id>`` / ``bone<id>`` until they are known).
    Dropped, per reason in the returned counter: ``tracking_invalid`` (a rigid body not tracked,
    or a skeleton with fewer than half its bones tracked), ``non_finite``, ``out_of_range``
    (a coordinate beyond ``max_range_m``), ``bad_quaternion`` (norm not within 10% of 1),
    ``duplicate_bone`` (two bones of a skeleton with the same name).
    Skeleton confidence is the fraction of tracked bones; rigid bodies have confidence 1.
    """

    def __init__(
        self,
        device_id: str,
        *,
        mount: MountTransform | None = None,
        frame_id: str = "mocap",
        skeleton_coordinates: str = "global",
        max_range_m: float = 100.0,
    ) -> None:
        """Args:
        device_id: Prefix of the source ids.
        mount: Motive world -> output frame; default Y up, +Z forward, no offset.
        frame_id: Frame name the samples are expressed in.
        skeleton_coordinates: ``"global"`` (bones in Motive world) or ``"local"`` (relative to
            the parent bone; composed here with the parents from the model definitions).
        max_range_m: Largest accepted |coordinate| [m] in the output frame.
        """
        if skeleton_coordinates not in ("global", "local"):
            raise WireError(f"skeleton_coordinates must be 'global' or 'local'; got {skeleton_coordinates!r}")
        self.device_id = device_id
        self.mount = mount or MountTransform()
        self.frame_id = frame_id
        self.local = skeleton_coordinates == "local"
        self.max_range_m = float(max_range_m)
        self._names = _Names()
        self._seq: dict[str, int] = {}
        self.has_models = False

    def set_models(self, defs: ModelDefinitions) -> None:
        """Take names and bone hierarchy from the server's model definitions."""
        names = _Names()
        for b in defs.rigid_bodies:
            names.bodies[b.id] = b.name
        for sk in defs.skeletons:
            bone_ids = [_bone_id(b.id) for b in sk.bones]
            index = {bid: i for i, bid in enumerate(bone_ids)}
            parents = tuple(index.get(_bone_id(b.parent_id), -1) if b.parent_id > 0 else -1 for b in sk.bones)
            names.skeletons[sk.id] = (sk.name, tuple(b.name for b in sk.bones), index, parents)
        self._names = names
        self.has_models = True

    def unknown_ids(self, frame: MocapFrame) -> bool:
        """Whether the frame names a rigid body or skeleton the model definitions do not."""
        return any(b.id not in self._names.bodies for b in frame.rigid_bodies) or any(
            s.id not in self._names.skeletons for s in frame.skeletons
        )

    def _stamp(self, source: str, device_ns: int, capture_ns: int, confidence: float) -> Stamp:
        seq = self._seq.get(source, -1) + 1
        self._seq[source] = seq
        return Stamp(source, seq, device_ns, capture_ns, 0, confidence)

    def _batch(
        self, rows: list[RigidBodyData]
    ) -> tuple[FloatArray, FloatArray, npt.NDArray[np.bool_], list[str]]:
        """Output positions, orientations, row validity and (for invalid rows) the reason, in one pass."""
        raw = np.array([(*b.position, b.orientation[3], *b.orientation[:3]) for b in rows], dtype=np.float64)
        finite: npt.NDArray[np.bool_] = np.asarray(np.isfinite(raw).all(axis=1))
        all_finite = bool(finite.all())
        if not all_finite:
            raw[~finite] = 0.0
        q = raw[:, 3:]
        norm = np.sqrt(np.einsum("ij,ij->i", q, q))  # float32 inputs cannot overflow float64 here
        good_q: npt.NDArray[np.bool_] = np.abs(norm - 1.0) <= 0.1
        q = q / np.maximum(norm, 1e-12)[:, None]
        po = self.mount.positions(raw[:, :3])
        qo = self.mount.orientations(q)
        in_range: npt.NDArray[np.bool_] = np.asarray((np.abs(po) <= self.max_range_m).all(axis=1))
        valid: npt.NDArray[np.bool_] = finite & good_q & in_range
        reasons: list[str] = []
        if not valid.all():
            reasons = [
                "" if ok else "non_finite" if not f else "bad_quaternion" if not g else "out_of_range"
                for ok, f, g in zip(valid.tolist(), finite.tolist(), good_q.tolist(), strict=True)
            ]
        return po, qo, valid, reasons

    def normalize(
        self, frame: MocapFrame, device_ns: int, capture_ns: int
    ) -> tuple[list[Sample], Counter[str]]:
        """IR samples of one frame and the count of dropped bodies per reason.

        ``device_ns`` / ``capture_ns`` [ns] stamp every sample of the frame (mid-exposure time in
        the server's clock and in the common clock).
        """
        drops: Counter[str] = Counter()
        out: list[Sample] = []
        rows: list[RigidBodyData] = list(frame.rigid_bodies)
        for sk in frame.skeletons:
            rows.extend(sk.bones)
        if not rows:
            return out, drops
        po, qo, valid, reasons = self._batch(rows)
        for i, b in enumerate(frame.rigid_bodies):
            if not b.params & 0x01:
                drops["tracking_invalid"] += 1
            elif not valid[i]:
                drops[reasons[i]] += 1
            else:
                name = self._names.bodies.get(b.id) or f"rb{b.id}"
                stamp = self._stamp(f"{self.device_id}/{name}", device_ns, capture_ns, 1.0)
                out.append(Pose(stamp, po[i], qo[i], self.frame_id))
        start = len(frame.rigid_bodies)
        for sk in frame.skeletons:
            end = start + len(sk.bones)
            sample = self._skeleton(
                sk,
                po[start:end],
                qo[start:end],
                valid[start:end],
                reasons[start:end],
                drops,
                device_ns,
                capture_ns,
            )
            if sample is not None:
                out.append(sample)
            start = end
        return out, drops

    def _skeleton(
        self,
        sk: SkeletonData,
        po: FloatArray,
        qo: FloatArray,
        valid: npt.NDArray[np.bool_],
        reasons: list[str],
        drops: Counter[str],
        device_ns: int,
        capture_ns: int,
    ) -> BodySkeleton | None:
        if not sk.bones:
            return None
        tracked = sum(b.params & 0x01 for b in sk.bones)
        if 2 * tracked < len(sk.bones):
            drops["tracking_invalid"] += 1
            return None
        if not valid.all():
            drops[next(r for r in reasons if r)] += 1
            return None
        known = self._names.skeletons.get(sk.id)
        if known is not None:
            sk_name, bone_names, index, parents = known
            names = [
                bone_names[i] if (i := index.get(_bone_id(b.id))) is not None else f"bone{_bone_id(b.id)}"
                for b in sk.bones
            ]
            if self.local:
                po, qo = self._local_to_world(sk.bones, index, parents)
                if not (np.isfinite(po).all() and (np.abs(po) <= self.max_range_m).all()):
                    drops["out_of_range"] += 1
                    return None
        else:
            sk_name = f"skeleton{sk.id}"
            names = [f"bone{_bone_id(b.id)}" for b in sk.bones]
        if len(set(names)) != len(names):
            drops["duplicate_bone"] += 1
            return None
        stamp = self._stamp(f"{self.device_id}/{sk_name}", device_ns, capture_ns, tracked / len(sk.bones))
        return BodySkeleton(stamp, tuple(names), po, qo, self.frame_id)

    def _local_to_world(
        self, bones: tuple[RigidBodyData, ...], index: dict[int, int], parents: tuple[int, ...]
    ) -> tuple[FloatArray, FloatArray]:
        raw = np.array([(*b.position, b.orientation[3], *b.orientation[:3]) for b in bones], dtype=np.float64)
        q = raw[:, 3:] / np.linalg.norm(raw[:, 3:], axis=1, keepdims=True)
        p, q = _compose_local(bones, raw[:, :3], q, index, parents)
        return self.mount.positions(p), self.mount.orientations(q)


def _compose_local(
    bones: tuple[RigidBodyData, ...],
    p: FloatArray,
    q: FloatArray,
    index: dict[int, int],
    parents: tuple[int, ...],
) -> tuple[FloatArray, FloatArray]:
    """World bone poses from parent-relative ones (parents are resolved through the definitions)."""
    n = len(bones)
    pw, qw = p.copy(), q.copy()
    done = [False] * n
    frame_index = {_bone_id(b.id): i for i, b in enumerate(bones)}
    order = sorted(range(n), key=lambda i: _depth(_bone_id(bones[i].id), index, parents))
    for i in order:
        d = index.get(_bone_id(bones[i].id))
        parent_def = parents[d] if d is not None else -1
        if parent_def < 0:
            done[i] = True
            continue
        parent_bone = next((bid for bid, k in index.items() if k == parent_def), None)
        j = frame_index.get(parent_bone) if parent_bone is not None else None
        if j is None or not done[j]:
            done[i] = True
            continue
        r = qw[j]
        t = 2.0 * cross3(r[1:], p[i])
        pw[i] = pw[j] + p[i] + r[0] * t + cross3(r[1:], t)
        qw[i] = quat_multiply(r, q[i])
        done[i] = True
    return pw, qw


def _depth(bone: int, index: dict[int, int], parents: tuple[int, ...]) -> int:
    d, k = 0, index.get(bone)
    while k is not None and k >= 0 and parents[k] >= 0 and d < len(parents):
        k = parents[k]
        d += 1
    return d


# ----------------------------------------------------------------------------------------- fuzzing

_FUZZ_VERSIONS = (NatNetVersion(3, 1), NatNetVersion(4, 1))


def _fuzz(data: bytes) -> object:
    """Parse ``data`` as a NatNet 3.1 and as a 4.1 datagram, normalizing frames; only WireError escapes.

    Each version is tried on its own (so a 4.1 frame is explored past the point where 3.1 fails);
    WireError is raised when neither parses.
    """
    out: list[object] = []
    errors: list[WireError] = []
    for version in _FUZZ_VERSIONS:
        try:
            message = parse_message(data, version)
        except WireError as exc:
            errors.append(exc)
            continue
        if isinstance(message, MocapFrame):
            samples, _ = FrameNormalizer("fuzz").normalize(message, 0, 0)
            out.extend(samples)
        else:
            out.append(message)
    if len(errors) == len(_FUZZ_VERSIONS):
        raise errors[-1]
    return out


#: One datagram in, parsed (and normalized) message out; raises only :class:`WireError`.
FUZZ_TARGET: Callable[[bytes], object] = _fuzz
