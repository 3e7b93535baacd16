"""Device node: runs one input device, validates its samples and publishes them and its health on the bus."""

from __future__ import annotations

import dataclasses
import json
import logging
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

from telerig.bus.base import Bus, Message, Subscription
from telerig.bus.catalogue import COMMAND, EVENTS, HEALTH, OBSERVATION, PAGE_IN, PAGE_OUT, device_stream
from telerig.bus.ticks import TICK, picking
from telerig.bus.topics import Topic, qos_for
from telerig.devices.base import (
    Device,
    DeviceAlert,
    ObservingDevice,
    OperatedDevice,
    RelayedDevice,
    on_change_streams,
)
from telerig.devices.observing import FrameObservingDevice
from telerig.devices.validate import SampleValidator
from telerig.errors import ConfigError, WireError
from telerig.ir import wire
from telerig.ir.types import Sample, now_ns
from telerig.runtime.device_calibration import MAX_SAMPLES, DeviceCalibration

__all__ = ["HEALTH", "DeviceHealth", "DeviceNode"]

log = logging.getLogger(__name__)

# HEALTH (from the catalogue): the stream of a device node's health counters (retained, QoS 1).


@dataclass(frozen=True, slots=True)
class DeviceHealth:
    """Counters of one device node, published as JSON on ``telerig/v1/<rig>/<device>/health``.

    Attributes:
        received: Samples the device delivered.
        published: Samples that passed validation and went on the bus.
        dropped: Samples dropped by validation, per reason (every reason present).
        rate_hz: Published samples per second since the previous health report [Hz].
        device: The device's own counters (its ``stats`` mapping, e.g. malformed packets per
            reason), empty when it has none.
    """

    received: int
    published: int
    dropped: Mapping[str, int]
    rate_hz: float
    device: Mapping[str, int]

    def to_json(self) -> bytes:
        """``{"received", "published", "dropped": {reason: n}, "rate_hz", "device": {name: n}}``."""
        return json.dumps(
            {
                "received": self.received,
                "published": self.published,
                "dropped": dict(self.dropped),
                "rate_hz": round(self.rate_hz, 3),
                "device": dict(self.device),
            },
            separators=(",", ":"),
        ).encode()


