"""Feature statistics as LeRobot 0.4 writes them: per episode, then aggregated over a dataset.

LeRobot's ``compute_stats`` gives every numeric feature ``min``, ``max``, ``mean``, ``std``
(population), ``count`` and the quantiles ``q01 q10 q50 q90 q99``; a camera's stats are per
channel over frames sampled from the episode (:func:`sample_indices`), strided down to about
150 px (:func:`downsample_factor`), scaled to [0, 1] and shaped (3, 1, 1). A dataset's stats are
the episodes' stats aggregated with :func:`aggregate` (count-weighted mean, pooled variance,
count-weighted quantiles, min of mins, max of maxes), as LeRobot's ``aggregate_stats`` does.

Two deliberate differences from LeRobot 0.4.4's code, neither visible in the file layout:
quantiles are exact (``np.quantile``'s linear rule, from a 256-bin histogram for images)
where LeRobot interpolates in a 5000-bin histogram, and image moments are computed in float64
where 0.4.4 squares ``uint8`` pixels and overflows (fixed in later LeRobot by a float cast).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

__all__ = [
    "QUANTILES",
    "STAT_KEYS",
    "ImageStats",
    "Stats",
    "aggregate",
    "downsample_factor",
    "sample_indices",
    "stats_to_json",
    "vector_stats",
]

#: Quantiles LeRobot computes, and their keys (``q01`` ... ``q99``).
QUANTILES: tuple[float, ...] = (0.01, 0.10, 0.50, 0.90, 0.99)
_QUANTILE_KEYS: tuple[str, ...] = tuple(f"q{round(q * 100):02d}" for q in QUANTILES)
#: Keys of one feature's stats, in LeRobot's order.
STAT_KEYS: tuple[str, ...] = ("min", "max", "mean", "std", "count", *_QUANTILE_KEYS)

#: One feature's statistics: stat key -> array (``count`` has shape (1,)).
Stats = dict[str, npt.NDArray[Any]]


def sample_indices(length: int) -> list[int]:
    """Frames of an episode that LeRobot samples for image stats.

    ``length**0.75`` frames, at least 100 (or all of a shorter episode), at most 10 000, evenly
    spread from the first frame to the last.

    Args:
        length: Frames in the episode; > 0.

    Returns:
        Sorted frame indices; every frame of an episode shorter than 100 frames.
    """
    minimum = min(100, length)
    count = max(minimum, min(int(length**0.75), 10_000))
    return [int(i) for i in np.round(np.linspace(0, length - 1, count)).astype(np.int64)]


def downsample_factor(height: int, width: int) -> int:
    """Pixel stride LeRobot applies to a frame before its stats: 1 under 300 px, else ~150 px left."""
    if max(height, width) < 300:
        return 1
    return int(width / 150) if width > height else int(height / 150)


def vector_stats(values: npt.NDArray[Any]) -> Stats:
    """Stats of a numeric feature over an episode.

    Args:
        values: Shape (F,) for a scalar feature or (F, D) for a vector; F >= 1. NaN entries (no
            sample) are left out of a column's stats.

    Returns:
        Stats with arrays of shape (1,) for a scalar feature, (D,) for a vector; ``min``/``max``
        keep an integer feature's integer type, the rest are float64.
    """
    data = values.reshape(len(values), -1)
    as_float = data.astype(np.float64)
    if np.isnan(as_float).any():
        return _nan_vector_stats(as_float, len(values))
    stats: Stats = {
        "min": data.min(axis=0),
        "max": data.max(axis=0),
        "mean": as_float.mean(axis=0),
        "std": as_float.std(axis=0),
        "count": np.array([len(values)], dtype=np.int64),
    }
    quantiles = np.quantile(as_float, QUANTILES, axis=0)
    for key, row in zip(_QUANTILE_KEYS, quantiles, strict=True):
        stats[key] = row
    return stats


def _nan_vector_stats(data: npt.NDArray[np.float64], count: int) -> Stats:
    """Stats over the non-NaN values of each column (NaN: no sample); 0 for an all-NaN column."""
    empty: npt.NDArray[np.bool_] = np.asarray(np.isnan(data).all(axis=0))
    filled = np.where(empty[None, :], 0.0, data)
    stats: Stats = {
        "min": np.nanmin(filled, axis=0),
        "max": np.nanmax(filled, axis=0),
        "mean": np.nanmean(filled, axis=0),
        "std": np.nanstd(filled, axis=0),
        "count": np.array([count], dtype=np.int64),
    }
    quantiles = np.nanquantile(filled, QUANTILES, axis=0)
    for key, row in zip(_QUANTILE_KEYS, quantiles, strict=True):
        stats[key] = row
    return stats


class ImageStats:
    """Accumulates per-channel stats of ``uint8`` RGB frames, as LeRobot computes a camera's.

    Each added frame is strided by :func:`downsample_factor`; pixel values are counted in a
    256-bin histogram per channel, from which moments and quantiles are exact.

    Args:
        height: Frame height [px].
        width: Frame width [px].
    """

    def __init__(self, height: int, width: int) -> None:
        self._step = downsample_factor(height, width)
        self._hist = np.zeros((3, 256), dtype=np.int64)
        self.frames = 0

    def add(self, frame: npt.NDArray[np.uint8]) -> None:
        """Count one RGB frame, shape (H, W, 3)."""
        small = frame[:: self._step, :: self._step]
        for channel in range(3):
            self._hist[channel] += np.bincount(small[..., channel].ravel(), minlength=256)
        self.frames += 1

    def result(self) -> Stats:
        """Stats in [0, 1], each (3, 1, 1); ``count`` is the number of frames added (>= 1)."""
        if self.frames == 0:
            raise ValueError("no frame was added")
        levels = np.arange(256, dtype=np.float64)
        totals = self._hist.sum(axis=1).astype(np.float64)
        mean = (self._hist * levels).sum(axis=1) / totals
        var = (self._hist * (levels[None, :] - mean[:, None]) ** 2).sum(axis=1) / totals
        present = self._hist > 0
        lo = np.argmax(present, axis=1).astype(np.float64)
        hi = (255 - np.argmax(present[:, ::-1], axis=1)).astype(np.float64)
        stats: Stats = {
            "min": lo,
            "max": hi,
            "mean": mean,
            "std": np.sqrt(var),
            "count": np.array([self.frames], dtype=np.int64),
        }
        for key, q in zip(_QUANTILE_KEYS, QUANTILES, strict=True):
            stats[key] = np.array([_hist_quantile(row, q) for row in self._hist])
        return {
            key: value if key == "count" else (value / 255.0).reshape(3, 1, 1) for key, value in stats.items()
        }


def _hist_quantile(hist: npt.NDArray[np.int64], q: float) -> float:
    """``np.quantile(values, q)`` (linear rule) of the values a 256-bin histogram counts."""
    cumulative = np.cumsum(hist)
    position = (int(cumulative[-1]) - 1) * q
    below = int(np.floor(position))
    low = int(np.searchsorted(cumulative, below, side="right"))
    high = int(np.searchsorted(cumulative, min(below + 1, int(cumulative[-1]) - 1), side="right"))
    return float(low + (position - below) * (high - low))


def aggregate(stats_list: Sequence[Mapping[str, npt.NDArray[Any]]]) -> Stats:
    """One feature's stats over several episodes (or datasets), as LeRobot aggregates them.

    Args:
        stats_list: Stats of the same feature, same shapes; at least one.

    Returns:
        Count-weighted mean and quantiles, pooled std, overall min and max, summed count.
    """
    if not stats_list:
        raise ValueError("nothing to aggregate")
    counts = np.stack([np.asarray(s["count"], dtype=np.float64) for s in stats_list])
    means = np.stack([np.asarray(s["mean"], dtype=np.float64) for s in stats_list])
    variances = np.stack([np.asarray(s["std"], dtype=np.float64) ** 2 for s in stats_list])
    total = counts.sum(axis=0)
    weights = counts.reshape(counts.shape[0], *([1] * (means.ndim - 1)))
    mean = (means * weights).sum(axis=0) / total
    variance = ((variances + (means - mean) ** 2) * weights).sum(axis=0) / total
    result: Stats = {
        "min": np.min(np.stack([np.asarray(s["min"]) for s in stats_list]), axis=0),
        "max": np.max(np.stack([np.asarray(s["max"]) for s in stats_list]), axis=0),
        "mean": mean,
        "std": np.sqrt(variance),
        "count": np.array([int(total.sum())], dtype=np.int64),
    }
    for key in _QUANTILE_KEYS:
        if all(key in s for s in stats_list):
            values = np.stack([np.asarray(s[key], dtype=np.float64) for s in stats_list])
            result[key] = (values * weights).sum(axis=0) / total
    return result


def stats_to_json(stats: Mapping[str, Mapping[str, npt.NDArray[Any]]]) -> dict[str, dict[str, Any]]:
    """``{feature: {stat: nested list}}``, the layout of LeRobot's ``meta/stats.json``."""
    return {
        feature: {key: np.asarray(value).tolist() for key, value in ft.items()}
        for feature, ft in stats.items()
    }
