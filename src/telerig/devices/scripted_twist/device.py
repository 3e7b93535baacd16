"""A scripted SpaceMouse stand-in: a looping twist script with button presses, for dry runs and tests."""

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
from telerig.ir.types import ControllerState, FloatArray, Handedness, Stamp, Twist, now_ns

__all__ = ["ScriptedTwistDevice", "TwistSegment"]

_log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class TwistSegment:
    """One step of a twist script.

    Attributes:
        duration_s: How long the segment lasts [s], > 0.
        linear: Linear velocity held during the segment [m/s], operator frame. Shape (3,).
        angular: Angular velocity held during the segment [rad/s], operator frame. Shape (3,).
        buttons: Buttons held during the segment.
    """

    duration_s: float
    linear: tuple[float, float, float] = (0.0, 0.0, 0.0)
    angular: tuple[float, float, float] = (0.0, 0.0, 0.0)
    buttons: frozenset[str] = frozenset()


def _min_jerk(u: float) -> float:
    """s(u) = 10u^3 - 15u^4 + 6u^5 on u in [0, 1]: zero velocity and acceleration at both ends."""
    u = 0.0 if u < 0.0 else 1.0 if u > 1.0 else u
    return u * u * u * (10.0 + u * (-15.0 + 6.0 * u))


