"""A gate's verdict and an episode's quality report, with their JSON form (index, manifest, exports)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

from pydantic import JsonValue

from telerig.config.qa import GATES
from telerig.errors import RecordingError

__all__ = ["REPORT_FORMAT", "GateVerdict", "QaReport"]

#: Version of :meth:`QaReport.to_json`'s layout.
REPORT_FORMAT = 1


@dataclass(frozen=True, slots=True)
class GateVerdict:
    """What one quality gate found in an episode.

    Attributes:
        gate: The gate (a :data:`~telerig.config.qa.GateName`), e.g. ``joint_limits``.
        passed: True passed, False failed; ``None`` not applicable (a fall on a fixed arm, no F/T
            recorded): ``detail`` says why.
        value: The measured value the threshold applies to, in ``unit``; ``None`` when nothing was
            measured.
        threshold: The threshold it was held to, in ``unit``.
        unit: Unit of ``value`` and ``threshold``, e.g. ``s``, ``rad``, ``N``, ``ms``, ``fraction``.
        detail: One line a person understands, e.g. "joint wrist_2_joint at 1.07x its velocity
            limit at t=3.2 s".
        events: Times to mark on plots [s from the episode start]: where each violation begins.
    """

    gate: str
    passed: bool | None
    value: float | None
    threshold: float | None
    unit: str
    detail: str
    events: tuple[float, ...] = ()

    def to_json(self) -> dict[str, JsonValue]:
        """JSON data (``value``/``threshold`` ``null`` when not finite)."""
        return {
            "gate": self.gate,
            "passed": self.passed,
            "value": _finite(self.value),
            "threshold": _finite(self.threshold),
            "unit": self.unit,
            "detail": self.detail,
            "events": [round(t, 4) for t in self.events],
        }

    @classmethod
    def from_json(cls, data: Mapping[str, JsonValue]) -> GateVerdict:
        """The verdict :meth:`to_json` wrote.

        Raises:
            RecordingError: ``data`` is not a verdict (names the field).
        """
        try:
            passed = data["passed"]
            events = data.get("events") or []
            if passed is not None and not isinstance(passed, bool):
                raise TypeError("passed")
            if not isinstance(events, list):
                raise TypeError("events")
            return cls(
                gate=str(data["gate"]),
                passed=passed,
                value=_float(data.get("value")),
                threshold=_float(data.get("threshold")),
                unit=str(data.get("unit", "")),
                detail=str(data.get("detail", "")),
                events=tuple(float(_number(t)) for t in events),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise RecordingError(f"gate verdict is malformed at {exc}: {str(data)[:200]}") from None


@dataclass(frozen=True, slots=True)
class QaReport:
    """The quality gates' verdicts on one episode.

    Attributes:
        episode_id: The episode.
        verdicts: One per gate that ran, in :data:`~telerig.config.qa.GATES` order.
        idle_fraction: Share of the episode's time without meaningful motion, in [0, 1].
        idle_segments: Idle stretches exports may trim, ``(start, end)`` [s from the episode
            start], sorted: the idle head and tail, and pauses of at least ``idle_min_pause_s``.
    """

    episode_id: str
    verdicts: tuple[GateVerdict, ...]
    idle_fraction: float
    idle_segments: tuple[tuple[float, float], ...] = ()

    @property
    def passed(self) -> bool:
        """No gate failed (not-applicable gates do not fail an episode)."""
        return all(v.passed is not False for v in self.verdicts)

    @property
    def reasons(self) -> tuple[str, ...]:
        """Why the episode failed, one ``"<gate>: <detail>"`` line per failed gate; empty if it passed."""
        return tuple(f"{v.gate}: {v.detail}" for v in self.verdicts if v.passed is False)

    def verdict(self, gate: str) -> GateVerdict | None:
        """The verdict of ``gate``; ``None`` when it did not run.

        Raises:
            ValueError: ``gate`` is not a gate name.
        """
        if gate not in GATES:
            raise ValueError(f"gate {gate!r} does not exist. Available: {', '.join(GATES)}")
        return next((v for v in self.verdicts if v.gate == gate), None)

    def to_json(self) -> dict[str, JsonValue]:
        """JSON data for the index and the manifest (``QaReport.from_json`` reads it back)."""
        return {
            "format": REPORT_FORMAT,
            "episode_id": self.episode_id,
            "passed": self.passed,
            "reasons": list(self.reasons),
            "idle_fraction": self.idle_fraction,
            "idle_segments": [[round(a, 4), round(b, 4)] for a, b in self.idle_segments],
            "verdicts": [v.to_json() for v in self.verdicts],
        }

    @classmethod
    def from_json(cls, data: Mapping[str, JsonValue]) -> QaReport:
        """The report :meth:`to_json` wrote (``passed`` and ``reasons`` are recomputed from the verdicts).

        Raises:
            RecordingError: ``data`` is not a report of this format (one line naming the field).
        """
        fmt = data.get("format")
        if fmt != REPORT_FORMAT:
            raise RecordingError(f"quality report format {fmt!r} is not {REPORT_FORMAT}; re-run telerig qa")
        try:
            verdicts = data["verdicts"]
            segments = data.get("idle_segments") or []
            if not isinstance(verdicts, list) or not isinstance(segments, list):
                raise TypeError("verdicts")
            parsed: list[GateVerdict] = []
            for v in verdicts:
                if not isinstance(v, dict):
                    raise TypeError("verdicts")
                parsed.append(GateVerdict.from_json(v))
            spans: list[tuple[float, float]] = []
            for s in segments:
                if not isinstance(s, list) or len(s) != 2:
                    raise TypeError("idle_segments")
                spans.append((float(_number(s[0])), float(_number(s[1]))))
            return cls(
                episode_id=str(data["episode_id"]),
                verdicts=tuple(parsed),
                idle_fraction=float(_number(data["idle_fraction"])),
                idle_segments=tuple(spans),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise RecordingError(f"quality report is malformed at {exc}") from None


def _finite(value: float | None) -> float | None:
    return value if value is not None and math.isfinite(value) else None


def _number(value: JsonValue) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise TypeError(repr(value)[:40])
    return float(value)


def _float(value: JsonValue) -> float | None:
    return None if value is None else _number(value)
