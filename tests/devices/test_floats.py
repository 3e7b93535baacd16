"""Signalling NaNs from device bytes never raise: they become NaN and the parsers reject them."""

from __future__ import annotations

import numpy as np
import pytest

from telerig.devices.floats import f32_to_f64
from telerig.devices.markerless.fake import typical_payload as markerless_payload
from telerig.devices.markerless.protocol import FUZZ_TARGET as MARKERLESS_FUZZ
from telerig.devices.webxr.fake import typical_payload as webxr_payload
from telerig.devices.webxr.protocol import FUZZ_TARGET as WEBXR_FUZZ
from telerig.errors import WireError

SIGNALLING_NAN = bytes.fromhex("0100807f")


def test_signalling_nan_casts_to_nan_without_a_warning() -> None:
    out = f32_to_f64(np.frombuffer(SIGNALLING_NAN + b"\x00\x00\x80\x3f", dtype="<f4"))
    assert np.isnan(out[0])
    assert out[1] == 1.0


@pytest.mark.parametrize(
    ("target", "payload", "offset"),
    [(WEBXR_FUZZ, webxr_payload(), -4), (MARKERLESS_FUZZ, markerless_payload(), 40)],
    ids=["webxr_hand_radius", "markerless_hand_landmark"],
)
def test_parsers_reject_a_signalling_nan_with_wire_error(target: object, payload: bytes, offset: int) -> None:
    data = bytearray(payload)
    end = offset + 4 if offset != -4 else None
    data[offset:end] = SIGNALLING_NAN
    with pytest.raises(WireError):
        target(bytes(data))  # type: ignore[operator]