class ScriptedTwistDevice:
    """Emits what a SpaceMouse does, from a script: ``Twist`` samples (source ``<id>``, device part
    ``twist``) at ``rate_hz`` while the script runs, and a button ``ControllerState`` (source
    ``<id>/buttons``, part ``<hand>_controller``, pose at the origin) whenever the held buttons change.

    A rig tested with it runs unchanged with ``type: spacemouse``: same samples, same parts. Each
    segment holds a twist; the twist blends from the previous segment's over ``ramp_s`` with a
    minimum-jerk profile, as a hand deflects the cap smoothly. The script loops when ``loop``
    (otherwise the last segment's twist holds). ``sample_at`` is pure (deterministic tests);
    ``start`` stamps with real clocks on its own thread.
    """

    def __init__(
        self,
        id: str = "twist0",
        *,
        segments: Sequence[TwistSegment],
        rate_hz: float = 100.0,
        ramp_s: float = 0.2,
        loop: bool = True,
        hand: Handedness = "right",
        frame_id: str = "operator",
    ) -> None:
        """Args:
        id: Device id; ``Twist`` source id, and ``<id>/buttons`` for buttons.
        segments: The script, at least one segment.
        rate_hz: ``Twist`` sample rate [Hz], in (0, 2000].
        ramp_s: Blend time between segment twists [s], >= 0 (capped at each segment's duration).
        loop: Start over after the last segment.
        hand: Hand reported in the button ``ControllerState`` (its device part).
        frame_id: Frame of the twists.
        """
        if not segments:
            raise ConfigError("a twist script needs at least one segment, e.g. [{duration_s: 1.0}]")
        for i, seg in enumerate(segments):
            if not (math.isfinite(seg.duration_s) and seg.duration_s > 0):
                raise ConfigError(f"segments[{i}].duration_s must be > 0 s, got {seg.duration_s}")
            if not all(math.isfinite(v) for v in (*seg.linear, *seg.angular)):
                raise ConfigError(f"segments[{i}]: linear and angular must be finite")
        if not (math.isfinite(rate_hz) and 0.0 < rate_hz <= 2000.0):
            raise ConfigError(f"rate_hz must be in (0, 2000], got {rate_hz}")
        if not (math.isfinite(ramp_s) and ramp_s >= 0.0):
            raise ConfigError(f"ramp_s must be >= 0 s, got {ramp_s}")
        if hand not in ("left", "right"):
            raise ConfigError(f"hand must be 'left' or 'right', got {hand!r}")
        self._id = id
        self.segments = tuple(segments)
        self.rate_hz = float(rate_hz)
        self.ramp_s = float(ramp_s)
        self.loop = loop
        self.hand: Handedness = hand
        self.frame_id = frame_id
        self.source_id = id
        self.buttons_source_id = f"{id}/buttons"
        self.duration_s = float(sum(s.duration_s for s in self.segments))
        self._starts = np.cumsum([0.0, *(s.duration_s for s in self.segments)])
        self._worker = DeviceWorker(id, kind="scripted twist", thread_name=f"telerig-twist-{id}", log=_log)
        self._rate = FixedRate(self.rate_hz)

    @property
    def id(self) -> str:
        """Device id."""
        return self._id

    @property
    def on_change_streams(self) -> frozenset[str]:
        """The buttons: sent when the held set changes (:class:`~telerig.devices.base.ChangeDrivenDevice`)."""
        return frozenset({f"{self.hand}_controller"})

    @property
    def running(self) -> bool:
        """Whether the emitting thread is running."""
        return self._worker.running

    @property
    def overruns(self) -> int:
        """Ticks skipped because a tick ran late, since construction."""
        return self._rate.overruns

    def segment_index(self, t_s: float) -> int:
        """Index of the segment active ``t_s`` seconds after start."""
        tc = t_s % self.duration_s if self.loop else min(t_s, self.duration_s - 1e-12)
        return int(np.searchsorted(self._starts, tc, side="right")) - 1

    def twist_at(self, t_s: float) -> tuple[FloatArray, FloatArray]:
        """Linear [m/s] and angular [rad/s] velocity ``t_s`` seconds after start, operator frame."""
        i = self.segment_index(t_s)
        seg = self.segments[i]
        tc = t_s % self.duration_s if self.loop else min(t_s, self.duration_s)
        into = tc - float(self._starts[i])
        # At rest before the first segment; when looping, segments[-1] precedes segments[0].
        prev = TwistSegment(1.0) if i == 0 and not self.loop else self.segments[i - 1]
        ramp = min(self.ramp_s, seg.duration_s)
        s = 1.0 if ramp == 0.0 else _min_jerk(into / ramp)
        linear = np.add(prev.linear, s * np.subtract(seg.linear, prev.linear))
        angular = np.add(prev.angular, s * np.subtract(seg.angular, prev.angular))
        return linear, angular

    def buttons_at(self, t_s: float) -> frozenset[str]:
        """Buttons held ``t_s`` seconds after start."""
        return self.segments[self.segment_index(t_s)].buttons

    def sample_at(self, t_s: float, seq: int = 0) -> Twist:
        """The ``Twist`` ``t_s`` seconds after start, stamped ``device_ns = capture_ns = t_s`` [ns]; pure."""
        t_ns = round(t_s * 1e9)
        linear, angular = self.twist_at(t_s)
        return Twist(Stamp(self.source_id, seq, t_ns, t_ns), linear, angular, self.frame_id)

    def start(self, sink: SampleSink) -> None:
        """Emit samples into ``sink`` from a new thread, starting at script time 0.

        Raises:
            DeviceError: the device is already running.
        """
        self._worker.start(self._run, sink)

    def stop(self) -> None:
        """Stop emitting and join the thread. Idempotent."""
        self._worker.stop()

    def _buttons_sample(self, buttons: frozenset[str], stamp: Stamp) -> ControllerState:
        return ControllerState(
            stamp=stamp,
            hand=self.hand,
            position=np.zeros(3),
            orientation=np.array([1.0, 0.0, 0.0, 0.0]),
            frame_id=self.frame_id,
            buttons=buttons,
        )

    def _run(self, sink: SampleSink, stop: threading.Event) -> None:
        button_seq = 0
        held: frozenset[str] = frozenset()
        for seq, (device_ns, t) in enumerate(self._rate.ticks(stop)):
            capture_ns = now_ns()
            buttons = self.buttons_at(t)
            if buttons != held:
                held = buttons
                stamp = Stamp(self.buttons_source_id, button_seq, device_ns, capture_ns)
                self._worker.deliver(sink, self._buttons_sample(buttons, stamp))
                button_seq += 1
            linear, angular = self.twist_at(t)
            stamp = Stamp(self.source_id, seq, device_ns, capture_ns)
            self._worker.deliver(sink, Twist(stamp, linear, angular, self.frame_id))
