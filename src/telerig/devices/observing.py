"""Devices that read cameras' observation frames from the bus (a policy): the protocol their device
node wires (:class:`~telerig.runtime.device_node.DeviceNode`)."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

__all__ = ["FrameObservingDevice"]


@runtime_checkable
class FrameObservingDevice(Protocol):
    """A device that reads cameras' ``observation`` frames (raw payloads, see
    :mod:`telerig.ir.observation`): its device node subscribes to ``<camera>/observation`` for each
    of :attr:`observes_frames` while it runs and hands each payload to :meth:`observe_frame` (from
    the bus thread: it must not block; it decodes, and counts what it cannot use)."""

    @property
    def observes_frames(self) -> tuple[str, ...]:
        """Camera ids."""
        ...

    def observe_frame(self, camera: str, payload: bytes) -> None: ...
