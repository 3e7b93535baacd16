"""A scripted VR controller that replays a smooth pick-and-place, for demos and tests.

Frames and conventions:

* Operator frame ``"operator"``: x forward, y left, z up, metres; the default positions assume its
  origin on the floor under the operator, hands at about waist height.
* Controller frame (the frame ``ControllerState.orientation`` rotates into the operator frame):
  +z is the pointing axis (like a robot flange's approach axis), +x is the controller's top.
* Quaternions are (w, x, y, z), Hamilton, active: ``orientation`` maps controller-frame vectors
  to operator-frame vectors. Pointing down is :data:`POINTING_DOWN` = (0, 1, 0, 0), a half turn
  about operator x: controller z -> operator -z (down), x -> +x (forward), y -> -y (right).

Real VR drivers (OpenXR's grip pose has -z forward, +y up) convert into this convention.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from telerig.devices.base import SampleSink
from telerig.devices.worker import DeviceWorker, FixedRate
from telerig.errors import ConfigError
from telerig.ir.types import ControllerState, FloatArray, Handedness, Stamp, now_ns

__all__ = ["POINTING_DOWN", "ButtonPress", "ScriptedVRController", "Segment"]

_log = logging.getLogger(__name__)

#: Controller orientation (w, x, y, z) pointing straight down with its top forward.
POINTING_DOWN: tuple[float, float, float, float] = (0.0, 1.0, 0.0, 0.0)

# Nominal segment durations [s] for a 10 s cycle; scaled to ``cycle_s``.
_NOMINAL: tuple[tuple[str, float], ...] = (
    ("approach", 1.5),  # home -> above pick
    ("descend", 1.0),  # above pick -> pick
    ("grasp", 0.6),  # at pick, trigger closes
    ("lift", 1.0),  # pick -> above pick
    ("transfer", 1.5),  # above pick -> above place
    ("lower", 1.0),  # above place -> place
    ("release", 0.6),  # at place, trigger opens
    ("retreat", 1.0),  # place -> above place
    ("return", 1.5),  # above place -> home
    ("idle", 0.3),  # at home
)
_NOMINAL_CYCLE_S = sum(d for _, d in _NOMINAL)
_TRIGGER_RAMP_S = 0.3


@dataclass(frozen=True, slots=True)
class Segment:
    """One phase of the scripted cycle.

    Attributes:
        phase: Name, e.g. ``"approach"``, ``"grasp"``.
        start_s: Start time within the cycle [s].
        end_s: End time within the cycle [s].
        start: Controller position at the start [m], operator frame. Shape (3,).
        end: Controller position at the end [m], operator frame. Shape (3,).
        trigger_start: Trigger value at the start, in [0, 1].
        trigger_end: Trigger value at the end, in [0, 1].
    """

    phase: str
    start_s: float
    end_s: float
    start: FloatArray
    end: FloatArray
    trigger_start: float
    trigger_end: float


@dataclass(frozen=True, slots=True)
class ButtonPress:
    """A button held down during part of every cycle.

    Attributes:
        button: Button name, e.g. ``"a"``.
        start_s: Press time within the cycle [s].
        end_s: Release time within the cycle [s].
    """

    button: str
    start_s: float
    end_s: float


def _min_jerk(u: float) -> float:
    """Minimum-jerk profile s(u) = 10u^3 - 15u^4 + 6u^5 on u in [0, 1] (zero vel/acc at both ends)."""
    u = 0.0 if u < 0.0 else 1.0 if u > 1.0 else u
    return u * u * u * (10.0 + u * (-15.0 + 6.0 * u))


def _point(value: Sequence[float], name: str) -> FloatArray:
    arr = np.array(value, dtype=np.float64)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ConfigError(f"{name} must be three finite coordinates (x, y, z) in metres, got {value!r}")
    arr.flags.writeable = False
    return arr


class ScriptedVRController:
    """A VR controller that plays a looping pick-and-place with minimum-jerk motion.

    Cycle: home -> above pick -> pick -> trigger closes (ramp to 1 over 0.3 s) -> above pick ->
    above place -> place -> trigger opens -> above place -> home -> short idle. The controller
    points down throughout (:data:`POINTING_DOWN`) and holds grip at ``grip`` (e.g. a deadman).

    ``sample_at`` is pure (deterministic tests); ``start`` emits ``ControllerState`` samples at
    ``rate_hz`` on its own thread with absolute deadlines, stamped with ``device_ns`` from the
    device's monotonic clock and ``capture_ns`` from the common clock at capture.
    """

    def __init__(
        self,
        id: str = "vr0",
        *,
        hand: Handedness = "right",
        rate_hz: float = 100.0,
        pick: Sequence[float] = (0.45, 0.10, 0.85),
        place: Sequence[float] = (0.45, -0.25, 0.85),
        home: Sequence[float] = (0.30, -0.10, 1.00),
        lift_m: float = 0.10,
        cycle_s: float = 10.0,
        grip: float = 1.0,
        presses: Sequence[ButtonPress] = (),
        frame_id: str = "operator",
    ) -> None:
        """Args:
        id: Device id; samples are stamped with source id ``"<id>/<hand>"``.
        hand: Hand holding the controller.
        rate_hz: Sample rate [Hz] (> 0, <= 2000).
        pick: Grasp point [m], operator frame. Shape (3,).
        place: Release point [m], operator frame. Shape (3,).
        home: Start and end point [m], operator frame. Shape (3,).
        lift_m: Height of the approach points above pick and place [m] (>= 0).
        cycle_s: Duration of one cycle [s] (>= 3; segments scale with it, the trigger ramp does not).
        grip: Grip value held throughout, in [0, 1].
        presses: Buttons held during parts of each cycle.
        frame_id: Frame the positions are in.
        """
        if hand not in ("left", "right"):
            raise ConfigError(f"hand must be 'left' or 'right', got {hand!r}")
        if not (math.isfinite(rate_hz) and 0.0 < rate_hz <= 2000.0):
            raise ConfigError(f"rate_hz must be in (0, 2000], got {rate_hz}")
        if not (math.isfinite(cycle_s) and cycle_s >= 3.0):
            raise ConfigError(f"cycle_s must be at least 3 s, got {cycle_s}")
        if not (math.isfinite(lift_m) and lift_m >= 0.0):
            raise ConfigError(f"lift_m must be >= 0 m, got {lift_m}")
        if not 0.0 <= grip <= 1.0:
            raise ConfigError(f"grip must be in [0, 1], got {grip}")
        for p in presses:
            if not 0.0 <= p.start_s < p.end_s <= cycle_s:
                raise ConfigError(
                    f"button press {p} must satisfy 0 <= start_s < end_s <= cycle_s ({cycle_s})"
                )
        self._id = id
        self.hand: Handedness = hand
        self.rate_hz = float(rate_hz)
        self.cycle_s = float(cycle_s)
        self.grip = float(grip)
        self.presses: tuple[ButtonPress, ...] = tuple(presses)
        self.frame_id = frame_id
        self.source_id = f"{id}/{hand}"
        self.pick = _point(pick, "pick")
        self.place = _point(place, "place")
        self.home = _point(home, "home")
        up = np.array([0.0, 0.0, lift_m])
        above_pick, above_place = self.pick + up, self.place + up
        waypoints = (
            (self.home, above_pick, 0.0, 0.0),
            (above_pick, self.pick, 0.0, 0.0),
            (self.pick, self.pick, 0.0, 1.0),
            (self.pick, above_pick, 1.0, 1.0),
            (above_pick, above_place, 1.0, 1.0),
            (above_place, self.place, 1.0, 1.0),
            (self.place, self.place, 1.0, 0.0),
            (self.place, above_place, 0.0, 0.0),
            (above_place, self.home, 0.0, 0.0),
            (self.home, self.home, 0.0, 0.0),
        )
        scale = self.cycle_s / _NOMINAL_CYCLE_S
        segments: list[Segment] = []
        t = 0.0
        for (phase, nominal), (start, end, g0, g1) in zip(_NOMINAL, waypoints, strict=True):
            duration = nominal * scale
            segments.append(Segment(phase, t, t + duration, start.copy(), end.copy(), g0, g1))
            t += duration
        self.segments: tuple[Segment, ...] = tuple(segments)
        self._orientation = np.array(POINTING_DOWN)
        self._orientation.flags.writeable = False
        self._joystick = np.zeros(2)
        self._joystick.flags.writeable = False
        self._worker = DeviceWorker(
            id, kind="scripted controller", thread_name=f"telerig-scripted-{id}", log=_log
        )
        self._rate = FixedRate(self.rate_hz)

    @property
    def id(self) -> str:
        """Device id."""
        return self._id

    @property
    def running(self) -> bool:
        """Whether the emitting thread is running."""
        return self._worker.running

    @property
    def overruns(self) -> int:
        """Ticks skipped because a tick ran late, since construction."""
        return self._rate.overruns

    def segment_at(self, t_s: float) -> Segment:
        """The segment active at ``t_s`` seconds after start (the cycle repeats)."""
        tc = t_s % self.cycle_s
        for seg in self.segments:
            if tc < seg.end_s:
                return seg
        return self.segments[-1]

    def phase_at(self, t_s: float) -> str:
        """Name of the phase at ``t_s`` seconds after start, e.g. ``"grasp"``."""
        return self.segment_at(t_s).phase

    def sample_at(self, t_s: float, seq: int = 0) -> ControllerState:
        """The controller state ``t_s`` seconds after start; pure and deterministic.

        The stamp has ``device_ns = capture_ns = round(t_s * 1e9)`` and the given ``seq``;
        :meth:`start` restamps with real clocks.
        """
        t_ns = round(t_s * 1e9)
        return self._state(t_s, Stamp(self.source_id, seq, t_ns, t_ns))

    def start(self, sink: SampleSink) -> None:
        """Emit samples into ``sink`` at ``rate_hz`` from a new thread, starting at trajectory time 0.

        Raises:
            DeviceError: If the controller is already running.
        """
        self._worker.start(self._run, sink)

    def stop(self) -> None:
        """Stop emitting and join the thread. Idempotent."""
        self._worker.stop()

    def _state(self, t_s: float, stamp: Stamp) -> ControllerState:
        seg = self.segment_at(t_s)
        tc = t_s % self.cycle_s
        duration = seg.end_s - seg.start_s
        s = _min_jerk((tc - seg.start_s) / duration)
        position = seg.start + s * (seg.end - seg.start)
        if seg.trigger_start == seg.trigger_end:
            trigger = seg.trigger_start
        else:
            # Ramp in the middle of the dwell so the hand is still while the trigger moves.
            ramp = min(_TRIGGER_RAMP_S, duration)
            t0 = seg.start_s + 0.5 * (duration - ramp)
            r = _min_jerk((tc - t0) / ramp)
            trigger = seg.trigger_start + r * (seg.trigger_end - seg.trigger_start)
        buttons = frozenset(p.button for p in self.presses if p.start_s <= tc < p.end_s)
        return ControllerState(
            stamp=stamp,
            hand=self.hand,
            position=position,
            orientation=self._orientation,
            frame_id=self.frame_id,
            buttons=buttons,
            trigger=trigger,
            grip=self.grip,
            joystick=self._joystick,
        )

    def _run(self, sink: SampleSink, stop: threading.Event) -> None:
        for seq, (device_ns, t) in enumerate(self._rate.ticks(stop)):
            stamp = Stamp(self.source_id, seq, device_ns, now_ns())
            self._worker.deliver(sink, self._state(t, stamp))
