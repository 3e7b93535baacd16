"""Reading float32 fields from untrusted device bytes without floating-point warnings."""

from __future__ import annotations

import numpy as np

from telerig.ir.types import FloatArray

__all__ = ["f32_to_f64"]


def f32_to_f64(values: np.ndarray) -> FloatArray:
    """Cast float32 wire values to float64.

    A signalling NaN from a peer makes the cast raise numpy's "invalid value" warning (an
    exception where warnings are errors); it becomes a quiet NaN here instead, which the
    parser's finite/range checks then reject like any other NaN.
    """
    with np.errstate(invalid="ignore"):
        return values.astype(np.float64)
