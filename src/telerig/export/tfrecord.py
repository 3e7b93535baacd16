"""TFRecord files of ``tf.train.Example`` protos, written and read without TensorFlow.

RLDS datasets (Open X-Embodiment) are TFRecord shards of ``tf.train.Example`` messages, one per
episode. Both formats are small and stable, so telerig writes them itself instead of depending on
TensorFlow (a ~600 MB wheel with its own protobuf pin):

- A TFRecord file is a sequence of records, each ``uint64 length | uint32 masked_crc32c(length) |
  data | uint32 masked_crc32c(data)``, little-endian; the mask is ``((crc >> 15) | (crc << 17)) +
  0xa282ead8`` modulo 2**32 (TensorFlow's ``core/lib/hash/crc32c.h``).
- ``Example { Features features = 1; }``, ``Features { map<string, Feature> feature = 1; }``,
  ``Feature { oneof kind { BytesList bytes_list = 1; FloatList float_list = 2; Int64List
  int64_list = 3; } }``, each list a ``repeated value = 1`` (floats and ints packed), from
  TensorFlow's ``core/example/{example,feature}.proto``. The encoder writes that wire format
  directly: a float list is one ``tobytes()`` of the little-endian float32 array, and an
  example is kept as a list of parts (:class:`Encoded`) so its images are never copied.

The test vectors in ``tests/export/test_tfrecord.py`` were produced by TensorFlow's own
``TFRecordWriter`` and ``Example.SerializeToString``.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO, Literal

import google_crc32c
import numpy as np
import numpy.typing as npt

from telerig.errors import ExportError
from telerig.ir.protowire import LEN as _LEN
from telerig.ir.protowire import len_field, len_header, varint

__all__ = [
    "Encoded",
    "Feature",
    "FeatureKind",
    "TFRecordWriter",
    "bytes_feature",
    "crc32c",
    "decode_example",
    "encode_example",
    "float_feature",
    "int64_feature",
    "masked_crc32c",
    "read_records",
]

_MASK_DELTA = 0xA282EAD8
_U32 = 0xFFFFFFFF
# Wire types of the protobuf encoding.
_VARINT = 0
_I64 = 1
_I32 = 5

#: Which list a ``tf.train.Feature`` holds.
FeatureKind = Literal["bytes", "float", "int64"]
_KIND_FIELD: dict[FeatureKind, int] = {"bytes": 1, "float": 2, "int64": 3}
_FIELD_KIND: dict[int, FeatureKind] = {v: k for k, v in _KIND_FIELD.items()}


def crc32c(data: bytes | memoryview) -> int:
    """CRC-32C (Castagnoli) of ``data``, as an unsigned 32-bit int (``b"123456789"`` → 0xE3069283)."""
    return int(google_crc32c.value(bytes(data)))


def masked_crc32c(data: bytes | memoryview) -> int:
    """TFRecord's masked CRC-32C of ``data`` (a CRC of data holding CRCs is a poor checksum)."""
    return _mask(crc32c(data))


def _mask(crc: int) -> int:
    return ((((crc >> 15) | (crc << 17)) & _U32) + _MASK_DELTA) & _U32


# -- protobuf wire format ------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Encoded:
    """Serialized protobuf bytes kept as parts, so large values (images) are never copied into one
    buffer: :class:`TFRecordWriter` checksums and writes the parts in order.

    Attributes:
        parts: The bytes, in order.
        size: Total length [bytes].
    """

    parts: tuple[bytes, ...]
    size: int

    def __bytes__(self) -> bytes:
        return b"".join(self.parts)


def _field(field: int, payload: Encoded) -> Encoded:
    header = len_header(field, payload.size)
    return Encoded((header, *payload.parts), len(header) + payload.size)


def _plain(data: bytes) -> Encoded:
    return Encoded((data,), len(data))


def bytes_feature(values: Iterable[bytes]) -> Encoded:
    """An encoded ``Feature`` holding a ``BytesList`` of ``values`` (images, UTF-8 text)."""
    parts: list[bytes] = []
    size = 0
    for value in values:
        header = len_header(1, len(value))
        parts += (header, value)
        size += len(header) + len(value)
    return _field(_KIND_FIELD["bytes"], Encoded(tuple(parts), size))


def float_feature(values: npt.ArrayLike) -> Encoded:
    """An encoded ``Feature`` holding a ``FloatList``: ``values`` flattened, as float32."""
    packed = np.ascontiguousarray(values, dtype="<f4").tobytes()
    payload = len_field(1, packed) if packed else b""
    return _plain(len_field(_KIND_FIELD["float"], payload))


