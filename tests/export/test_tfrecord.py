"""TFRecord framing and tf.train.Example encoding without TensorFlow, pinned to bytes TensorFlow wrote."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from telerig.errors import ExportError
from telerig.export.tfrecord import (
    TFRecordWriter,
    bytes_feature,
    crc32c,
    decode_example,
    encode_example,
    float_feature,
    int64_feature,
    masked_crc32c,
    read_records,
)

# tf.io.TFRecordWriter (TensorFlow 2.21) writing the records b"" and b"telerig".
TF_RECORDS = bytes.fromhex("000000000000000029039807d8ea82a20700000000000000bbd79f1174656c657269672bb0c3f0")
# tf.train.Example(features={'a': int64 [1, -1, 300], 'b': float [0.5], 'c': bytes [b'x', b'']})
# .SerializeToString() (TensorFlow 2.21; map entries in its order, c, a, b).
TF_EXAMPLE = bytes.fromhex(
    "0a350a0c0a016312070a050a01780a000a160a016112111a0f0a0d01ffffffffffffffffff01ac020a0d0a0162120812060a040000003f"
)


def test_crc32c_matches_the_castagnoli_check_value() -> None:
    assert crc32c(b"123456789") == 0xE3069283


def test_masked_crc_of_an_empty_length_header_matches_tensorflow() -> None:
    assert struct.pack("<I", masked_crc32c(b"\0" * 8)) == TF_RECORDS[8:12]
    assert struct.pack("<I", masked_crc32c(b"")) == TF_RECORDS[12:16]


def test_writer_produces_the_bytes_tensorflow_writes(tmp_path: Path) -> None:
    path = tmp_path / "v.tfrecord"
    with TFRecordWriter(path) as writer:
        writer.write(b"")
        writer.write(b"telerig")
    assert path.read_bytes() == TF_RECORDS
    assert writer.bytes_written == len(TF_RECORDS)
    assert list(read_records(path)) == [b"", b"telerig"]


def test_writer_checksums_an_example_written_in_parts(tmp_path: Path) -> None:
    example = encode_example({"c": bytes_feature([b"x", b""]), "a": int64_feature([1, -1, 300])})
    path = tmp_path / "e.tfrecord"
    with TFRecordWriter(path) as writer:
        writer.write(example)
    assert list(read_records(path)) == [bytes(example)]


def test_reader_names_a_truncated_record(tmp_path: Path) -> None:
    path = tmp_path / "t.tfrecord"
    path.write_bytes(TF_RECORDS[:-3])
    with pytest.raises(ExportError, match="record 1 is truncated"):
        list(read_records(path))


def test_reader_names_a_corrupt_record(tmp_path: Path) -> None:
    path = tmp_path / "c.tfrecord"
    path.write_bytes(TF_RECORDS.replace(b"telerig", b"telerog"))
    with pytest.raises(ExportError, match="record 1 fails its CRC"):
        list(read_records(path))


def test_encoder_produces_the_example_tensorflow_serializes() -> None:
    encoded = encode_example(
        {
            "c": bytes_feature([b"x", b""]),
            "a": int64_feature([1, -1, 300]),
            "b": float_feature(np.array([0.5], np.float32)),
        }
    )
    assert bytes(encoded) == TF_EXAMPLE
    assert encoded.size == len(TF_EXAMPLE)


def test_decoder_reads_the_example_tensorflow_serializes() -> None:
    decoded = decode_example(TF_EXAMPLE)
    assert decoded["c"].as_bytes("c") == [b"x", b""]
    assert decoded["a"].as_array("a", "int64").tolist() == [1, -1, 300]
    assert decoded["b"].as_array("b", "float").tolist() == [0.5]


def test_round_trip_keeps_empty_lists_and_large_values() -> None:
    floats = np.random.default_rng(0).normal(size=(7, 3)).astype(np.float32)
    encoded = encode_example(
        {
            "empty_bytes": bytes_feature([]),
            "empty_floats": float_feature(np.empty(0, np.float32)),
            "ns": int64_feature(np.array([1_795_640_590_254_767_832, -(2**63)], np.int64)),
            "floats": float_feature(floats),
            "flags": int64_feature(np.array([True, False])),
        }
    )
    decoded = decode_example(bytes(encoded))
    assert decoded["empty_bytes"].as_bytes("empty_bytes") == []
    assert decoded["empty_floats"].as_array("empty_floats", "float").size == 0
    assert decoded["ns"].as_array("ns", "int64").tolist() == [1_795_640_590_254_767_832, -(2**63)]
    np.testing.assert_array_equal(decoded["floats"].as_array("floats", "float"), floats.ravel())
    assert decoded["flags"].as_array("flags", "int64").tolist() == [1, 0]


def test_feature_of_another_kind_is_one_line_naming_the_key() -> None:
    decoded = decode_example(TF_EXAMPLE)
    with pytest.raises(ExportError, match="feature 'a' holds int64 values, expected float"):
        decoded["a"].as_array("a", "float")
