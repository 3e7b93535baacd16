"""Device clock -> common clock offset, shared by devices, robot drivers and cameras."""

from __future__ import annotations

from collections import deque

__all__ = ["ClockOffsetEstimator"]


class ClockOffsetEstimator:
    """Estimates ``offset_ns`` so that ``capture_ns = device_ns + offset_ns`` in the common clock.

    Every packet gives ``arrival_ns - device_ns`` = true offset + transport delay, the delay
    (network, OS stack, queueing) being >= 0. So the packet that travelled fastest bounds the
    offset from above, and the minimum difference over the packets that arrived in the last
    ``window_ns`` is the offset plus the smallest recent delay (well under a millisecond on a LAN
    or loopback). The window is a compromise: long enough to contain a fast packet, short enough
    to follow slow drift between the device clock and the common clock. Because the current
    packet is always in the window, ``device_ns + offset_ns`` never puts a capture time after the
    packet's arrival.

    With ``reset_ns`` set, a device restart or clock step restarts the estimate from that packet
    alone: a difference more than ``reset_ns`` below the estimate (the device clock stepped
    forward), or more than ``reset_ns`` above it while the device time went backwards (the device
    clock started over or stepped back). A difference far above the estimate whose device time
    moved forward is a late packet, not a new clock: a sender or receiver that stalled for a
    second delivers its backlog with device times that continue where they left off, and those
    keep the old offset, so their capture times stay evenly spaced. Call :meth:`reset` when the
    caller knows the device clock may have a new origin (a reconnect, a sender restart).

    A monotonic deque of ``(arrival_ns, difference)`` with increasing differences holds the
    candidates, so :meth:`update` is amortised O(1). Arrival times should not decrease.

    Units: every time, offset and duration is integer nanoseconds; ``device_ns`` in the device
    clock, ``arrival_ns`` in the common clock (:func:`telerig.ir.types.now_ns`).

    Args:
        window_ns: Length of the sliding window over arrival times [ns] (> 0).
        reset_ns: Jump of the difference from the estimate that restarts it [ns] (> 0), or None
            to never restart on a jump.
    """

    def __init__(self, window_ns: int = 2_000_000_000, *, reset_ns: int | None = None) -> None:
        if window_ns <= 0:
            raise ValueError(f"window_ns must be > 0, got {window_ns}")
        if reset_ns is not None and reset_ns <= 0:
            raise ValueError(f"reset_ns must be > 0 or None, got {reset_ns}")
        self.window_ns = window_ns
        self.reset_ns = reset_ns
        # (arrival_ns, arrival_ns - device_ns); differences increase front to back: front = minimum.
        self._q: deque[tuple[int, int]] = deque()
        self._last_device_ns: int | None = None

    @property
    def offset_ns(self) -> int | None:
        """Current estimate [ns], or None before the first update (and after :meth:`reset`)."""
        return self._q[0][1] if self._q else None

    def reset(self) -> None:
        """Forget every observation (the device clock may have restarted)."""
        self._q.clear()
        self._last_device_ns = None

    def update(self, device_ns: int, arrival_ns: int) -> int:
        """Add one packet's device time and arrival time [ns]; return the current offset [ns].

        The result is <= ``arrival_ns - device_ns``, so ``device_ns + result <= arrival_ns``.
        """
        diff = arrival_ns - device_ns
        q = self._q
        horizon = arrival_ns - self.window_ns
        while q and q[0][0] < horizon:
            q.popleft()
        last_device, self._last_device_ns = self._last_device_ns, device_ns
        if self.reset_ns is not None and q:
            jump = diff - q[0][1]
            if jump < -self.reset_ns or (
                jump > self.reset_ns and last_device is not None and device_ns < last_device
            ):
                q.clear()
        while q and q[-1][1] >= diff:
            q.pop()
        q.append((arrival_ns, diff))
        return q[0][1]
