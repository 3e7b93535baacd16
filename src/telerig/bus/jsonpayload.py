"""JSON read from the bus, parsed defensively: bounded size and nesting, one ``WireError`` on any fault."""

from __future__ import annotations

import json
import re

from pydantic import JsonValue

from telerig.errors import WireError

__all__ = ["MAX_JSON_BYTES", "MAX_JSON_DEPTH", "json_depth", "parse_json", "parse_json_object"]

#: Default size limit of a JSON payload [bytes]: node state documents are a few KiB.
MAX_JSON_BYTES = 256 * 1024
#: Default nesting limit (objects and arrays). Our documents nest 4 deep at most; CPython's
#: ``json`` recurses once per level and raises ``RecursionError`` near 1000.
MAX_JSON_DEPTH = 32

# Tokens for the depth scan: an escape pair, a quote, a run of openers or of closers. Fixed-length
# alternatives, so the scan is linear (a string regex backtracked quadratically on '"\\"\\...').
_TOKENS = re.compile(rb'\\.|"|[\[{]+|[\]}]+', re.DOTALL)


def json_depth(data: bytes) -> int:
    """Deepest nesting of objects and arrays in ``data`` (0 for a scalar), counted without parsing.

    Brackets inside strings do not count; unbalanced input returns the deepest point reached.
    Linear in ``len(data)``.
    """
    depth = deepest = 0
    in_string = False
    for token in _TOKENS.finditer(data):
        first = data[token.start()]
        if first == 0x22:  # '"'
            in_string = not in_string
        elif in_string or first == 0x5C:  # bracket in a string, or an escape pair
            continue
        elif first in b"[{":
            depth += token.end() - token.start()
            deepest = max(deepest, depth)
        else:
            depth -= token.end() - token.start()
    return deepest


def parse_json(
    payload: bytes, *, max_bytes: int = MAX_JSON_BYTES, max_depth: int = MAX_JSON_DEPTH
) -> JsonValue:
    """Parse a UTF-8 JSON payload received from the bus.

    Args:
        payload: The message bytes.
        max_bytes: Largest accepted payload [bytes].
        max_depth: Deepest accepted nesting of objects and arrays.

    Raises:
        WireError: too large, too deeply nested, not UTF-8 or not JSON; the message says which
            (one line, for a counted drop; never a ``RecursionError``).
    """
    if len(payload) > max_bytes:
        raise WireError(f"JSON payload of {len(payload)} bytes is over the {max_bytes}-byte limit")
    # Fast path: fewer openers than the limit cannot nest deeper than it.
    openers = payload.count(b"[") + payload.count(b"{")
    depth = json_depth(payload) if openers > max_depth else 0
    if depth > max_depth:
        raise WireError(f"JSON payload nests {depth} levels deep; at most {max_depth} allowed")
    try:
        value: JsonValue = json.loads(payload)
    except UnicodeDecodeError:
        raise WireError("JSON payload is not UTF-8") from None
    except (ValueError, RecursionError) as exc:
        raise WireError(f"payload is not JSON ({str(exc).splitlines()[0][:120]})") from None
    return value


def parse_json_object(
    payload: bytes, *, max_bytes: int = MAX_JSON_BYTES, max_depth: int = MAX_JSON_DEPTH
) -> dict[str, JsonValue]:
    """Like :func:`parse_json`, and the value must be a JSON object.

    Raises:
        WireError: as :func:`parse_json`, or the value is not an object.
    """
    value = parse_json(payload, max_bytes=max_bytes, max_depth=max_depth)
    if not isinstance(value, dict):
        raise WireError(f"JSON payload is a {type(value).__name__}, not an object")
    return value
