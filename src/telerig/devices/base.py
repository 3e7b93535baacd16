"""The input device interface: a source of IR samples with capture timestamps."""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol, runtime_checkable

from telerig.ir.types import Sample

__all__ = ["Device", "SampleSink"]

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
