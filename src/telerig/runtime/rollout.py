"""What a rollout episode records about its policy: the manifest's ``policy`` section.

An episode of a rig with a ``policy`` device is a policy episode: its manifest says which checkpoint
drove (id and sha256 content hash, so a dataset can be filtered by policy and a result traced to
its weights), how the policy kept its deadlines, and per robot how often control changed hands and
how often an operator intervened. Interventions are kept whole in the episode; the per-tick record
of who drove is the ``control_source`` stream.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Protocol, runtime_checkable

from pydantic import JsonValue

__all__ = ["policy_record"]


@runtime_checkable
class _RolledOut(Protocol):
    """A policy device (:class:`~telerig.devices.policy.device.PolicyDevice`), structurally."""

    checkpoint: str
    robot: str

    @property
    def info(self) -> object: ...

    @property
    def stats(self) -> Mapping[str, int]: ...


def policy_record(devices: Mapping[str, object], handovers: Mapping[str, object]) -> dict[str, JsonValue]:
    """``{"policy": {...}}`` for the manifest's extra, or ``{}`` when no policy device ran.

    Args:
        devices: Device id → the device (the station's device nodes' devices).
        handovers: Robot id → its handover's state (:meth:`~telerig.runtime.handover.Handover.state`).
    """
    policies: dict[str, JsonValue] = {}
    for device_id, device in devices.items():
        if not isinstance(device, _RolledOut):
            continue
        info = device.info
        policies[device_id] = {
            "checkpoint": device.checkpoint,
            "checkpoint_id": str(getattr(info, "checkpoint_id", "")),
            "checkpoint_sha256": str(getattr(info, "checkpoint_sha256", "")),
            "policy_type": str(getattr(info, "policy_type", "")),
            "robot": device.robot,
            "stats": {k: int(v) for k, v in device.stats.items()},
        }
    if not policies:
        return {}
    control: dict[str, JsonValue] = {}
    interventions = 0
    for robot, state in handovers.items():
        if isinstance(state, dict):
            control[robot] = state
            count = state.get("interventions", 0)
            interventions += count if isinstance(count, int) else 0
    return {
        "policy": {
            "episode": "intervened" if interventions else "rollout",
            "devices": policies,
            "control": control,
        }
    }
