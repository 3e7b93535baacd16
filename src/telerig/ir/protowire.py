"""Protobuf's wire format written by hand, for the few messages whose bytes are cheaper to join than
to build through a message object: a control tick's Bundle (:mod:`telerig.ir.wire`) and TFRecord's
``tf.train.Example`` (:mod:`telerig.export.tfrecord`). Each writer is pinned against protobuf's own
serializer in its tests."""

from __future__ import annotations

__all__ = ["LEN", "len_field", "len_header", "varint"]

#: Wire type of a length-delimited field (bytes, string, embedded message, packed repeated).
LEN = 2
_U64 = 0xFFFFFFFFFFFFFFFF


def varint(value: int) -> bytes:
    """Base-128 varint of an int64 (negative values as their 10-byte two's complement)."""
    value &= _U64
    out = bytearray()
    while value > 0x7F:
        out.append((value & 0x7F) | 0x80)
        value >>= 7
    out.append(value)
    return bytes(out)


def len_header(field: int, size: int) -> bytes:
    """Tag and length of a length-delimited field of ``size`` bytes."""
    return varint((field << 3) | LEN) + varint(size)


def len_field(field: int, payload: bytes) -> bytes:
    """A whole length-delimited field: tag, length, ``payload``."""
    return len_header(field, len(payload)) + payload
