"""The input device interface: a source of IR samples with capture timestamps."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Literal, Protocol, runtime_checkable

from pydantic import JsonValue

from telerig.ir.types import Sample

__all__ = [
    "AlertSink",
    "ChangeDrivenDevice",
    "Device",
    "DeviceAlert",
    "ObservingDevice",
    "OperatedDevice",
    "PageSink",
    "RelayedDevice",
    "SampleSink",
    "on_change_streams",
]

#: Where a device delivers its samples. Called from the device's own thread; must not block.
SampleSink = Callable[[Sample], None]


@runtime_checkable
class Device(Protocol):
    """An operator input device.

    ``start`` begins producing samples into ``sink`` on the device's own thread;
    ``stop`` ends it and is idempotent. Samples carry ``stamp.capture_ns`` from
    the moment they were captured, never from when they were delivered.
    """

    @property
    def id(self) -> str: ...

    def start(self, sink: SampleSink) -> None: ...

    def stop(self) -> None: ...


@dataclass(frozen=True, slots=True)
class DeviceAlert:
    """Something about a device the operator must know (a client took it over, a client was refused).

    Attributes:
        code: What happened, e.g. ``"takeover"``.
        device: Device id.
        reason: One line with the details (addresses, counts).
        suggested_action: One line for the operator.
        severity: ``info``, ``warning`` or ``error``.
        time_ns: When it happened, common clock [ns].
    """

    code: str
    device: str
    reason: str
    suggested_action: str
    severity: Literal["info", "warning", "error"]
    time_ns: int

    def to_json(self) -> dict[str, JsonValue]:
        """The alert as JSON data (every attribute, by name)."""
        return {
            "code": self.code,
            "device": self.device,
            "reason": self.reason,
            "suggested_action": self.suggested_action,
            "severity": self.severity,
            "time_ns": self.time_ns,
        }


#: Where a device reports its alerts. Called from the device's own thread; must not block.
AlertSink = Callable[[DeviceAlert], None]


@runtime_checkable
class OperatedDevice(Protocol):
    """A device that reports alerts and takes commands from the operator (through its device node).

    ``set_alert_sink`` is called before ``start``; ``command`` gets a decoded JSON command (e.g.
    ``{"takeover": "confirm"}``) and returns one line saying what it did; it must not block and
    never raises for a bad command (it says what is wrong instead).
    """

    def set_alert_sink(self, sink: AlertSink) -> None: ...

    def command(self, command: Mapping[str, JsonValue]) -> str: ...


#: Where a relayed device sends its answers to its pages (its device node publishes them on the
#: device's ``page_out`` topic). Must not block.
PageSink = Callable[[bytes], None]


@runtime_checkable
class RelayedDevice(Protocol):
    """A device whose operator pages reach it through ``telerig serve`` (the WebXR page).

    The web server logs the operator in and relays the page's messages on the device's ``page_in``
    topic; the device node hands each payload to :meth:`page_message` (from the bus thread: it must
    not block) and publishes what the device sends to its page sink on ``page_out``.
    ``set_page_sink`` is called before ``start``.
    """

    def set_page_sink(self, sink: PageSink) -> None: ...

    def page_message(self, payload: bytes) -> None: ...


@runtime_checkable
class ObservingDevice(Protocol):
    """A device that watches a robot's IR streams (a scripted operator planning from the cube's
    observed pose, a policy from the joint state): its device node subscribes to the robot's
    ``tick`` while it runs (those streams travel in it, see :mod:`telerig.bus.ticks`), decodes the
    parts of :attr:`observes` and hands each sample to :meth:`observe` (from the bus thread: it must
    not block).

    Only samples whose ``stamp.source_id`` names the topic's node (``<node>`` or ``<node>/...``)
    arrive; undecodable or forged ones are counted by the node and dropped.
    """

    @property
    def observes(self) -> tuple[tuple[str, str], ...]:
        """``(robot, stream)`` pairs to watch, e.g. ``(("arm0", "object_pose"),)``."""
        ...

    def observe(self, sample: Sample) -> None: ...


@runtime_checkable
class ChangeDrivenDevice(Protocol):
    """A device that sends some of its streams only when their value changes: a SpaceMouse's or
    a gamepad's buttons and sticks, a keyboard's held keys, a script's button presses. Such a
    stream has no period, so a pause in it is no outage: the validator's gap check
    (:class:`~telerig.devices.validate.GapCheck`) leaves it alone. Before, it learned a "period"
    from the first presses and dropped the next press that came after a longer pause (the fleet
    soak: the TIAGo's mode button lost one press in every episode)."""

    @property
    def on_change_streams(self) -> frozenset[str]:
        """The streams (``right_controller``, ``twist``...) sent only on a change."""
        ...


def on_change_streams(device: object) -> frozenset[str]:
    """``device``'s streams sent only on a change (:class:`ChangeDrivenDevice`); none for others."""
    return device.on_change_streams if isinstance(device, ChangeDrivenDevice) else frozenset()
