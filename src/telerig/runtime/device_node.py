"""Device node: runs one input device and publishes its samples on the bus."""

from __future__ import annotations

import logging

from telerig.bus.base import Bus
from telerig.bus.topics import Topic
from telerig.devices.base import Device
from telerig.ir import wire
from telerig.ir.types import Sample
from telerig.runtime.streams import device_stream

__all__ = ["DeviceNode"]

log = logging.getLogger(__name__)


class DeviceNode:
    """Publishes every sample of ``device`` on ``telerig/v1/<rig>/<device id>/<part>`` (QoS 0)."""

    def __init__(self, rig: str, device: Device, bus: Bus) -> None:
        self.rig = rig
        self.device = device
        self._bus = bus
        self._topics: dict[str, str] = {}
        self.published = 0
        self._running = False

    def start(self) -> None:
        """Start the device; idempotent."""
        if not self._running:
            self._running = True
            self.device.start(self._publish)

    def stop(self) -> None:
        """Stop the device; idempotent."""
        if self._running:
            self._running = False
            self.device.stop()

    def swap(self, device: Device) -> Device:
        """Replace the (stopped) device by another with the same id, e.g. a replay; returns the old one."""
        if self._running:
            raise RuntimeError(f"device {self.device.id!r} is running; stop() it before swapping")
        if device.id != self.device.id:
            raise ValueError(f"replacement device id {device.id!r} must be {self.device.id!r} (same topics)")
        old, self.device = self.device, device
        return old

    def _publish(self, sample: Sample) -> None:
        stream = device_stream(sample)
        topic = self._topics.get(stream)
        if topic is None:
            topic = self._topics[stream] = str(Topic(self.rig, self.device.id, stream))
        self._bus.publish(topic, wire.encode(sample))
        self.published += 1
