"""The fake glove device: a FakeGloveBridge on a free local port and a GloveDevice reading it."""

from __future__ import annotations

import threading

from telerig.devices.base import SampleSink
from telerig.devices.glove.device import GloveDevice
from telerig.devices.glove.fake import FakeGloveBridge
from telerig.ir.types import Handedness

__all__ = ["FakeGloveDevice"]


class FakeGloveDevice:
    """Implements :class:`~telerig.devices.base.Device`: every sample crosses the glove bridge protocol.

    :meth:`start` starts the bridge (a free port on 127.0.0.1) and the glove device connected to
    it; :meth:`stop` stops both and is idempotent. Samples are exactly the glove device's.

    Args:
        id: Device id.
        hand: Handedness the bridge streams and the device accepts.
        rate_hz: Bridge frame rate [Hz].
        dwell_s: Hold time of each gesture [s].
        transition_s: Blend time between gestures [s].
    """

    def __init__(
        self,
        id: str = "glove0",
        *,
        hand: Handedness = "right",
        rate_hz: float = 60.0,
        dwell_s: float = 0.6,
        transition_s: float = 0.4,
    ) -> None:
        self._id = id
        self.hand: Handedness = hand
        self.bridge = FakeGloveBridge(hand=hand, rate_hz=rate_hz, dwell_s=dwell_s, transition_s=transition_s)
        self._glove: GloveDevice | None = None
        self._lock = threading.Lock()

    @property
    def id(self) -> str:
        """Device id."""
        return self._id

    @property
    def glove(self) -> GloveDevice | None:
        """The glove device reading the bridge while running (its ``stats`` count frames and drops)."""
        return self._glove

    def start(self, sink: SampleSink) -> None:
        """Start the bridge and the glove device delivering ``HandPose`` samples into ``sink``."""
        with self._lock:
            if self._glove is not None:
                return
            self.bridge.start()
            glove = GloveDevice(self._id, host="127.0.0.1", port=self.bridge.port, hand=self.hand)
            glove.start(sink)
            self._glove = glove

    def stop(self) -> None:
        """Stop the glove device, then the bridge. Idempotent."""
        with self._lock:
            glove, self._glove = self._glove, None
        if glove is not None:
            glove.stop()
        self.bridge.stop()
