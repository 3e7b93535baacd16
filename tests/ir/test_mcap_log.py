"""MCAP episode log: standard readers open it, the embedded schema decodes it, crashes lose little."""

from __future__ import annotations

import shutil
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from telerig.errors import RecordingError
from telerig.ir import wire
from telerig.ir.mcap_log import (
    LogEntry,
    McapLog,
    control_source_from_json,
    read_control_sources,
    read_json,
    read_log,
)
from telerig.ir.types import ControllerState, ControlSource, GripperCommand, Stamp

CTRL = "telerig/v1/test/vr0/controller_right"
GRIP = "telerig/v1/test/control/gripper"


def _controller(i: int) -> ControllerState:
    return ControllerState(
        Stamp("vr0/right", i, device_ns=10 * i, capture_ns=1_000_000 + 10_000_000 * i),
        "right",
        (0.01 * i, 0.0, 1.0),
        (1.0, 0.0, 0.0, 0.0),
        "operator",
        frozenset({"a"}) if i % 2 else frozenset(),
        trigger=i / 100,
        joystick=(0.0, 0.5),
    )


def _write(log: McapLog, n: int) -> list[LogEntry]:
    """Write n controller samples and n // 2 gripper commands; return what was written."""
    written = []
    for i in range(n):
        samples = [(CTRL, _controller(i))]
        if i % 2 == 0:
            samples.append((GRIP, GripperCommand(Stamp("control", i // 2, i, 2_000_000 + i), i / n)))
        for topic, s in samples:
            log_ns = s.stamp.capture_ns + 500
            log.write(topic, wire.encode(s), log_time_ns=log_ns, publish_time_ns=s.stamp.capture_ns)
            written.append(LogEntry(topic, s, log_ns, s.stamp.capture_ns))
    return written


def _same(a: LogEntry, b: LogEntry) -> bool:
    return (
        a.topic == b.topic
        and a.log_time_ns == b.log_time_ns
        and wire.encode(a.sample) == wire.encode(b.sample)
    )


def test_standard_reader_sees_schema_channels_and_messages(tmp_path: Path) -> None:
    path = tmp_path / "ep.mcap"
    with McapLog(path) as log:
        written = _write(log, 10)
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        assert [s.name for s in summary.schemas.values()] == [wire.ENVELOPE_SCHEMA_NAME]
        assert {s.encoding for s in summary.schemas.values()} == {"protobuf"}
        assert {c.topic: c.message_encoding for c in summary.channels.values()} == {
            CTRL: "protobuf",
            GRIP: "protobuf",
        }
        assert summary.statistics is not None
        assert summary.statistics.message_count == len(written)
        assert {c.compression for c in summary.chunk_indexes} == {"zstd"}
        messages = list(reader.iter_messages(log_time_order=False))
    assert [m.data for _, _, m in messages] == [wire.encode(e.sample) for e in written]
    assert [m.publish_time for _, _, m in messages] == [e.publish_time_ns for e in written]


def test_embedded_schema_decodes_with_mcap_protobuf(tmp_path: Path) -> None:
    import mcap_protobuf.decoder as decoder_mod  # a dev dependency: a missing one fails the test

    path = tmp_path / "ep.mcap"
    with McapLog(path) as log:
        written = _write(log, 4)
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[decoder_mod.DecoderFactory()])
        decoded = [d.decoded_message for d in reader.iter_decoded_messages(log_time_order=False)]
    assert len(decoded) == len(written)
    first = decoded[0]
    assert first.DESCRIPTOR.full_name == wire.ENVELOPE_SCHEMA_NAME
    assert first.WhichOneof("body") == "controller_state"
    assert first.stamp.source_id == "vr0/right"
    assert list(first.controller_state.orientation) == [1.0, 0.0, 0.0, 0.0]
    for msg, entry in zip(decoded, written, strict=True):
        assert wire.encode(wire.decode(msg.SerializeToString())) == wire.encode(entry.sample)


def test_read_log_returns_samples_and_times(tmp_path: Path) -> None:
    path = tmp_path / "ep.mcap"
    with McapLog(path) as log:
        written = _write(log, 20)
    got = list(read_log(path))
    assert len(got) == len(written)
    assert all(_same(a, b) for a, b in zip(got, written, strict=True))
    assert [e.publish_time_ns for e in got] == [e.publish_time_ns for e in written]
    np.testing.assert_array_equal(got[3].sample.position, written[3].sample.position)  # type: ignore[union-attr]


def test_read_log_filters_topics(tmp_path: Path) -> None:
    path = tmp_path / "ep.mcap"
    with McapLog(path) as log:
        _write(log, 10)
    assert {e.topic for e in read_log(path, topics=[GRIP])} == {GRIP}
    assert len(list(read_log(path, topics=[GRIP]))) == 5


def test_stats_count_messages_and_times_per_topic(tmp_path: Path) -> None:
    with McapLog(tmp_path / "ep.mcap") as log:
        _write(log, 10)
        stats = log.stats()
    ctrl = stats[CTRL]
    assert ctrl.count == 10
    assert ctrl.first_publish_ns == 1_000_000
    assert ctrl.last_publish_ns == 1_000_000 + 90_000_000
    assert ctrl.last_log_ns == ctrl.last_publish_ns + 500
    assert stats[GRIP].count == 5


def test_json_state_streams_get_their_own_channel(tmp_path: Path) -> None:
    path = tmp_path / "ep.mcap"
    status = "telerig/v1/test/coordinator/status"
    with McapLog(path) as log:
        written = _write(log, 2)
        log.write_json(status, b'{"state": "recording"}', log_time_ns=5)
        with pytest.raises(RecordingError, match="json channel"):
            log.write(status, b"", log_time_ns=6, publish_time_ns=6)
    with open(path, "rb") as f:
        found = [
            (c.topic, c.message_encoding, c.schema_id, m.data) for _, c, m in make_reader(f).iter_messages()
        ]
    assert (status, "json", 0, b'{"state": "recording"}') in found
    assert len(list(read_log(path))) == len(written)


def test_close_is_idempotent_and_write_after_close_fails(tmp_path: Path) -> None:
    log = McapLog(tmp_path / "ep.mcap")
    log.close()
    log.close()
    assert log.closed
    with pytest.raises(RecordingError, match="closed"):
        log.write(CTRL, b"", log_time_ns=0, publish_time_ns=0)


def test_existing_file_is_never_overwritten(tmp_path: Path) -> None:
    path = tmp_path / "ep.mcap"
    path.write_bytes(b"precious")
    with pytest.raises(RecordingError, match="already exists"):
        McapLog(path)
    assert path.read_bytes() == b"precious"


def test_concurrent_writers_lose_nothing(tmp_path: Path) -> None:
    path = tmp_path / "ep.mcap"
    payload = wire.encode(_controller(1))
    with McapLog(path, chunk_size=4096) as log:

        def worker(k: int) -> None:
            for i in range(300):
                log.write(f"telerig/v1/t/n{k}/s", payload, log_time_ns=i, publish_time_ns=i)

        threads = [threading.Thread(target=worker, args=(k,)) for k in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert sum(s.count for s in log.stats().values()) == 1200
    assert len(list(read_log(path))) == 1200


def test_copy_of_open_log_recovers_flushed_messages(tmp_path: Path) -> None:
    path, crash = tmp_path / "ep.mcap", tmp_path / "crash.mcap"
    with McapLog(path) as log:
        written = _write(log, 30)
        log.flush()
        _write(log, 5)  # still buffered: lost in the "crash"
        shutil.copy(path, crash)
    got = list(read_log(crash))
    assert len(got) == len(written)
    assert all(_same(a, b) for a, b in zip(got, written, strict=True))


def test_background_flush_reaches_the_file_without_writes(tmp_path: Path) -> None:
    path, crash = tmp_path / "ep.mcap", tmp_path / "crash.mcap"
    with McapLog(path, flush_interval_s=0.05) as log:
        written = _write(log, 3)
        size = path.stat().st_size
        deadline = time.monotonic() + 5.0
        while path.stat().st_size == size and time.monotonic() < deadline:
            time.sleep(0.01)
        shutil.copy(path, crash)
    assert len(list(read_log(crash))) == len(written)


def test_truncated_log_yields_a_prefix_of_the_messages(tmp_path: Path) -> None:
    path = tmp_path / "ep.mcap"
    with McapLog(path, chunk_size=1024) as log:
        written = _write(log, 60)
    data = path.read_bytes()
    cut_path = tmp_path / "cut.mcap"
    counts = []
    for cut in [0, 4, 100, *range(1000, len(data), 997), len(data) - 1]:
        cut_path.write_bytes(data[:cut])
        got = list(read_log(cut_path))
        assert all(_same(a, b) for a, b in zip(got, written, strict=False))
        counts.append(len(got))
    assert counts == sorted(counts)
    assert 0 < counts[len(counts) // 2] < len(written)
    assert counts[-1] == len(written)


def test_non_mcap_file_is_rejected(tmp_path: Path) -> None:
    path = tmp_path / "x.mcap"
    path.write_bytes(b"not an mcap file at all")
    with pytest.raises(RecordingError, match="not an MCAP file"):
        list(read_log(path))


def test_missing_file_is_named(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match=r"nope\.mcap"):
        list(read_log(tmp_path / "nope.mcap"))


def test_read_json_skips_a_deeply_nested_message_of_an_old_episode(tmp_path: Path) -> None:
    """Episodes recorded before the recorder bounded JSON may hold 100 000-deep JSON (a forged clock_pong)."""
    path = tmp_path / "old.mcap"
    with McapLog(path) as log:
        log.write_json("telerig/v1/rig/st0/clock_pong", b"[" * 100_000 + b"]" * 100_000, log_time_ns=1)
        log.write_json("telerig/v1/rig/st0/clock_pong", b'{"seq": 1}', log_time_ns=2)
    assert [value for _, value, _ in read_json(path)] == [{"seq": 1}]


CONTROL = "telerig/v1/test/arm0/control_source"
CONTROL_1 = "telerig/v1/test/arm1/control_source"  # a topic is one channel: JSON or protobuf


def test_control_sources_read_the_typed_stream_and_the_json_of_older_episodes(tmp_path: Path) -> None:
    typed = [
        ControlSource(Stamp("arm0", 1, 10, 10), None, "none", "auto"),
        ControlSource(Stamp("arm0", 2, 20, 20), "pi0", "policy", "auto"),
        ControlSource(Stamp("arm0", 3, 30, 30), "vr0", "paused", "operator"),
    ]
    legacy = [  # what telerig recorded before control_source was typed
        b'{"capture_ns": 10, "source": null, "kind": null, "mode": "auto"}',
        b'{"capture_ns": 20, "source": "pi0", "kind": "policy", "mode": "auto"}',
        b'{"capture_ns": 25, "source": "home", "kind": "home", "mode": "policy"}',
        b'{"capture_ns": 30, "source": "vr0", "kind": "operator"}',  # no mode: auto
    ]
    new, old = tmp_path / "new.mcap", tmp_path / "old.mcap"
    with McapLog(new) as log:
        for c in typed:
            ns = c.stamp.capture_ns
            log.write(CONTROL, wire.encode(c), log_time_ns=ns + 1, publish_time_ns=ns)
        log.write(
            GRIP, wire.encode(GripperCommand(Stamp("g", 1, 0, 0), 0.5)), log_time_ns=1, publish_time_ns=0
        )
    with McapLog(old) as log:
        for i, payload in enumerate(legacy):
            log.write_json(CONTROL, payload, log_time_ns=100 + i)
    got_new = list(read_control_sources(new, [CONTROL]))
    assert [(t, s, ns) for t, s, ns in got_new] == [(CONTROL, c, c.stamp.capture_ns + 1) for c in typed]
    got_old = [
        (s.source, s.kind, s.mode, s.stamp.capture_ns, s.stamp.seq)
        for _, s, _ in read_control_sources(old, [CONTROL])
    ]
    assert got_old == [
        (None, "none", "auto", 10, 1),
        ("pi0", "policy", "auto", 20, 2),
        ("home", "home", "policy", 25, 3),
        ("vr0", "operator", "auto", 30, 4),
    ]
    assert all(s.stamp.source_id == "arm0" for _, s, _ in read_control_sources(old, [CONTROL]))


@pytest.mark.parametrize(
    "value",
    [
        None,
        [],
        "policy",
        {},
        {"capture_ns": "10", "source": "pi0", "kind": "policy", "mode": "auto"},
        {"capture_ns": True, "source": "pi0", "kind": "policy", "mode": "auto"},
        {"capture_ns": 1.5, "source": "pi0", "kind": "policy", "mode": "auto"},
        {"capture_ns": 1, "source": "pi0", "kind": "driver", "mode": "auto"},
        {"capture_ns": 1, "source": "pi0", "kind": ["policy"], "mode": "auto"},
        {"capture_ns": 1, "source": "pi0", "kind": "policy", "mode": {"a": 1}},
        {"capture_ns": 1, "source": "pi0", "kind": "policy", "mode": "manual"},
        {"capture_ns": 1, "source": 7, "kind": "policy", "mode": "auto"},
        {"capture_ns": 1, "source": "", "kind": "policy", "mode": "auto"},
        {"capture_ns": 1, "source": "pi0", "kind": None, "mode": "auto"},
        {"capture_ns": 1, "source": None, "kind": "policy", "mode": "auto"},
    ],
)
def test_a_malformed_legacy_control_source_is_none(value: object) -> None:
    assert control_source_from_json(value, "arm0", 1) is None  # type: ignore[arg-type]


def test_malformed_control_source_messages_are_counted_and_left_out(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "ep.mcap"
    good = ControlSource(Stamp("arm0", 1, 5, 5), "pi0", "policy", "auto")
    with McapLog(path) as log:
        log.write_json(CONTROL, b'{"capture_ns": 1, "kind": "driver"}', log_time_ns=1)
        log.write_json(CONTROL, b"[" * 100_000 + b"]" * 100_000, log_time_ns=2)
        log.write_json(CONTROL, b"not json", log_time_ns=3)
        log.write_json(
            CONTROL, b'{"capture_ns": 4, "source": "vr0", "kind": "operator", "mode": "auto"}', log_time_ns=4
        )
        other = GripperCommand(Stamp("arm1", 1, 5, 5), 0.5)  # an Envelope of another type
        log.write(CONTROL_1, wire.encode(other), log_time_ns=5, publish_time_ns=5)
        log.write(CONTROL_1, wire.encode(good), log_time_ns=6, publish_time_ns=5)
    with caplog.at_level("WARNING"):
        got = list(read_control_sources(path, [CONTROL, CONTROL_1]))
    assert [(s.source, s.kind) for _, s, _ in got] == [("vr0", "operator"), ("pi0", "policy")]
    assert "4 control_source messages are not control sources" in caplog.text
