"""A control tick's Bundle: the hand-written encoder against protobuf's, and garbage to the decoder."""

from __future__ import annotations

import os

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from telerig.errors import WireError
from telerig.ir import wire
from telerig.ir._pb import ir_pb2
from telerig.ir.types import JointState, Stamp

_NAMES = st.text(alphabet="abcdefghijklmnopqrstuvwxyz0123456789_.-", min_size=1, max_size=64)


def _protobuf(parts: list[tuple[str, bytes]]) -> bytes:
    bundle = ir_pb2.Bundle(schema_version=wire.SCHEMA_VERSION)
    for stream, envelope in parts:
        bundle.parts.add(stream=stream, envelope=envelope)
    return bundle.SerializeToString()


def test_the_bytes_of_a_small_bundle() -> None:
    # Field 1 varint 1; field 2 (a part of 6 bytes): field 1 "x", field 2 the byte 0x01.
    assert wire.encode_bundle([("x", b"\x01")]) == bytes.fromhex("0801" + "1206" + "0a0178" + "120101")


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(_NAMES, st.binary(min_size=1, max_size=3000)), max_size=wire.MAX_BUNDLE_PARTS))
def test_the_encoder_writes_what_protobuf_writes(parts: list[tuple[str, bytes]]) -> None:
    # Lengths up to 3000 bytes need two-byte varints; protobuf leaves an empty bytes field out, so
    # every envelope has a byte at least (an Envelope is never empty).
    data = wire.encode_bundle(parts)
    assert data == _protobuf(parts)
    if parts:
        assert wire.decode_bundle(data) == parts


def test_a_tick_of_real_samples_round_trips() -> None:
    t = 1_700_000_000_000_000_000
    state = JointState(Stamp("arm0", 7, t, t), ("a", "b"), np.array([0.1, 0.2]), np.zeros(2))
    parts = [("joint_state", wire.encode(state)), ("wrench", b"\x08\x01")]
    (stream, envelope), second = wire.decode_bundle(wire.encode_bundle(parts))
    assert stream == "joint_state"
    decoded = wire.decode(envelope)
    assert isinstance(decoded, JointState)
    assert decoded.stamp == state.stamp
    np.testing.assert_array_equal(decoded.positions, state.positions)
    assert second == ("wrench", b"\x08\x01")


def test_the_encoder_refuses_what_the_decoder_would() -> None:
    with pytest.raises(ValueError, match="at most 64 parts"):
        wire.encode_bundle([("x", b"1")] * (wire.MAX_BUNDLE_PARTS + 1))
    for name in ("", "a/b", "x" * 65, "joint state", "#"):
        with pytest.raises(ValueError, match="is not a topic level"):
            wire.encode_bundle([(name, b"1")])


@pytest.mark.parametrize(
    ("data", "error"),
    [
        (b"", "schema_version 0"),
        (b"\x08\x01", "carries 1 to 64 parts, this one 0"),
        (_protobuf([("x", b"1")])[2:], "schema_version 0"),
        (b"\x08\x02" + _protobuf([("x", b"1")])[2:], "schema_version 2"),
        (_protobuf([("x", b"1")])[:-1], "truncated or not protobuf"),
        (b"\xff" * 16, "truncated or not protobuf"),
        (_protobuf([("x", b"1")] * 65), "this one 65"),
        (_protobuf([("a/b", b"1")]), "'a/b' is not a topic level"),
        (_protobuf([("", b"1")]), "'' is not a topic level"),
        (_protobuf([("x" * 100_000, b"1")]), "is not a topic level"),
    ],
)
def test_garbage_fails_with_one_line(data: bytes, error: str) -> None:
    with pytest.raises(WireError, match=error) as info:
        wire.decode_bundle(data)
    assert "\n" not in str(info.value)


def test_random_bytes_never_crash_the_decoder() -> None:
    rng = np.random.default_rng(5)
    for _ in range(3000):
        data = os.urandom(int(rng.integers(0, 400)))
        try:
            parts = wire.decode_bundle(data)
        except WireError:
            continue
        assert 0 < len(parts) <= wire.MAX_BUNDLE_PARTS
