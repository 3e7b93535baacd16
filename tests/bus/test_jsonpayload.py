"""The bus's JSON parser: bounded size and depth, one WireError for every kind of bad payload."""

from __future__ import annotations

import time

import pytest

from telerig.bus.jsonpayload import json_depth, parse_json, parse_json_object
from telerig.errors import WireError


def test_depth_counts_structure_not_brackets_in_strings() -> None:
    assert json_depth(b"1") == 0
    assert json_depth(b'{"a": [1, {"b": []}]}') == 4
    assert json_depth(b'{"text": "[[[[{{{{ \\" ]]"}') == 1


def test_deep_nesting_is_a_wire_error_not_a_recursion_error() -> None:
    with pytest.raises(WireError, match="levels deep"):
        parse_json(b"[" * 50_000 + b"]" * 50_000, max_bytes=1 << 20)
    with pytest.raises(WireError, match="levels deep"):
        parse_json(b'{"a":' * 40 + b"1" + b"}" * 40)


def test_size_utf8_and_syntax_are_checked() -> None:
    with pytest.raises(WireError, match="over the 10-byte limit"):
        parse_json(b'{"a": 12345678}', max_bytes=10)
    with pytest.raises(WireError, match="not UTF-8"):
        parse_json(b'"\xff"')
    with pytest.raises(WireError, match="not JSON"):
        parse_json(b"{not json")
    with pytest.raises(WireError, match="not an object"):
        parse_json_object(b"[1, 2]")
    assert parse_json_object(b'{"seq": 1, "nested": {"x": [1, 2]}}') == {"seq": 1, "nested": {"x": [1, 2]}}


@pytest.mark.parametrize(
    "payload",
    [b'"' + b"a" * 250_000, b'["' * 120_000, b'"\\' * 120_000, b"[" * 250_000],
    ids=["unterminated-string", "open-strings", "escapes", "brackets"],
)
def test_adversarial_payloads_at_the_size_limit_are_cheap(payload: bytes) -> None:
    start = time.perf_counter()
    with pytest.raises(WireError):
        parse_json(payload)
    assert time.perf_counter() - start < 1.0  # measured ~10 ms; a loose bound for a loaded CI box