def int64_feature(values: npt.ArrayLike) -> Encoded:
    """An encoded ``Feature`` holding an ``Int64List``: ``values`` flattened (bools as 0/1)."""
    flat = np.asarray(values).astype(np.int64, copy=False).ravel()
    packed = b"".join(varint(int(v)) for v in flat)
    payload = len_field(1, packed) if packed else b""
    return _plain(len_field(_KIND_FIELD["int64"], payload))


def encode_example(features: Mapping[str, Encoded]) -> Encoded:
    """A serialized ``tf.train.Example`` from feature key → encoded ``Feature`` (``*_feature``)."""
    parts: list[bytes] = []
    size = 0
    for key, value in features.items():
        entry = _field(2, value)
        name = len_field(1, key.encode())
        header = len_header(1, len(name) + entry.size)
        parts += (header, name, *entry.parts)
        size += len(header) + len(name) + entry.size
    return _field(1, Encoded(tuple(parts), size))


@dataclass(frozen=True, slots=True)
class Feature:
    """One decoded ``tf.train.Feature``.

    Attributes:
        kind: Which list it held.
        values: ``list[bytes]`` for ``bytes``; float32 array (N,) for ``float``; int64 array (N,)
            for ``int64``.
    """

    kind: FeatureKind
    values: list[bytes] | npt.NDArray[np.float32] | npt.NDArray[np.int64]

    def as_bytes(self, key: str) -> list[bytes]:
        """The values of a bytes feature; raises ExportError naming ``key`` for another kind."""
        if self.kind != "bytes" or not isinstance(self.values, list):
            raise ExportError(f"feature {key!r} holds {self.kind} values, expected bytes")
        return self.values

    def as_array(self, key: str, kind: Literal["float", "int64"]) -> npt.NDArray[np.generic]:
        """The values of a float or int64 feature; raises ExportError naming ``key`` for another kind."""
        if self.kind != kind or isinstance(self.values, list):
            raise ExportError(f"feature {key!r} holds {self.kind} values, expected {kind}")
        return self.values


class _Reader:
    """Cursor over one protobuf message's bytes."""

    __slots__ = ("data", "end", "pos")

    def __init__(self, data: memoryview, start: int = 0, end: int | None = None) -> None:
        self.data = data
        self.pos = start
        self.end = len(data) if end is None else end

    def more(self) -> bool:
        return self.pos < self.end

    def varint(self) -> int:
        shift = 0
        result = 0
        while True:
            if self.pos >= self.end:
                raise ExportError("truncated protobuf varint in a tf.train.Example")
            byte = self.data[self.pos]
            self.pos += 1
            result |= (byte & 0x7F) << shift
            if byte < 0x80:
                return result
            shift += 7
            if shift > 63:
                raise ExportError("protobuf varint longer than 10 bytes in a tf.train.Example")

    def tag(self) -> tuple[int, int]:
        key = self.varint()
        return key >> 3, key & 7

    def sub(self) -> _Reader:
        """The length-delimited field at the cursor, as its own reader; the cursor moves past it."""
        size = self.varint()
        start = self.pos
        self.pos += size
        if self.pos > self.end:
            raise ExportError("truncated length-delimited field in a tf.train.Example")
        return _Reader(self.data, start, self.pos)

    def raw(self) -> memoryview:
        sub = self.sub()
        return sub.data[sub.pos : sub.end]

    def skip(self, wire: int) -> None:
        if wire == _VARINT:
            self.varint()
        elif wire == _I64:
            self.pos += 8
        elif wire == _LEN:
            self.sub()
        elif wire == _I32:
            self.pos += 4
        else:
            raise ExportError(f"unsupported protobuf wire type {wire} in a tf.train.Example")


def _signed(value: int) -> int:
    return value - (1 << 64) if value >= 1 << 63 else value


def _decode_list(kind: FeatureKind, msg: _Reader) -> Feature:
    if kind == "bytes":
        items: list[bytes] = []
        while msg.more():
            field, wire = msg.tag()
            if field == 1 and wire == _LEN:
                items.append(bytes(msg.raw()))
            else:
                msg.skip(wire)
        return Feature("bytes", items)
    chunks: list[npt.NDArray[np.generic]] = []
    while msg.more():
        field, wire = msg.tag()
        if field != 1:
            msg.skip(wire)
        elif kind == "float" and wire == _LEN:  # packed (what every writer emits)
            chunks.append(np.frombuffer(msg.raw(), dtype="<f4"))
        elif kind == "float" and wire == _I32:  # unpacked
            chunks.append(np.frombuffer(msg.data[msg.pos : msg.pos + 4], dtype="<f4"))
            msg.pos += 4
        elif kind == "int64" and wire == _LEN:
            packed = msg.sub()
            ints = []
            while packed.more():
                ints.append(_signed(packed.varint()))
            chunks.append(np.asarray(ints, dtype=np.int64))
        elif kind == "int64" and wire == _VARINT:
            chunks.append(np.asarray([_signed(msg.varint())], dtype=np.int64))
        else:
            msg.skip(wire)
    if kind == "float":
        floats = np.concatenate(chunks).astype(np.float32) if chunks else np.empty(0, np.float32)
        return Feature("float", floats)
    ints64 = np.concatenate(chunks).astype(np.int64) if chunks else np.empty(0, np.int64)
    return Feature("int64", ints64)


