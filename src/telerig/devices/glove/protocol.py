"""telerig glove bridge stream v1: a little-endian framed binary format over TCP, pure parsing.

There is no open wire standard for Manus-class data gloves, so telerig defines the stream a
vendor-SDK bridge process (C++, next to the vendor SDK) emits. The bridge is a TCP server; telerig
connects as a client and reads back-to-back frames. One frame, all fields little-endian::

    offset size  type      field
    0      4     bytes     magic b"TGLV"
    4      1     uint8     version = 1
    5      1     uint8     flags: bit 0 = fingertip positions present; bits 1-7 must be 0
    6      2     uint16    length: bytes in the whole frame, magic to CRC inclusive
    8      4     uint32    seq: frame counter of this hand's glove, +1 per frame, wraps at 2**32
    12     8     uint64    device timestamp [ns] in the bridge's monotonic clock
    20     1     uint8     handedness: 0 = left, 1 = right
    21     1     uint8     n_angles: 20 (fingers) or 22 (fingers + wrist)
    22     2     -         reserved, 0
    24     4*n   float32   joint angles [rad], order below
    ..     60    float32   fingertip positions [mm], 5 x (x, y, z), thumb..little (only if flag bit 0)
    ..     5     uint8     per-finger confidence, thumb..little, 0..255 -> [0, 1]
    ..     4     uint32    CRC-32 (IEEE 802.3, zlib.crc32) of every byte before it

Joint angle order (:data:`JOINT_NAMES`), four per finger, fingers thumb, index, middle, ring,
little: thumb CMC spread, CMC flex, MCP flex, IP flex; other fingers MCP spread, MCP flex, PIP flex,
DIP flex; then, when ``n_angles == 22``, wrist flex and wrist deviation. Signs: flex > 0 curls
toward the palm; spread > 0 moves the finger toward the thumb side (radial abduction; for the
thumb, away from the index finger); wrist flex > 0 is palmar flexion, deviation > 0 is radial.
Every angle must be finite with ``|angle| <= pi``.

Fingertip positions are in the hand frame ``"<hand>_glove"`` (see :mod:`.kinematics`): origin at
the wrist, x toward the fingers, z out of the back of the hand, y = z x x (toward the thumb on a
right hand, away from it on a left hand); each coordinate within +-400 mm.

Stream framing (:class:`GloveStreamDecoder`): frames are found by their magic; bytes before a magic
are garbage and skipped; a candidate whose header is inconsistent or whose CRC fails is a false
magic, and the search resumes one byte later; a CRC-valid frame whose content is invalid is skipped
whole. A header must be self-consistent before the decoder waits for the rest of a frame, so garbage
delays a good frame by at most one maximum frame length (:data:`MAX_FRAME_LEN` bytes).
"""

from __future__ import annotations

import math
import struct
import zlib
from dataclasses import dataclass

import numpy as np

from telerig.errors import WireError
from telerig.ir.types import FloatArray, Handedness

__all__ = [
    "FINGERS",
    "HEADER",
    "JOINT_NAMES",
    "MAGIC",
    "MAX_ANGLE_RAD",
    "MAX_FRAME_LEN",
    "MAX_TIP_MM",
    "VERSION",
    "GloveFrame",
    "GloveStreamDecoder",
    "GloveWireError",
    "decode_frame",
    "encode_frame",
    "frame_length",
]

MAGIC = b"TGLV"
VERSION = 1
#: Header layout: magic, version, flags, length, seq, device_ns, handedness, n_angles, reserved.
HEADER = struct.Struct("<4sBBHIQBB2x")
_CRC = struct.Struct("<I")
_TIPS = struct.Struct("<15f")
FLAG_FINGERTIPS = 0x01
FINGERS: tuple[str, ...] = ("thumb", "index", "middle", "ring", "little")
JOINT_NAMES: tuple[str, ...] = (
    "thumb_cmc_spread",
    "thumb_cmc_flex",
    "thumb_mcp_flex",
    "thumb_ip_flex",
    *(f"{f}_{j}" for f in FINGERS[1:] for j in ("mcp_spread", "mcp_flex", "pip_flex", "dip_flex")),
    "wrist_flex",
    "wrist_deviation",
)
N_FINGER_ANGLES = 20
N_ALL_ANGLES = 22
#: Largest accepted joint angle magnitude [rad].
MAX_ANGLE_RAD = math.pi
#: Largest accepted fingertip coordinate magnitude [mm].
MAX_TIP_MM = 400.0
#: Largest frame of any version the decoder waits for [bytes].
MAX_FRAME_LEN = 1024
_MIN_FRAME_LEN = HEADER.size + _CRC.size


