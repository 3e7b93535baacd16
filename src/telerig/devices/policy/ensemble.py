"""Temporal ensembling of action chunks (ACT, Zhao et al. 2023, section 3.3).

A chunking policy asked every tick predicts each future tick's action several times, once in every
chunk that still covers it. Sending the weighted mean of those predictions instead of one chunk's
smooths the motion: where one chunk jitters a few milliradians per tick (which a still-arm check
sees as motion), the mean of up to ``chunk`` overlapping predictions does not, and a switch between
chunks never steps. ACT weights the prediction made ``i`` chunks ago by ``exp(-k * i)``
counting from the oldest, so older predictions weigh more and a new one joins gradually (``k``
0.01 per tick in ACT). A tick whose inference was late still gets an action from the chunks already
there.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np
import numpy.typing as npt

__all__ = ["TemporalEnsemble"]


class TemporalEnsemble:
    """The weighted mean, per tick, of every live chunk's prediction for that tick.

    Args:
        k: Weight decay per chunk [1/tick] (> 0, finite): the prediction of the ``i``-th oldest
            live chunk weighs ``exp(-k * i)``.
    """

    def __init__(self, k: float) -> None:
        if not (math.isfinite(k) and k > 0):
            raise ValueError(f"temporal ensemble k must be a finite number > 0, got {k}")
        self.k = k
        self._tick = 0
        self._chunks: deque[tuple[int, npt.NDArray[np.float64]]] = deque()  # (first tick, chunk)

    def add(self, chunk: npt.NDArray[np.float64]) -> None:
        """A chunk predicted now: its first action is for the current tick. Shape (T, A)."""
        self._chunks.append((self._tick, np.asarray(chunk, dtype=np.float64)))

    def next(self) -> npt.NDArray[np.float64] | None:
        """This tick's action (None when no live chunk covers it); then advance one tick."""
        tick = self._tick
        self._tick += 1
        while self._chunks and tick - self._chunks[0][0] >= len(self._chunks[0][1]):
            self._chunks.popleft()  # oldest first: a chunk that expired before a newer one goes first
        live = [c[tick - t0] for t0, c in self._chunks if tick - t0 < len(c)]
        if not live:
            return None
        weights = np.exp(-self.k * np.arange(len(live)))
        return np.asarray(weights @ np.stack(live) / weights.sum(), dtype=np.float64)

    def clear(self) -> None:
        """Forget every chunk (the policy stopped acting or was handed the robot anew)."""
        self._chunks.clear()
