"""The residual reader: typed RetargetResidual streams and the JSON objects of earlier episodes read
alike, garbage counted and left out (issue 18: the residual stopped being per-tick JSON)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from telerig.bus.catalogue import RESIDUAL
from telerig.errors import WireError
from telerig.ir import wire
from telerig.ir.mcap_log import (
    RESIDUAL_STREAM,
    McapLog,
    decode_residual,
    read_residuals,
    residual_from_json,
)
from telerig.ir.types import ControlSource, JointState, RetargetResidual, Stamp

ARM = "telerig/v1/test/arm0/residual"
G1 = "telerig/v1/test/g1/residual"
OLD = "telerig/v1/test/arm1/residual"


def _typed(seq: int, t: int, flagged: bool = False, error: float = 0.01) -> RetargetResidual:
    return RetargetResidual(
        Stamp("arm0", seq, t, t), flagged, ("position_error_m", "orientation_error_rad"), (error, 0.2)
    )


def _old_json(capture_ns: int, flagged: bool, **metrics: float) -> bytes:
    """What the control node published before issue 18, verbatim (``json.dumps`` of the record)."""
    record: dict[str, float | int | bool] = {"capture_ns": capture_ns, "flagged": flagged}
    record.update(metrics)
    return json.dumps(record).encode()


def test_the_reader_finds_the_catalogue_stream() -> None:
    assert RESIDUAL_STREAM == RESIDUAL


def test_typed_and_old_json_residuals_read_alike(tmp_path: Path) -> None:
    path = tmp_path / "ep.mcap"
    typed = [_typed(1, 100), _typed(2, 200, flagged=True, error=0.08)]
    with McapLog(path) as log:
        for r in typed:
            log.write(
                ARM, wire.encode(r), log_time_ns=r.stamp.capture_ns + 5, publish_time_ns=r.stamp.capture_ns
            )
        log.write_json(
            OLD, _old_json(150, False, position_error_m=0.02, orientation_error_rad=0.3), log_time_ns=151
        )
        # The humanoid's residual before issue 18, with the NaN json.dumps wrote for an unmeasured time.
        log.write_json(
            G1, _old_json(250, True, right_wrist_error_m=0.06, ik_time_s=math.nan), log_time_ns=252
        )
        log.write_json(OLD, b'{"flagged": true, "position_error_m": 0.5}', log_time_ns=300)  # no capture_ns
        # Streams that are not residuals are not read: another robot's status, a control_source.
        log.write_json("telerig/v1/test/arm0/status", b'"ok"', log_time_ns=1)
        source = ControlSource(Stamp("arm0", 1, 5, 5), "vr0", "operator", "auto")
        log.write(
            "telerig/v1/test/arm0/control_source", wire.encode(source), log_time_ns=5, publish_time_ns=5
        )
    got = list(read_residuals(path))
    assert [(t, ns) for t, _, ns in got] == [(ARM, 105), (ARM, 205), (OLD, 151), (G1, 252), (OLD, 300)]
    assert [r for t, r, _ in got if t == ARM] == typed
    old = [r for t, r, _ in got if t != ARM]
    assert [(r.stamp.source_id, r.stamp.seq, r.stamp.capture_ns, r.flagged) for r in old] == [
        ("arm1", 1, 150, False),
        ("g1", 1, 250, True),
        ("arm1", 2, 300, True),  # the log time stands in for the missing capture time
    ]
    assert old[0].metrics() == {"position_error_m": 0.02, "orientation_error_rad": 0.3}
    assert old[1].names == ("right_wrist_error_m", "ik_time_s")
    assert math.isnan(old[1].get("ik_time_s"))
    # Only the topics asked for.
    assert [t for t, _, _ in read_residuals(path, [G1])] == [G1]
    assert list(read_residuals(path, [])) == []


@pytest.mark.parametrize(
    ("value", "expected"),
    [
        ({"capture_ns": 7, "flagged": True}, (7, True, {})),
        ({"capture_ns": 7, "flagged": "true", "a_m": 1}, (7, False, {"a_m": 1.0})),  # only JSON true flags
        ({"capture_ns": True, "a_m": 0.5}, (99, False, {"a_m": 0.5})),  # a bool is no time
        ({"capture_ns": -1, "a_m": 0.5}, (99, False, {"a_m": 0.5})),
        ({"capture_ns": 2**63, "a_m": 0.5}, (99, False, {"a_m": 0.5})),  # beyond int64
        ({"capture_ns": "7", "a_m": 0.5}, (99, False, {"a_m": 0.5})),
        ({"capture_ns": 7.5, "a_m": 0.5}, (99, False, {"a_m": 0.5})),
        # Values that are no numbers are left out; NaN, inf and 1e308 are kept as recorded.
        (
            {
                "capture_ns": 7,
                "s": "x",
                "b": False,
                "l": [1],
                "d": {"a": 1},
                "n": None,
                "": 1.0,
                "big": 10**400,
            },
            (7, False, {}),
        ),
        (
            {"capture_ns": 7, "nan_m": math.nan, "inf_m": math.inf, "max_m": 1e308, "int_m": 3},
            (7, False, {"nan_m": math.nan, "inf_m": math.inf, "max_m": 1e308, "int_m": 3.0}),
        ),
    ],
)
def test_old_json_fields(value: dict[str, object], expected: tuple[int, bool, dict[str, float]]) -> None:
    r = residual_from_json(value, "arm0", 4, 99)  # type: ignore[arg-type]
    assert r is not None
    capture, flagged, metrics = expected
    assert (r.stamp.capture_ns, r.stamp.device_ns, r.flagged, r.stamp.seq, r.stamp.source_id) == (
        capture,
        capture,
        flagged,
        4,
        "arm0",
    )
    got = r.metrics()
    assert list(got) == list(metrics)
    assert all(
        g == m or (math.isnan(g) and math.isnan(m))
        for g, m in zip(got.values(), metrics.values(), strict=True)
    )


@pytest.mark.parametrize("value", [None, [], [{"flagged": True}], "flagged", 1.5, True])
def test_old_json_that_is_no_object_is_none(value: object) -> None:
    assert residual_from_json(value, "arm0", 1, 0) is None  # type: ignore[arg-type]


def test_malformed_residual_messages_are_counted_and_left_out(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "ep.mcap"
    good = _typed(3, 300)
    data = wire.encode(good)
    with McapLog(path) as log:
        log.write(ARM, data[: len(data) // 2], log_time_ns=1, publish_time_ns=1)  # truncated
        log.write(ARM, b"\x00garbage", log_time_ns=2, publish_time_ns=2)
        state = JointState(Stamp("arm0", 1, 3, 3), ("j",), (0.0,), (0.0,))  # type: ignore[arg-type]
        log.write(ARM, wire.encode(state), log_time_ns=3, publish_time_ns=3)  # wrong type
        log.write(ARM, data, log_time_ns=4, publish_time_ns=300)
        log.write_json(OLD, b"[" * 100_000 + b"]" * 100_000, log_time_ns=5)  # nests past the recursion limit
        log.write_json(OLD, b"not json", log_time_ns=6)
        log.write_json(OLD, b"[1, 2]", log_time_ns=7)
        log.write_json(OLD, b'{"capture_ns": 8, "flagged": false, "position_error_m": 0.25}', log_time_ns=8)
    with caplog.at_level("WARNING"):
        got = list(read_residuals(path))
    assert [(t, r.stamp.capture_ns) for t, r, _ in got] == [(ARM, 300), (OLD, 8)]
    assert got[0][1] == good
    assert got[1][1].get("position_error_m") == 0.25
    assert "6 residual messages are not residuals" in caplog.text


def test_a_log_without_footer_yields_the_residuals_of_its_complete_chunks(tmp_path: Path) -> None:
    path = tmp_path / "crash.mcap"
    log = McapLog(path, chunk_size=512)
    for i in range(200):
        r = _typed(i + 1, 1000 + i)
        log.write(ARM, wire.encode(r), log_time_ns=1000 + i, publish_time_ns=1000 + i)
    log.flush()
    data = path.read_bytes()  # as a crash leaves it: no footer, the last chunk maybe torn
    (tmp_path / "torn.mcap").write_bytes(data[: len(data) - 40])
    log.close()
    got = [r.stamp.seq for _, r, _ in read_residuals(tmp_path / "torn.mcap")]
    assert len(got) > 100
    assert got == list(range(1, len(got) + 1))


@pytest.mark.parametrize(
    ("data", "json_form", "message"),
    [
        (b"\x00garbage", False, "cannot decode Envelope"),
        (
            wire.encode(ControlSource(Stamp("arm0", 1, 5, 5), "vr0", "operator", "auto")),
            False,
            "a ControlSource where a RetargetResidual belongs",
        ),
        (b"not json", True, "neither an Envelope nor JSON"),
        (b'["a"]', True, "residual JSON is a list, not an object"),
    ],
)
def test_decode_residual_names_what_is_wrong_in_one_line(data: bytes, json_form: bool, message: str) -> None:
    with pytest.raises(WireError, match=message) as info:
        decode_residual(data, json_form=json_form, source_id="arm0", seq=1, log_time_ns=0)
    assert "\n" not in str(info.value)


def test_decode_residual_reads_both_forms() -> None:
    typed = _typed(1, 10, flagged=True)
    assert decode_residual(wire.encode(typed), json_form=False, source_id="x", seq=9, log_time_ns=0) == typed
    old = decode_residual(
        _old_json(10, True, position_error_m=0.01), json_form=True, source_id="arm0", seq=1, log_time_ns=0
    )
    assert (old.flagged, old.metrics(), old.stamp.capture_ns) == (True, {"position_error_m": 0.01}, 10)
