"""Rig fingerprint: what makes episodes of one dataset compatible, hashed and kept in each manifest."""

from __future__ import annotations

import hashlib
import json
import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

from pydantic import JsonValue, ValidationError

from telerig.config.schema import RigConfig
from telerig.errors import RecordingError
from telerig.ir import wire
from telerig.store.episodes import EpisodeManifest, EpisodeStore

__all__ = [
    "FINGERPRINT_VERSION",
    "MANIFEST_KEY",
    "RigFingerprint",
    "check_compatible",
    "fingerprint",
    "rig_fingerprint",
]

_log = logging.getLogger("telerig.store.fingerprint")

#: Version of the component layout below; a change makes every older fingerprint differ.
FINGERPRINT_VERSION = 1
#: Key under ``EpisodeManifest.extra`` where :meth:`RigFingerprint.to_json` is stored.
MANIFEST_KEY = "fingerprint"
_DIGEST_CHARS = 16
_MAX_DIFFS = 4


def _num(value: float) -> str:
    return f"{float(value):g}"


@dataclass(frozen=True, slots=True)
class RigFingerprint:
    """The components of a rig that decide dataset compatibility, and their hash.

    Attributes:
        components: Component name → canonical description, e.g. ``"camera scene" → "640x480@30"``,
            ``"robot arm0" → "mujoco_arm ur5e_robotiq85"``, ``"robot arm0 control" → "100 Hz"``.
    """

    components: Mapping[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "components", MappingProxyType(dict(sorted(self.components.items()))))

    @property
    def digest(self) -> str:
        """Stable hash of the components: 16 hex chars of SHA-256 over their canonical JSON."""
        text = json.dumps(dict(self.components), sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(text.encode()).hexdigest()[:_DIGEST_CHARS]

    def to_json(self) -> dict[str, JsonValue]:
        """``{"digest": ..., "components": {...}}``, to store under ``extra[MANIFEST_KEY]``."""
        components: dict[str, JsonValue] = dict(self.components)
        return {"digest": self.digest, "components": components}

    @classmethod
    def from_json(cls, data: JsonValue) -> RigFingerprint:
        """Parse what :meth:`to_json` wrote; raises ``ValueError`` on any other shape."""
        components = data.get("components") if isinstance(data, dict) else None
        if not isinstance(components, dict) or not all(isinstance(v, str) for v in components.values()):
            raise ValueError("a fingerprint must be {'digest': str, 'components': {name: str}}")
        return cls({k: str(v) for k, v in components.items()})

    def differences(self, other: RigFingerprint) -> list[tuple[str, str, str]]:
        """``(component, value here, value in other)`` per differing component; ``none`` where absent."""
        names = sorted(set(self.components) | set(other.components))
        return [
            (name, self.components.get(name, "none"), other.components.get(name, "none"))
            for name in names
            if self.components.get(name) != other.components.get(name)
        ]


def rig_fingerprint(rig: RigConfig) -> RigFingerprint:
    """The compatibility components of ``rig``.

    Included: the wire schema version, each robot (type, model, joint names when its config has
    them, control rate [Hz]), each device (type, rate [Hz] when configured), each camera
    (resolution [px] and rate [Hz]) and each binding's retargeter type (what the actions mean).
    Excluded on purpose: names of the rig, task and operator, stations and hosts, the broker,
    safety and validation thresholds, alignment offsets: they vary between sessions of one dataset.
    """
    c: dict[str, str] = {"schema": f"wire v{wire.SCHEMA_VERSION}, fingerprint v{FINGERPRINT_VERSION}"}
    for robot in rig.robots:
        text = robot.type
        model = getattr(robot, "model", None)
        if model is not None:
            text += f" {model}"
        joints = getattr(robot, "joint_names", None)
        if joints:
            text += f" joints {','.join(str(j) for j in joints)}"
        c[f"robot {robot.id}"] = text
        rate = getattr(robot, "control_rate_hz", None)
        if rate is not None:
            c[f"robot {robot.id} control"] = f"{_num(rate)} Hz"
    for device in rig.devices:
        rate = getattr(device, "rate_hz", None)
        c[f"device {device.id}"] = device.type if rate is None else f"{device.type} @{_num(rate)} Hz"
    for camera in rig.cameras:
        c[f"camera {camera.id}"] = f"{camera.width}x{camera.height}@{_num(camera.fps)}"
    for b in rig.bindings:
        c[f"binding {b.device}.{b.part} -> {b.robot}.{b.target}"] = b.retargeter.type
    return RigFingerprint(c)


def fingerprint(rig: RigConfig) -> str:
    """Stable hash (16 hex chars) of what makes ``rig``'s episodes compatible; see :func:`rig_fingerprint`."""
    return rig_fingerprint(rig).digest


def check_compatible(store: EpisodeStore, rig: RigFingerprint | RigConfig) -> None:
    """Refuse to add episodes of ``rig`` to ``store`` when its committed episodes (failures included) came
    from another rig setup.

    Episodes whose manifest has no fingerprint (older recordings) are not compared.

    Raises:
        RecordingError: one line naming the differing components (stored vs this rig) and the fix.
    """
    mine = rig if isinstance(rig, RigFingerprint) else rig_fingerprint(rig)
    for summary in store.list(include_failures=True):
        try:
            manifest = EpisodeManifest.model_validate_json((summary.path / "manifest.json").read_bytes())
            stored_json = manifest.extra.get(MANIFEST_KEY)
            if stored_json is None:
                continue
            stored = RigFingerprint.from_json(stored_json)
        except (OSError, ValidationError, ValueError) as exc:
            _log.warning("cannot read the fingerprint of %s: %s", summary.path, exc)
            continue
        if stored.digest == mine.digest:
            continue
        diffs = [f"{name}: {theirs} vs {ours}" for name, theirs, ours in stored.differences(mine)]
        more = len(diffs) - _MAX_DIFFS
        shown = "; ".join(diffs[:_MAX_DIFFS]) + (f"; and {more} more" if more > 0 else "")
        raise RecordingError(
            f"rig differs from episode {summary.id} in {store.root} (stored vs this rig): {shown}; "
            "record into another data root, or restore the stored setup"
        )