class DeviceNode:
    """Validates every sample of ``device`` and publishes the valid ones on
    ``telerig/v1/<rig>/<device id>/<part>`` (QoS 0); dropped samples are never published, so
    consumers hold the last valid value. Health goes on ``.../<device id>/health`` (retained) every
    ``health_period_s`` and on :meth:`stop`.

    Args:
        rig: Rig name (topic prefix).
        device: The input device.
        bus: Bus client of this node.
        validator: Sample validation; ``SampleValidator.default()`` when None (with the device's
            :func:`~telerig.devices.base.on_change_streams`).
        health_period_s: Health report period [s] (> 0); ``None`` reports only on ``stop`` and
            :meth:`publish_health` (tests).
        clock: Monotonic clock [ns] used for the reported rate; injectable for tests.
        profile_root: Where an operator calibration launched over the bus saves its profile
            (:mod:`telerig.runtime.device_calibration`); ``None``: reported, not saved.
    """

    def __init__(
        self,
        rig: str,
        device: Device,
        bus: Bus,
        *,
        validator: SampleValidator | None = None,
        health_period_s: float | None = 1.0,
        clock: Callable[[], int] = time.monotonic_ns,
        profile_root: Path | None = None,
    ) -> None:
        if health_period_s is not None and not health_period_s > 0:
            raise ConfigError(f"health_period_s must be > 0 s or None, got {health_period_s}")
        self.rig = rig
        self.device = device
        if validator is None:
            validator = SampleValidator.default(on_change_streams=on_change_streams(device))
        self.validator = validator
        self._bus = bus
        self._topics: dict[str, str] = {}
        self._health_topic = str(Topic(rig, device.id, HEALTH))
        self._health_period_s = health_period_s
        self._clock = clock
        self.published = 0
        self._running = False
        self._sink_lock = threading.Lock()
        self._health_lock = threading.Lock()
        self._health_stop = threading.Event()
        self._health_thread: threading.Thread | None = None
        self._rate_ns = clock()
        self._rate_count = 0
        self._events_topic = str(Topic(rig, device.id, EVENTS))
        self._command_topic = str(Topic(rig, device.id, COMMAND))
        self._command_sub: Subscription | None = None
        self._page_sub: Subscription | None = None
        self._observe_subs: list[Subscription] = []
        #: Observed messages dropped (an :class:`ObservingDevice`'s streams): undecodable, or a
        #: sample whose source is not the topic's node.
        self.observed_dropped = 0
        #: Operator calibration launched with ``{"calibrate": {...}}`` on ``<device>/command``.
        self.calibration = DeviceCalibration(
            rig, device, bus, self._publish_alert, lambda: self._running, profile_root=profile_root
        )

    def start(self) -> None:
        """Start the device and the health reports (cancelling a calibration between episodes that
        runs the device itself: the episode wins); idempotent."""
        if self._running:
            return
        self.calibration.cancel_own()
        self._running = True
        with self._sink_lock:
            self.validator.reset()  # the pause before this start is not an abnormal gap
        with self._health_lock:
            self._rate_ns = self._clock()
            self._rate_count = self.published
        if self._health_period_s is not None:
            self._health_stop.clear()
            self._health_thread = threading.Thread(
                target=self._health_loop, name=f"health-{self.device.id}", daemon=True
            )
            self._health_thread.start()
        if isinstance(self.device, OperatedDevice):
            # Its alerts (a WebXR takeover) go on <device>/events; the operator answers on <device>/command.
            self.device.set_alert_sink(self._publish_alert)
            self._command_sub = self._bus.subscribe(self._command_topic, self._on_command, qos=1)
        if isinstance(self.device, RelayedDevice):
            # Its operator pages come through telerig serve (login first) on <device>/page_in.
            self._relay(self.device)
        if isinstance(self.device, FrameObservingDevice):
            self._observe_frames(self.device)
        if isinstance(self.device, ObservingDevice):
            self._observe(self.device)
        self.device.start(self._publish)

    def stop(self) -> None:
        """Stop the device and publish a last health report; idempotent."""
        if not self._running:
            return
        self._running = False
        for sub in (self._command_sub, self._page_sub, *self._observe_subs):
            if sub is not None:
                sub.cancel()
        self._command_sub = self._page_sub = None
        self._observe_subs = []
        try:
            self.device.stop()
        finally:
            self._health_stop.set()
            if self._health_thread is not None:
                self._health_thread.join(timeout=5.0)
                self._health_thread = None
            self.publish_health()

    def swap(self, device: Device) -> Device:
        """Replace the (stopped) device by another with the same id, e.g. a replay; returns the old one."""
        if self._running:
            raise RuntimeError(f"device {self.device.id!r} is running; stop() it before swapping")
        if device.id != self.device.id:
            raise ValueError(f"replacement device id {device.id!r} must be {self.device.id!r} (same topics)")
        old, self.device = self.device, device
        return old

    def health(self) -> DeviceHealth:
        """The current counters; ``rate_hz`` covers the time since the previous health report."""
        with self._health_lock:
            return self._health(advance=False)

    def publish_health(self) -> DeviceHealth:
        """Publish the counters on the retained health topic and start a new rate window."""
        with self._health_lock:
            health = self._health(advance=True)
        qos, retain = qos_for(HEALTH)
        self._bus.publish(self._health_topic, health.to_json(), qos=qos, retain=retain)
        return health

    def _health(self, *, advance: bool) -> DeviceHealth:
        v = self.validator
        now = self._clock()
        published = self.published
        elapsed_s = (now - self._rate_ns) / 1e9
        rate = (published - self._rate_count) / elapsed_s if elapsed_s > 0 else 0.0
        if advance:
            self._rate_ns, self._rate_count = now, published
        return DeviceHealth(v.received, published, dict(v.dropped), rate, _device_stats(self.device))

    def _health_loop(self) -> None:
        assert self._health_period_s is not None
        while not self._health_stop.wait(self._health_period_s):
            try:
                self.publish_health()
            except Exception:
                log.exception("health report of device %s failed", self.device.id)

    def _publish_alert(self, alert: DeviceAlert) -> None:
        level = logging.INFO if alert.severity == "info" else logging.WARNING
        log.log(level, "%s: %s: %s", alert.device, alert.code, alert.reason)
        try:
            self._bus.publish(self._events_topic, json.dumps(alert.to_json()).encode(), qos=1)
        except Exception:
            log.exception("publishing an alert of device %s failed", self.device.id)

    def _relay(self, device: RelayedDevice) -> None:
        out = str(Topic(self.rig, self.device.id, PAGE_OUT))
        device.set_page_sink(lambda payload: self._bus.publish(out, payload))
        topic = str(Topic(self.rig, self.device.id, PAGE_IN))
        self._page_sub = self._bus.subscribe(topic, lambda m: device.page_message(m.payload))

    def _observe_frames(self, device: FrameObservingDevice) -> None:
        """A policy's cameras: raw observation payloads to the device (it decodes and counts)."""
        for camera in device.observes_frames:
            topic = str(Topic(self.rig, camera, OBSERVATION))

            def handle(message: Message, camera: str = camera) -> None:
                device.observe_frame(camera, message.payload)

            self._observe_subs.append(self._bus.subscribe(topic, handle))

    def _observe(self, device: ObservingDevice) -> None:
        # A robot's IR streams travel in its tick (telerig.bus.ticks): one subscription per robot.
        wanted: dict[str, set[str]] = {}
        for node, stream in device.observes:
            wanted.setdefault(node, set()).add(stream)
        for node, node_streams in wanted.items():
            topic = str(Topic(self.rig, node, TICK))
            handler = self._observer(device, node, frozenset(node_streams))
            self._observe_subs.append(self._bus.subscribe(topic, handler))

    def _observer(
        self, device: ObservingDevice, node: str, streams: frozenset[str]
    ) -> Callable[[Message], None]:
        def handle(message: Message) -> None:
            try:
                pick(message)
            except WireError as exc:  # the tick itself (a part that does not decode is counted below)
                self._dropped_observation(f"undecodable message on {message.topic}: {exc}")

        def observe(message: Message) -> None:
            try:
                sample = wire.decode(message.payload)
            except (WireError, ValueError) as exc:
                self._dropped_observation(f"undecodable message on {message.topic}: {exc}")
                return
            source = sample.stamp.source_id
            if source != node and not source.startswith(node + "/"):
                self._dropped_observation(f"{message.topic} carried a sample of {source!r}")
                return
            device.observe(sample)

        pick = picking(streams, observe)
        return handle

    def _dropped_observation(self, reason: str) -> None:
        self.observed_dropped += 1
        if self.observed_dropped == 1 or self.observed_dropped % 1000 == 0:
            log.warning(
                "%s: dropped an observed message (%d so far): %s",
                self.device.id,
                self.observed_dropped,
                reason,
            )

    def _on_command(self, message: Message) -> None:
        device = self.device
        try:
            command = json.loads(message.payload)
        except ValueError:
            command = None
        if isinstance(command, dict) and "calibrate" in command:
            return  # the calibration answers it (self.calibration)
        if not isinstance(command, dict) or not isinstance(device, OperatedDevice):
            log.warning("%s: dropped a command that is not a JSON object: %.80r", device.id, message.payload)
            return
        reply = device.command(command)
        log.info("%s", reply)
        # The answer goes on <device>/events too, for the operator who sent the command.
        self._publish_alert(DeviceAlert("command_reply", device.id, reply, "", "info", now_ns()))

    def _publish(self, sample: Sample) -> None:
        # The sample reached telerig now, unless its device stamped that itself (the ``receive``
        # latency stage ends here); a copy of the stamp, off any control thread.
        if sample.stamp.arrival_ns == 0:
            sample = dataclasses.replace(sample, stamp=sample.stamp.arrived())
        # Devices may deliver from more than one thread; the validator keeps per-stream state.
        with self._sink_lock:
            if self.validator.validate(sample) is not None:
                return
            stream = device_stream(sample)
            topic = self._topics.get(stream)
            if topic is None:
                topic = self._topics[stream] = str(Topic(self.rig, self.device.id, stream))
            self._bus.publish(topic, wire.encode(sample))
            self.published += 1
            tap = self.calibration.tap
            if tap is not None and len(tap) < MAX_SAMPLES:
                tap.append(sample)  # a calibration while the device is paused (see DeviceCalibration)


def _device_stats(device: Device) -> dict[str, int]:
    stats = getattr(device, "stats", None)
    if not isinstance(stats, Mapping):
        return {}
    try:
        items = list(stats.items())
    except RuntimeError:  # resized by the device thread while we copied it: report it next time
        return {}
    return {str(k): int(v) for k, v in items if isinstance(v, int | float)}