class GloveWireError(WireError):
    """A glove frame could not be decoded; ``reason`` is a short stats key (e.g. ``"crc"``)."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


def frame_length(n_angles: int, fingertips: bool) -> int:
    """Length [bytes] of a version-1 frame with ``n_angles`` angles and optional fingertips."""
    return HEADER.size + 4 * n_angles + (60 if fingertips else 0) + 5 + _CRC.size


@dataclass(frozen=True, slots=True)
class GloveFrame:
    """One decoded glove frame.

    Attributes:
        seq: Frame counter of this hand's glove (uint32, wraps).
        device_ns: Bridge monotonic timestamp [ns].
        handedness: ``"left"`` or ``"right"``.
        finger_angles: Joint angles [rad], rows thumb..little, columns spread, flex1, flex2, flex3
            (see :data:`JOINT_NAMES`). Shape (5, 4).
        wrist_angles: Wrist (flex, deviation) [rad], or None when the glove has no wrist sensor.
            Shape (2,).
        fingertips_mm: Fingertip positions [mm] in the ``"<hand>_glove"`` frame, rows thumb..little,
            or None. Shape (5, 3).
        confidence: Per-finger confidence in [0, 1], thumb..little. Shape (5,).
    """

    seq: int
    device_ns: int
    handedness: Handedness
    finger_angles: FloatArray
    wrist_angles: FloatArray | None
    fingertips_mm: FloatArray | None
    confidence: FloatArray


def encode_frame(frame: GloveFrame) -> bytes:
    """Encode ``frame`` as one version-1 wire frame (used by the fake bridge and tests).

    Raises:
        ValueError: If a field does not fit the format (shapes, ranges, counters).
    """
    angles = np.asarray(frame.finger_angles, dtype=np.float64)
    if angles.shape != (5, 4):
        raise ValueError(f"finger_angles must have shape (5, 4), got {angles.shape}")
    parts = [angles.reshape(-1)]
    if frame.wrist_angles is not None:
        wrist = np.asarray(frame.wrist_angles, dtype=np.float64)
        if wrist.shape != (2,):
            raise ValueError(f"wrist_angles must have shape (2,), got {wrist.shape}")
        parts.append(wrist)
    all_angles = np.concatenate(parts)
    tips = frame.fingertips_mm
    flags = 0
    if tips is not None:
        tips = np.asarray(tips, dtype=np.float64)
        if tips.shape != (5, 3):
            raise ValueError(f"fingertips_mm must have shape (5, 3), got {tips.shape}")
        flags |= FLAG_FINGERTIPS
    conf = np.asarray(frame.confidence, dtype=np.float64)
    if conf.shape != (5,) or not np.all((conf >= 0.0) & (conf <= 1.0)):
        raise ValueError(f"confidence must be 5 values in [0, 1], got {conf!r}")
    if frame.handedness not in ("left", "right"):
        raise ValueError(f"handedness must be 'left' or 'right', got {frame.handedness!r}")
    n = all_angles.size
    length = frame_length(n, tips is not None)
    body = bytearray(
        HEADER.pack(
            MAGIC,
            VERSION,
            flags,
            length,
            frame.seq & 0xFFFFFFFF,
            frame.device_ns,
            1 if frame.handedness == "right" else 0,
            n,
        )
    )
    body += all_angles.astype("<f4").tobytes()
    if tips is not None:
        body += tips.astype("<f4").tobytes()
    body += np.round(conf * 255.0).astype(np.uint8).tobytes()
    body += _CRC.pack(zlib.crc32(body))
    return bytes(body)


def _check_header(version: int, flags: int, length: int, hand: int, n_angles: int) -> GloveWireError | None:
    """Why a version-1 header is inconsistent, or None if it is fine."""
    if flags & ~FLAG_FINGERTIPS:
        return GloveWireError("header", f"flags must use only bit 0 in version 1, got 0x{flags:02x}")
    if hand > 1:
        return GloveWireError("header", f"handedness byte must be 0 (left) or 1 (right), got {hand}")
    if n_angles not in (N_FINGER_ANGLES, N_ALL_ANGLES):
        return GloveWireError("header", f"n_angles must be 20 or 22, got {n_angles}")
    expected = frame_length(n_angles, bool(flags & FLAG_FINGERTIPS))
    if length != expected:
        return GloveWireError(
            "header", f"length must be {expected} for {n_angles} angles and flags 0x{flags:02x}, got {length}"
        )
    return None


def decode_frame(data: bytes | bytearray | memoryview) -> GloveFrame:
    """Decode exactly one frame (magic to CRC).

    Raises:
        GloveWireError: (a :class:`~telerig.errors.WireError`) with ``reason`` one of ``"header"``
            (magic, length or header fields), ``"version"``, ``"crc"``, ``"values"`` (non-finite or
            out-of-range angle or fingertip).
    """
    view = data if isinstance(data, bytes) else bytes(data)
    size = len(view)
    if size < _MIN_FRAME_LEN:
        raise GloveWireError("header", f"frame must be at least {_MIN_FRAME_LEN} bytes, got {size}")
    magic, version, flags, length, seq, device_ns, hand, n_angles = HEADER.unpack_from(view, 0)
    if magic != MAGIC:
        raise GloveWireError("header", f"frame must start with magic {MAGIC!r}, got {bytes(magic)!r}")
    if length != size:
        raise GloveWireError("header", f"length field says {length} bytes but the frame has {size}")
    (crc,) = _CRC.unpack_from(view, size - 4)
    if zlib.crc32(view[: size - 4]) != crc:
        raise GloveWireError("crc", "CRC-32 mismatch; the frame was corrupted in transit")
    if version != VERSION:
        raise GloveWireError("version", f"version must be {VERSION}, got {version}; update telerig")
    problem = _check_header(version, flags, length, hand, n_angles)
    if problem is not None:
        raise problem
    off = HEADER.size
    angles = struct.unpack_from(f"<{n_angles}f", view, off)
    off += 4 * n_angles
    for k, value in enumerate(angles):
        if not -MAX_ANGLE_RAD <= value <= MAX_ANGLE_RAD:  # False for NaN as well
            raise GloveWireError(
                "values", f"angle {JOINT_NAMES[k]} must be finite within +-pi rad, got {value}"
            )
    tips: FloatArray | None = None
    if flags & FLAG_FINGERTIPS:
        tip_values = _TIPS.unpack_from(view, off)
        off += _TIPS.size
        if not all(-MAX_TIP_MM <= v <= MAX_TIP_MM for v in tip_values):
            raise GloveWireError("values", f"fingertip coordinates must be finite within +-{MAX_TIP_MM} mm")
        tips = np.array(tip_values).reshape(5, 3)
    conf = np.array([b / 255.0 for b in view[off : off + 5]])
    finger = np.array(angles[:N_FINGER_ANGLES]).reshape(5, 4)
    wrist = np.array(angles[N_FINGER_ANGLES:]) if n_angles == N_ALL_ANGLES else None
    return GloveFrame(
        seq=seq,
        device_ns=device_ns,
        handedness="right" if hand == 1 else "left",
        finger_angles=finger,
        wrist_angles=wrist,
        fingertips_mm=tips,
        confidence=conf,
    )


class GloveStreamDecoder:
    """Splits a TCP byte stream into frames, resynchronizing on the magic after garbage.

    Pure and incremental: :meth:`feed` any chunk of bytes, get back the frames completed by it.
    ``stats`` counts ``frames``, ``garbage_bytes`` (skipped while searching for a magic), and drops
    per reason: ``header``, ``crc``, ``version``, ``values``.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self.stats: dict[str, int] = {
            "frames": 0,
            "garbage_bytes": 0,
            "header": 0,
            "crc": 0,
            "version": 0,
            "values": 0,
        }

    @property
    def buffered(self) -> int:
        """Bytes held back waiting for the rest of a frame."""
        return len(self._buf)

    def feed(self, data: bytes | bytearray | memoryview) -> list[GloveFrame]:
        """Append ``data`` and return the complete, valid frames now available, in stream order."""
        buf = self._buf
        buf += data
        out: list[GloveFrame] = []
        pos = 0
        stats = self.stats
        end = len(buf)
        while True:
            start = buf.find(MAGIC, pos)
            if start < 0:
                # Keep a possible partial magic at the tail.
                keep = 0
                for k in range(min(3, end - pos), 0, -1):
                    if buf.endswith(MAGIC[:k]):
                        keep = k
                        break
                stats["garbage_bytes"] += end - pos - keep
                pos = end - keep
                break
            stats["garbage_bytes"] += start - pos
            pos = start
            if end - pos < HEADER.size:
                break
            _, version, flags, length, _, _, hand, n_angles = HEADER.unpack_from(buf, pos)
            if version == VERSION:
                if _check_header(version, flags, length, hand, n_angles) is not None:
                    stats["header"] += 1
                    pos += 1
                    continue
            elif not _MIN_FRAME_LEN <= length <= MAX_FRAME_LEN:
                stats["header"] += 1
                pos += 1
                continue
            if end - pos < length:
                break
            try:
                frame = decode_frame(bytes(buf[pos : pos + length]))
            except GloveWireError as exc:
                stats[exc.reason] = stats.get(exc.reason, 0) + 1
                # A CRC failure means the length may be wrong too: resume right after this magic.
                pos += 1 if exc.reason in ("crc", "header") else length
                continue
            out.append(frame)
            stats["frames"] += 1
            pos += length
        del buf[:pos]
        return out