def _decode_feature(msg: _Reader) -> Feature:
    found: Feature | None = None
    while msg.more():
        field, wire = msg.tag()
        kind = _FIELD_KIND.get(field)
        if kind is not None and wire == _LEN:
            found = _decode_list(kind, msg.sub())
        else:
            msg.skip(wire)
    # A Feature with no list set is an empty list of unknown kind; TensorFlow reads it as empty.
    return found if found is not None else Feature("bytes", [])


def decode_example(data: bytes) -> dict[str, Feature]:
    """Feature key → :class:`Feature` of a serialized ``tf.train.Example``.

    Raises:
        ExportError: The bytes are not a well-formed Example.
    """
    top = _Reader(memoryview(data))
    out: dict[str, Feature] = {}
    while top.more():
        field, wire = top.tag()
        if field != 1 or wire != _LEN:
            top.skip(wire)
            continue
        features = top.sub()
        while features.more():
            f_field, f_wire = features.tag()
            if f_field != 1 or f_wire != _LEN:
                features.skip(f_wire)
                continue
            entry = features.sub()
            key = ""
            value = Feature("bytes", [])
            while entry.more():
                e_field, e_wire = entry.tag()
                if e_field == 1 and e_wire == _LEN:
                    key = bytes(entry.raw()).decode()
                elif e_field == 2 and e_wire == _LEN:
                    value = _decode_feature(entry.sub())
                else:
                    entry.skip(e_wire)
            out[key] = value
    return out


# -- TFRecord framing ----------------------------------------------------------------------------


class TFRecordWriter:
    """Appends records to one TFRecord file; ``close()`` flushes and fsyncs it (idempotent).

    Use as a context manager. ``bytes_written`` is the file size so far [bytes].
    """

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self._file: BinaryIO | None = None
        self.bytes_written = 0
        self.records = 0

    def __enter__(self) -> TFRecordWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def write(self, data: bytes | Encoded) -> None:
        """Append one record (its length, the masked CRCs, the data)."""
        if self._file is None:
            if self.records:
                raise ExportError(f"{self.path}: write after close")
            self._file = self.path.open("wb")
        record = data if isinstance(data, Encoded) else _plain(data)
        header = struct.pack("<Q", record.size)
        crc = 0
        for part in record.parts:
            crc = google_crc32c.extend(crc, part)
        self._file.write(header)
        self._file.write(struct.pack("<I", masked_crc32c(header)))
        self._file.writelines(record.parts)
        self._file.write(struct.pack("<I", _mask(crc)))
        self.bytes_written += record.size + 16
        self.records += 1

    def close(self) -> None:
        """Flush the file to disk (fsync) and close it."""
        if self._file is None:
            return
        self._file.flush()
        os.fsync(self._file.fileno())
        self._file.close()
        self._file = None


def read_records(path: Path) -> Iterator[bytes]:
    """Yield every record of a TFRecord file, checking both CRCs of each.

    Raises:
        ExportError: One line naming the file and the record that is truncated or corrupt.
    """
    with Path(path).open("rb") as f:
        index = 0
        while True:
            header = f.read(12)
            if not header:
                return
            if len(header) < 12:
                raise ExportError(f"{path}: record {index} is truncated (header); re-export this shard")
            (length,) = struct.unpack_from("<Q", header)
            (length_crc,) = struct.unpack_from("<I", header, 8)
            if masked_crc32c(header[:8]) != length_crc:
                raise ExportError(f"{path}: record {index} has a corrupt length; re-export this shard")
            data = f.read(length)
            footer = f.read(4)
            if len(data) < length or len(footer) < 4:
                raise ExportError(f"{path}: record {index} is truncated; re-export this shard")
            if masked_crc32c(data) != struct.unpack("<I", footer)[0]:
                raise ExportError(f"{path}: record {index} fails its CRC; re-export this shard")
            yield data
            index += 1
