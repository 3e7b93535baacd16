"""Device clock -> common clock mapping by the minimum observed transport delay."""

from __future__ import annotations

from collections import deque

__all__ = ["OffsetEstimator"]


class OffsetEstimator:
    """Estimates ``offset`` so that ``capture_ns = device_ns + offset`` in the common clock.

    The offset is the minimum of ``arrival_ns - device_ns`` over the last ``window_ns`` of
    arrivals: the sample that travelled fastest bounds the true offset from above, and a sliding
    window follows slow drift between the two clocks. The result never puts a capture time after
    its arrival. Call :meth:`reset` when the device's clock may have restarted (a reconnect).

    Args:
        window_ns: Length of the sliding window [ns].
    """

    def __init__(self, window_ns: int = 2_000_000_000) -> None:
        self.window_ns = window_ns
        self._q: deque[tuple[int, int]] = deque()

    def reset(self) -> None:
        """Forget every observation."""
        self._q.clear()

    def update(self, device_ns: int, arrival_ns: int) -> int:
        """Add one observation and return the current offset [ns]."""
        diff = arrival_ns - device_ns
        q = self._q
        # Monotonic deque: differences increase from front to back, so the front is the minimum.
        while q and q[-1][1] >= diff:
            q.pop()
        q.append((arrival_ns, diff))
        horizon = arrival_ns - self.window_ns
        while q[0][0] < horizon:
            q.popleft()
        return q[0][1]
