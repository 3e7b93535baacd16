"""Sample validation for every device: drop non-finite, out-of-range, late, jumpy or unsure samples."""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType
from typing import Literal, Protocol, runtime_checkable

import numpy as np

from telerig.bus.catalogue import device_stream
from telerig.config.schema import ValidationConfig
from telerig.errors import ConfigError
from telerig.ir.types import (
    BaseVelocity,
    BodySkeleton,
    ControllerState,
    FloatArray,
    HandPose,
    Pose,
    Sample,
    Twist,
    now_ns,
)

__all__ = [
    "DROP_REASONS",
    "ConfidenceCheck",
    "DropReason",
    "FiniteCheck",
    "GapCheck",
    "JumpCheck",
    "MonotonicCheck",
    "REJECT_REASONS",
    "RangeCheck",
    "RejectReason",
    "SampleCheck",
    "SampleGate",
    "SampleValidator",
    "StampCheck",
    "Track",
    "ValidationConfig",
    "ValidationStats",
    "position_of",
    "stream_of",
]

log = logging.getLogger(__name__)

#: Why a sample was dropped.
DropReason = Literal[
    "non_finite", "out_of_range", "low_confidence", "future_stamp", "non_monotonic", "gap", "jump"
]

#: Every :data:`DropReason`, in the order the default validator checks them.
DROP_REASONS: tuple[DropReason, ...] = (
    "non_finite",
    "out_of_range",
    "low_confidence",
    "future_stamp",
    "non_monotonic",
    "gap",
    "jump",
)


def stream_of(sample: Sample) -> str:
    """The device part a sample belongs to: its bus stream (:func:`telerig.bus.catalogue.device_stream`:
    ``right_controller``, ``left_hand``, ``head`` for source ``quest/head``...); samples that are not
    device samples (commands, joint states) get their class name.
    """
    try:
        return device_stream(sample)
    except ValueError:
        return type(sample).__name__


def position_of(sample: Sample) -> FloatArray | None:
    """The tracked position(s) of a sample [m]: shape (3,) for poses, controllers and hands (the
    wrist), (N, 3) for a skeleton; ``None`` for samples without a position."""
    match sample:
        case ControllerState() | Pose():
            return sample.position
        case HandPose():
            return sample.wrist_position
        case BodySkeleton():
            return sample.positions
        case _:
            return None


class Track:
    """What the validator remembers about one ``(source_id, stream)``; checks read it.

    Attributes:
        key: ``(source_id, stream)``.
        last_valid: The last accepted sample, or ``None``.
        last_ns: Capture time of ``last_valid`` [ns], common clock; 0 before the first.
        prev_ns: Capture time of the previous sample that was not older than ``last_ns`` (accepted
            or not) [ns]; what inter-frame gaps are measured from. 0 before the first.
        rejected: The previous sample if it was dropped as a ``jump`` (so a real re-centring of
            the tracker is accepted from its second sample on), else ``None``.
        period_ns: Inter-frame period learned from normal gaps [ns] (exponential average).
        gaps: Number of gaps ``period_ns`` was learned from.
    """

    __slots__ = ("gaps", "key", "last_ns", "last_valid", "period_ns", "prev_ns", "rejected")

    def __init__(self, key: tuple[str, str]) -> None:
        self.key = key
        self.last_valid: Sample | None = None
        self.last_ns = 0
        self.prev_ns = 0
        self.rejected: Sample | None = None
        self.period_ns = 0.0
        self.gaps = 0


@runtime_checkable
class SampleCheck(Protocol):
    """One rule a sample must pass; the validator runs its checks in order and stops at the first drop."""

    def check(self, sample: Sample, track: Track) -> DropReason | None:
        """Return ``None`` if ``sample`` passes, else why it must be dropped.

        ``track`` holds the stream's state before this sample; checks may only update the
        statistics they own (e.g. a learned period), never ``last_valid``.
        """
        ...


# ---------------------------------------------------------------------------------------------
# Non-finite values


def _finite_pose(s: Pose) -> bool:
    return math.isfinite(sum(s.position.tolist()) + sum(s.orientation.tolist()))


def _finite_controller(s: ControllerState) -> bool:
    total = sum(s.position.tolist()) + sum(s.orientation.tolist()) + sum(s.joystick.tolist())
    return math.isfinite(total + s.trigger + s.grip)


def _finite_hand(s: HandPose) -> bool:
    total = sum(s.wrist_position.tolist()) + sum(s.wrist_orientation.tolist())
    k, c = s.keypoints, s.keypoint_confidence
    return math.isfinite(total + float(np.vdot(k, k)) + float(np.vdot(c, c)))


def _finite_body(s: BodySkeleton) -> bool:
    p, q = s.positions, s.orientations
    return math.isfinite(float(np.vdot(p, p)) + float(np.vdot(q, q)))


def _finite_twist(s: Twist) -> bool:
    return math.isfinite(sum(s.linear.tolist()) + sum(s.angular.tolist()))


def _finite_base(s: BaseVelocity) -> bool:
    return math.isfinite(s.vx + s.vy + s.wz)


def _finite_any(s: object) -> bool:
    for f in dataclasses.fields(s):  # type: ignore[arg-type]
        value = getattr(s, f.name)
        if isinstance(value, np.ndarray):
            if value.dtype.kind == "f" and not math.isfinite(float(np.vdot(value, value))):
                return False
        elif isinstance(value, float) and not math.isfinite(value):
            return False
    return True


_FINITE: dict[type, Callable[[object], bool]] = {
    Pose: _finite_pose,  # type: ignore[dict-item]
    ControllerState: _finite_controller,  # type: ignore[dict-item]
    HandPose: _finite_hand,  # type: ignore[dict-item]
    BodySkeleton: _finite_body,  # type: ignore[dict-item]
    Twist: _finite_twist,  # type: ignore[dict-item]
    BaseVelocity: _finite_base,  # type: ignore[dict-item]
}


class FiniteCheck:
    """Drops samples with NaN or inf in any float or array field, or in ``stamp.confidence``.

    (Sums of values and of squares are tested, so finite values so large that they overflow,
    |x| > 1e154, also count as non-finite.)
    """

    __slots__ = ()

    def check(self, sample: Sample, track: Track) -> DropReason | None:
        if not math.isfinite(sample.stamp.confidence):
            return "non_finite"
        fn = _FINITE.get(type(sample), _finite_any)
        return None if fn(sample) else "non_finite"


# ---------------------------------------------------------------------------------------------
# Out-of-range values


_ONES3 = np.ones(3)
_ONES4 = np.ones(4)
_SQRT3 = math.sqrt(3.0)


def _sq(v: list[float]) -> float:
    return sum(x * x for x in v)


class RangeCheck:
    """Drops samples with values outside what any real device produces.

    Positions beyond ``workspace_radius_m`` from the frame origin, quaternions whose norm is
    more than ``quaternion_tolerance`` from 1, trigger/grip outside [0, 1], joystick components
    outside [-1, 1], keypoint confidences or ``stamp.confidence`` outside [0, 1], twists and base
    velocities faster than the velocity limits, and a missing capture time (``capture_ns <= 0``).
    Expects finite values (run after :class:`FiniteCheck`).
    """

    __slots__ = ("_handlers", "_q_hi", "_q_lo", "_r2", "max_angular_rad_s", "max_linear_m_s")

    def __init__(
        self,
        workspace_radius_m: float = 5.0,
        *,
        quaternion_tolerance: float = 0.01,
        max_linear_m_s: float = 10.0,
        max_angular_rad_s: float = 20.0,
    ) -> None:
        """Args:
        workspace_radius_m: Largest distance of a tracked point from its frame origin [m] (> 0).
        quaternion_tolerance: Allowed ``| |q| - 1 |`` of orientations, in (0, 1).
        max_linear_m_s: Largest linear speed of a ``Twist`` / ``BaseVelocity`` [m/s] (> 0).
        max_angular_rad_s: Largest angular speed of a ``Twist`` / ``BaseVelocity`` [rad/s] (> 0).
        """
        _positive("workspace_radius_m", workspace_radius_m)
        _positive("max_linear_m_s", max_linear_m_s)
        _positive("max_angular_rad_s", max_angular_rad_s)
        if not (math.isfinite(quaternion_tolerance) and 0.0 < quaternion_tolerance < 1.0):
            raise ConfigError(f"quaternion_tolerance must be in (0, 1), got {quaternion_tolerance}")
        self._r2 = workspace_radius_m * workspace_radius_m
        self._q_lo = (1.0 - quaternion_tolerance) ** 2
        self._q_hi = (1.0 + quaternion_tolerance) ** 2
        self.max_linear_m_s = float(max_linear_m_s)
        self.max_angular_rad_s = float(max_angular_rad_s)
        self._handlers: dict[type, Callable[[object], bool]] = {
            Pose: self._pose,  # type: ignore[dict-item]
            ControllerState: self._controller,  # type: ignore[dict-item]
            HandPose: self._hand,  # type: ignore[dict-item]
            BodySkeleton: self._body,  # type: ignore[dict-item]
            Twist: self._twist,  # type: ignore[dict-item]
            BaseVelocity: self._base,  # type: ignore[dict-item]
        }

    @property
    def workspace_radius_m(self) -> float:
        return math.sqrt(self._r2)

    def check(self, sample: Sample, track: Track) -> DropReason | None:
        stamp = sample.stamp
        if stamp.capture_ns <= 0 or not 0.0 <= stamp.confidence <= 1.0:
            return "out_of_range"
        fn = self._handlers.get(type(sample))
        return None if fn is None or fn(sample) else "out_of_range"

    def _quat_ok(self, q: FloatArray) -> bool:
        return self._q_lo <= _sq(q.tolist()) <= self._q_hi

    def _pose(self, s: Pose) -> bool:
        return _sq(s.position.tolist()) <= self._r2 and self._quat_ok(s.orientation)

    def _controller(self, s: ControllerState) -> bool:
        jx, jy = s.joystick.tolist()
        return (
            _sq(s.position.tolist()) <= self._r2
            and self._quat_ok(s.orientation)
            and 0.0 <= s.trigger <= 1.0
            and 0.0 <= s.grip <= 1.0
            and -1.0 <= jx <= 1.0
            and -1.0 <= jy <= 1.0
        )

    def _hand(self, s: HandPose) -> bool:
        if not (_sq(s.wrist_position.tolist()) <= self._r2 and self._quat_ok(s.wrist_orientation)):
            return False
        if not self._points_ok(s.keypoints):
            return False
        c = s.keypoint_confidence
        return float(c.min()) >= 0.0 and float(c.max()) <= 1.0

    def _body(self, s: BodySkeleton) -> bool:
        if not s.joint_names:
            return True
        if not self._points_ok(s.positions):
            return False
        n2 = np.square(s.orientations) @ _ONES4
        return float(n2.min()) >= self._q_lo and float(n2.max()) <= self._q_hi

    def _points_ok(self, p: FloatArray) -> bool:
        """Every row of ``p`` (N, 3) within the workspace radius; cheap bounds first."""
        if float(np.vdot(p, p)) <= self._r2 or float(np.abs(p).max()) * _SQRT3 <= math.sqrt(self._r2):
            return True
        return float(np.max(np.square(p) @ _ONES3)) <= self._r2

    def _twist(self, s: Twist) -> bool:
        v2 = self.max_linear_m_s**2
        w2 = self.max_angular_rad_s**2
        return _sq(s.linear.tolist()) <= v2 and _sq(s.angular.tolist()) <= w2

    def _base(self, s: BaseVelocity) -> bool:
        return s.vx * s.vx + s.vy * s.vy <= self.max_linear_m_s**2 and abs(s.wz) <= self.max_angular_rad_s


# ---------------------------------------------------------------------------------------------
# Confidence and timing


class ConfidenceCheck:
    """Drops samples whose producer is not sure of them: ``stamp.confidence < min_confidence``."""

    __slots__ = ("min_confidence",)

    def __init__(self, min_confidence: float = 0.5) -> None:
        """Args:
        min_confidence: Lowest accepted ``stamp.confidence``, in [0, 1] (0 accepts everything).
        """
        if not (math.isfinite(min_confidence) and 0.0 <= min_confidence <= 1.0):
            raise ConfigError(f"min_confidence must be in [0, 1], got {min_confidence}")
        self.min_confidence = float(min_confidence)

    def check(self, sample: Sample, track: Track) -> DropReason | None:
        return "low_confidence" if sample.stamp.confidence < self.min_confidence else None


class MonotonicCheck:
    """Drops samples not captured strictly after the stream's last accepted sample (``capture_ns``)."""

    __slots__ = ()

    def check(self, sample: Sample, track: Track) -> DropReason | None:
        return "non_monotonic" if sample.stamp.capture_ns <= track.last_ns else None


class StampCheck:
    """Drops samples captured implausibly far ahead of the clock (``future_stamp``).

    Runs before :class:`MonotonicCheck`, so a sample stamped an hour (or 2^62 ns) ahead never
    becomes the stream's reference and the real samples after it still pass: one bad stamp costs
    one sample, not the episode.
    """

    __slots__ = ("_clock", "_max_future_ns")

    def __init__(self, max_future_s: float = 0.5, *, clock: Callable[[], int] = now_ns) -> None:
        """Args:
        max_future_s: How far a capture time may be ahead of ``clock`` [s] (> 0): clock-sync
            error between stations, never a real capture.
        clock: The rig's common clock [ns] (the clock of ``capture_ns``).
        """
        _positive("max_future_s", max_future_s)
        self._max_future_ns = int(max_future_s * 1e9)
        self._clock = clock

    def check(self, sample: Sample, track: Track) -> DropReason | None:
        return "future_stamp" if sample.stamp.capture_ns - self._clock() > self._max_future_ns else None


class GapCheck:
    """Drops a sample that arrives after an abnormally long inter-frame gap (capture time).

    The gap is measured from the previous sample of the stream (accepted or not, see
    :attr:`Track.prev_ns`), so after an outage only the first sample is dropped. A gap is abnormal
    when it exceeds ``max(max_gap_factor * period, min_gap_s)``; the period is ``expected_period_s``
    when given, else learned per stream from the normal gaps (exponential average, weight
    ``1/16``) once ``warmup`` gaps were seen; before that nothing is dropped. Streams a device
    sends only when their value changes (``on_change``, see
    :class:`~telerig.devices.base.ChangeDrivenDevice`) have no period and are not checked.
    """

    __slots__ = ("_alpha", "_expected_ns", "_min_gap_ns", "_on_change", "max_gap_factor", "warmup")

    def __init__(
        self,
        max_gap_factor: float = 5.0,
        *,
        min_gap_s: float = 0.05,
        expected_period_s: float | None = None,
        warmup: int = 5,
        on_change: Collection[str] = (),
    ) -> None:
        """Args:
        max_gap_factor: Gap threshold in periods (> 1).
        min_gap_s: Smallest gap ever called abnormal [s] (>= 0), so OS jitter on fast devices
            does not count.
        expected_period_s: Nominal period of every stream [s] (> 0); ``None`` learns it.
        warmup: Gaps to learn from before checking (>= 1) when the period is learned.
        on_change: Streams (:func:`stream_of`) sent only when their value changes: never checked.
        """
        if not (math.isfinite(max_gap_factor) and max_gap_factor > 1.0):
            raise ConfigError(f"max_gap_factor must be > 1, got {max_gap_factor}")
        if not (math.isfinite(min_gap_s) and min_gap_s >= 0.0):
            raise ConfigError(f"min_gap_s must be >= 0 s, got {min_gap_s}")
        if expected_period_s is not None:
            _positive("expected_period_s", expected_period_s)
        if warmup < 1:
            raise ConfigError(f"warmup must be >= 1 gap, got {warmup}")
        self.max_gap_factor = float(max_gap_factor)
        self._min_gap_ns = min_gap_s * 1e9
        self._expected_ns = None if expected_period_s is None else expected_period_s * 1e9
        self.warmup = int(warmup)
        self._alpha = 1.0 / 16.0
        self._on_change = frozenset(on_change)

    def check(self, sample: Sample, track: Track) -> DropReason | None:
        if track.prev_ns == 0 or track.key[1] in self._on_change:
            return None
        gap = sample.stamp.capture_ns - track.prev_ns
        if gap <= 0:
            return None
        period = self._expected_ns
        if period is None:
            if track.gaps < self.warmup:
                self._learn(track, gap)
                return None
            period = track.period_ns
        if gap > self.max_gap_factor * period and gap > self._min_gap_ns:
            return "gap"
        if self._expected_ns is None:
            self._learn(track, gap)
        return None

    def _learn(self, track: Track, gap: int) -> None:
        if track.gaps == 0:
            track.period_ns = float(gap)
        else:
            track.period_ns += self._alpha * (gap - track.period_ns)
        track.gaps += 1


def _displacement_sq(a: FloatArray, b: FloatArray) -> float | None:
    """Largest squared distance between corresponding points [m^2]; ``None`` if shapes differ."""
    if a.shape != b.shape:
        return None
    if a.ndim == 1:
        ax, ay, az = a.tolist()
        bx, by, bz = b.tolist()
        return float((ax - bx) ** 2 + (ay - by) ** 2 + (az - bz) ** 2)
    if a.shape[0] == 0:
        return 0.0
    d = a - b
    return float(np.max(np.square(d) @ _ONES3))


class JumpCheck:
    """Drops a sample whose position jumped faster than a human moves since the last valid one.

    Allowed displacement = ``max_speed_m_s * dt + tolerance_m`` (dt from the last accepted sample).
    If the previous sample was dropped as a jump and this one is consistent with it, the jump was
    real (tracker re-centred, device re-mounted) and this sample is accepted, so a stream is never
    locked out; a single outlier costs one sample.
    """

    __slots__ = ("max_speed_m_s", "tolerance_m")

    def __init__(self, max_speed_m_s: float = 10.0, *, tolerance_m: float = 0.02) -> None:
        """Args:
        max_speed_m_s: Largest plausible speed of a tracked point [m/s] (> 0).
        tolerance_m: Displacement always allowed, for noise between close samples [m] (>= 0).
        """
        _positive("max_speed_m_s", max_speed_m_s)
        if not (math.isfinite(tolerance_m) and tolerance_m >= 0.0):
            raise ConfigError(f"tolerance_m must be >= 0 m, got {tolerance_m}")
        self.max_speed_m_s = float(max_speed_m_s)
        self.tolerance_m = float(tolerance_m)

    def check(self, sample: Sample, track: Track) -> DropReason | None:
        last = track.last_valid
        if last is None:
            return None
        pos = position_of(sample)
        if pos is None:
            return None
        ns = sample.stamp.capture_ns
        if self._consistent(pos, ns, last):
            return None
        rejected = track.rejected
        if rejected is not None and self._consistent(pos, ns, rejected):
            return None
        return "jump"

    def _consistent(self, pos: FloatArray, ns: int, ref: Sample) -> bool:
        ref_pos = position_of(ref)
        if ref_pos is None:
            return True
        d2 = _displacement_sq(pos, ref_pos)
        if d2 is None:
            return True  # e.g. a skeleton that changed its joint set: nothing to compare
        allowed = self.max_speed_m_s * max(ns - ref.stamp.capture_ns, 0) * 1e-9 + self.tolerance_m
        return d2 <= allowed * allowed


def _positive(name: str, value: float) -> None:
    if not (math.isfinite(value) and value > 0.0):
        raise ConfigError(f"{name} must be a finite value > 0, got {value}")


# ---------------------------------------------------------------------------------------------
# The validator


@dataclass(frozen=True, slots=True)
class ValidationStats:
    """Counters of a validator.

    Attributes:
        received: Samples validated.
        accepted: Samples that passed.
        dropped: Samples dropped, per :data:`DropReason` (every reason present, 0 if none).
    """

    received: int
    accepted: int
    dropped: Mapping[str, int]


class SampleValidator:
    """Runs every sample through a list of :class:`SampleCheck` and remembers the last valid one.

    State is kept per ``(stamp.source_id, stream)`` (:func:`stream_of`). A dropped sample is
    counted under the first check that rejects it. Not thread-safe: call from one thread (the
    device node serializes its sink).
    """

    def __init__(self, checks: Sequence[SampleCheck]) -> None:
        """Args:
        checks: Checks in the order they run; see :meth:`default` for the recommended list.
        """
        for i, c in enumerate(checks):
            if not isinstance(c, SampleCheck):
                raise ConfigError(f"checks[{i}] ({type(c).__name__}) has no check(sample, track) method")
        self.checks: tuple[SampleCheck, ...] = tuple(checks)
        self._tracks: dict[tuple[str, str], Track] = {}
        self._dropped: dict[str, int] = dict.fromkeys(DROP_REASONS, 0)
        self.received = 0
        self.accepted = 0

    @classmethod
    def default(
        cls,
        *,
        workspace_radius_m: float = 5.0,
        quaternion_tolerance: float = 0.01,
        max_linear_m_s: float = 10.0,
        max_angular_rad_s: float = 20.0,
        min_confidence: float = 0.5,
        max_gap_factor: float = 5.0,
        min_gap_s: float = 0.05,
        expected_period_s: float | None = None,
        max_speed_m_s: float = 10.0,
        jump_tolerance_m: float = 0.02,
        max_future_s: float = 0.5,
        on_change_streams: Collection[str] = (),
    ) -> SampleValidator:
        """The recommended checks: finite, range, confidence, stamp, monotonic, gap, jump (see each
        class); ``on_change_streams`` are the device's streams sent only on a change (no gap check)."""
        return cls(
            [
                FiniteCheck(),
                RangeCheck(
                    workspace_radius_m,
                    quaternion_tolerance=quaternion_tolerance,
                    max_linear_m_s=max_linear_m_s,
                    max_angular_rad_s=max_angular_rad_s,
                ),
                ConfidenceCheck(min_confidence),
                StampCheck(max_future_s),
                MonotonicCheck(),
                GapCheck(
                    max_gap_factor,
                    min_gap_s=min_gap_s,
                    expected_period_s=expected_period_s,
                    on_change=on_change_streams,
                ),
                JumpCheck(max_speed_m_s, tolerance_m=jump_tolerance_m),
            ]
        )

    @classmethod
    def from_config(
        cls, config: ValidationConfig, *, on_change_streams: Collection[str] = ()
    ) -> SampleValidator:
        """The default checks with the thresholds of ``config`` (``on_change_streams``: :meth:`default`)."""
        return cls.default(**config.model_dump(), on_change_streams=on_change_streams)

    @property
    def dropped(self) -> Mapping[str, int]:
        """Dropped samples per reason (live, read-only view)."""
        return MappingProxyType(self._dropped)

    def validate(self, sample: Sample) -> DropReason | None:
        """Check ``sample``: ``None`` if it is valid (and now the stream's last valid), else why not."""
        self.received += 1
        key = (sample.stamp.source_id, stream_of(sample))
        track = self._tracks.get(key)
        if track is None:
            track = self._tracks[key] = Track(key)
        reason: DropReason | None = None
        for c in self.checks:
            reason = c.check(sample, track)
            if reason is not None:
                break
        ns = sample.stamp.capture_ns
        if reason is None:
            track.last_valid = sample
            track.last_ns = ns
            track.prev_ns = ns
            track.rejected = None
            self.accepted += 1
            return None
        self._dropped[reason] = self._dropped.get(reason, 0) + 1
        # A sample older than the last valid one says nothing about the current gap, nor does one
        # with an implausible stamp (it must not become any reference).
        if ns > track.last_ns and reason != "future_stamp":
            track.prev_ns = ns
            if reason == "jump":
                track.rejected = sample
        return reason

    def reset(self) -> None:
        """Forget every stream's state (last valid samples, timing); keep the counters.

        Call when a device (re)starts, so the pause before it is not taken for an abnormal gap.
        """
        self._tracks.clear()

    def last_valid(self, source_id: str, stream: str) -> Sample | None:
        """The last accepted sample of ``(source_id, stream)``, for a consumer to hold; ``None`` if none."""
        track = self._tracks.get((source_id, stream))
        return None if track is None else track.last_valid

    def streams(self) -> list[tuple[str, str]]:
        """The ``(source_id, stream)`` pairs seen so far."""
        return list(self._tracks)

    def stats(self) -> ValidationStats:
        """A snapshot of the counters."""
        return ValidationStats(self.received, self.accepted, dict(self._dropped))


# ---------------------------------------------------------------------------------------------
# Where samples are consumed

#: Why a consumer (a control node) rejected a decoded sample (see :class:`SampleGate`).
RejectReason = Literal[
    "non_finite", "out_of_range", "bad_quaternion", "future_stamp", "stale_stamp", "non_monotonic"
]

#: Every :data:`RejectReason`, in the order :class:`SampleGate` checks them.
REJECT_REASONS: tuple[RejectReason, ...] = (
    "non_finite",
    "out_of_range",
    "bad_quaternion",
    "future_stamp",
    "stale_stamp",
    "non_monotonic",
)

#: ``| |q|^2 - 1 |`` below which a quaternion is used as it is (IK normalizes anyway).
_UNIT_EPS = 1e-9

_Admitted = Sample | RejectReason


class SampleGate:
    """Validates decoded samples where they are consumed, before anything computes with them.

    A device node validates what its device delivers, but anything on the bus may reach a
    consumer (another client, a bridge in another language, a replay), so a control node puts
    every decoded sample through a gate before retargeting, grippers, bases, aids and the deadman
    see it. Checks, in order (the first failure is the sample's reason):

    * ``non_finite``: NaN or inf in any float (or a value so large its square overflows).
    * ``out_of_range``: a position, keypoint or joint coordinate beyond ``max_position_m``, a speed
      beyond ``max_speed``, trigger/grip outside [0, 1], a joystick axis or a confidence outside
      its range. The bounds are loose on purpose: the device's own validator applies the rig's
      policy; the gate keeps numbers the retargeting can compute with.
    * ``bad_quaternion``: an orientation whose norm is outside ``quaternion_norm`` (zero, huge).
      Admitted orientations whose norm is off 1 come back normalized.
    * ``future_stamp`` / ``stale_stamp``: capture time more than ``max_future_s`` ahead of or more
      than ``max_age_s`` behind the consumer's clock.
    * ``non_monotonic``: captured not after the last admitted sample of the same key (topic).

    A rejected sample never becomes the reference of the monotonic check, so a sample stamped an
    hour ahead costs one sample, not the episode. Each rejection is counted per reason and logged as
    a warning naming the key and the sample's source, at most once per ``warn_interval_s`` per
    (key, reason) with the number suppressed since. Not thread-safe: call from the consuming thread.
    """

    def __init__(
        self,
        name: str = "consumer",
        *,
        max_position_m: float = 1000.0,
        max_speed: float = 1000.0,
        quaternion_norm: tuple[float, float] = (0.5, 2.0),
        max_future_s: float = 0.5,
        max_age_s: float = 2.0,
        warn_interval_s: float = 5.0,
    ) -> None:
        """Args:
        name: Who consumes (named in warnings), e.g. ``"control arm0"``.
        max_position_m: Largest coordinate of a position or keypoint [m] (> 0).
        max_speed: Largest linear [m/s] and angular [rad/s] speed of a twist or base velocity (> 0).
        quaternion_norm: ``(lowest, highest)`` norm of an orientation that is normalized and used,
            with ``0 < lowest <= 1 <= highest``.
        max_future_s: How far a capture time may be ahead of ``clock`` [s] (> 0).
        max_age_s: How far a capture time may be behind ``clock`` [s] (> 0).
        warn_interval_s: Shortest time between two warnings of one (key, reason) [s] (>= 0).
        """
        _positive("max_position_m", max_position_m)
        _positive("max_speed", max_speed)
        _positive("max_future_s", max_future_s)
        _positive("max_age_s", max_age_s)
        lo, hi = quaternion_norm
        if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 < lo <= 1.0 <= hi):
            raise ConfigError(f"quaternion_norm must be (lowest, highest) around 1, got {quaternion_norm}")
        if not (math.isfinite(warn_interval_s) and warn_interval_s >= 0.0):
            raise ConfigError(f"warn_interval_s must be >= 0 s, got {warn_interval_s}")
        self.name = name
        self._p = float(max_position_m)
        self._p2 = self._p * self._p
        self._v2 = float(max_speed) ** 2
        self._q_lo2, self._q_hi2 = lo * lo, hi * hi
        self._future_ns = int(max_future_s * 1e9)
        self._age_ns = int(max_age_s * 1e9)
        self._warn_ns = int(warn_interval_s * 1e9)
        self._last_ns: dict[str, int] = {}
        self._rejected: dict[str, int] = dict.fromkeys(REJECT_REASONS, 0)
        self._warned: dict[tuple[str, str], tuple[int, int]] = {}
        self.received = 0
        self.admitted = 0
        self._values: dict[type, Callable[[object], _Admitted]] = {
            Pose: self._pose,  # type: ignore[dict-item]
            ControllerState: self._controller,  # type: ignore[dict-item]
            HandPose: self._hand,  # type: ignore[dict-item]
            BodySkeleton: self._body,  # type: ignore[dict-item]
            Twist: self._twist,  # type: ignore[dict-item]
            BaseVelocity: self._base,  # type: ignore[dict-item]
        }

    @property
    def rejected(self) -> Mapping[str, int]:
        """Rejected samples per :data:`RejectReason` (every reason present; live, read-only view)."""
        return MappingProxyType(self._rejected)

    def admit(self, key: str, sample: Sample, now_ns: int) -> Sample | RejectReason:
        """The sample to consume (normalized if needed), or why it is rejected (counted); test the
        result with ``isinstance(result, str)``.

        Args:
            key: What the monotonic check is kept per, e.g. the topic the sample came on.
            sample: A decoded sample.
            now_ns: The consumer's time in the rig's common clock [ns].
        """
        self.received += 1
        stamp = sample.stamp
        result: _Admitted
        confidence = stamp.confidence
        if not math.isfinite(confidence):
            result = "non_finite"
        elif not 0.0 <= confidence <= 1.0:
            result = "out_of_range"
        else:
            result = self._values.get(type(sample), _finite_or_not)(sample)
        if not isinstance(result, str):
            ns = stamp.capture_ns
            if ns - now_ns > self._future_ns:
                result = "future_stamp"
            elif now_ns - ns > self._age_ns:
                result = "stale_stamp"
            elif ns <= self._last_ns.get(key, -(2**63)):
                result = "non_monotonic"
            else:
                self._last_ns[key] = ns
                self.admitted += 1
                return result
        self._rejected[result] += 1
        self._warn(key, sample, result, now_ns)
        return result

    def reset(self) -> None:
        """Forget the monotonic references (e.g. when the producers restart); keep the counters."""
        self._last_ns.clear()

    # -- values ------------------------------------------------------------------------------

    def _unit(self, q: FloatArray) -> FloatArray | None:
        """``q`` if unit, ``q`` normalized if its norm is plausible, else ``None``."""
        n2 = _sq(q.tolist())
        if abs(n2 - 1.0) <= _UNIT_EPS:
            return q
        if self._q_lo2 <= n2 <= self._q_hi2:
            return q / math.sqrt(n2)
        return None

    def _orientation(self, n2: float) -> float | None:
        """The factor that normalizes a quaternion of squared norm ``n2``: 1.0 when it is unit
        already, ``None`` when it cannot be used."""
        if abs(n2 - 1.0) <= _UNIT_EPS:
            return 1.0
        if self._q_lo2 <= n2 <= self._q_hi2:
            return 1.0 / math.sqrt(n2)
        return None

    # Controllers and poses are the hot path (one per control tick): one pass over plain floats.

    def _pose(self, s: Pose) -> _Admitted:
        px, py, pz = s.position.tolist()
        w, x, y, z = s.orientation.tolist()
        if not math.isfinite(px + py + pz + w + x + y + z):
            return "non_finite"
        if px * px + py * py + pz * pz > self._p2:
            return "out_of_range"
        k = self._orientation(w * w + x * x + y * y + z * z)
        if k is None:
            return "bad_quaternion"
        return s if k == 1.0 else dataclasses.replace(s, orientation=s.orientation * k)

    def _controller(self, s: ControllerState) -> _Admitted:
        px, py, pz = s.position.tolist()
        w, x, y, z = s.orientation.tolist()
        jx, jy = s.joystick.tolist()
        trigger, grip = s.trigger, s.grip
        if not math.isfinite(px + py + pz + w + x + y + z + jx + jy + trigger + grip):
            return "non_finite"
        if not (
            px * px + py * py + pz * pz <= self._p2
            and 0.0 <= trigger <= 1.0
            and 0.0 <= grip <= 1.0
            and -1.0 <= jx <= 1.0
            and -1.0 <= jy <= 1.0
        ):
            return "out_of_range"
        k = self._orientation(w * w + x * x + y * y + z * z)
        if k is None:
            return "bad_quaternion"
        return s if k == 1.0 else dataclasses.replace(s, orientation=s.orientation * k)

    def _hand(self, s: HandPose) -> _Admitted:
        if not _finite_hand(s):
            return "non_finite"
        c = s.keypoint_confidence
        if not (
            _sq(s.wrist_position.tolist()) <= self._p2
            and float(np.abs(s.keypoints).max()) <= self._p
            and float(c.min()) >= 0.0
            and float(c.max()) <= 1.0
        ):
            return "out_of_range"
        q = self._unit(s.wrist_orientation)
        if q is None:
            return "bad_quaternion"
        return s if q is s.wrist_orientation else dataclasses.replace(s, wrist_orientation=q)

    def _body(self, s: BodySkeleton) -> _Admitted:
        if not _finite_body(s):
            return "non_finite"
        if not s.joint_names:
            return s
        if float(np.abs(s.positions).max()) > self._p:
            return "out_of_range"
        n2 = np.square(s.orientations) @ _ONES4
        if float(np.abs(n2 - 1.0).max()) <= _UNIT_EPS:
            return s
        if float(n2.min()) < self._q_lo2 or float(n2.max()) > self._q_hi2:
            return "bad_quaternion"
        return dataclasses.replace(s, orientations=s.orientations / np.sqrt(n2)[:, None])

    def _twist(self, s: Twist) -> _Admitted:
        if not _finite_twist(s):
            return "non_finite"
        ok = _sq(s.linear.tolist()) <= self._v2 and _sq(s.angular.tolist()) <= self._v2
        return s if ok else "out_of_range"

    def _base(self, s: BaseVelocity) -> _Admitted:
        if not _finite_base(s):
            return "non_finite"
        ok = s.vx * s.vx + s.vy * s.vy <= self._v2 and s.wz * s.wz <= self._v2
        return s if ok else "out_of_range"

    # -- warnings ----------------------------------------------------------------------------

    def _warn(self, key: str, sample: Sample, reason: RejectReason, now_ns: int) -> None:
        t = time.monotonic_ns()
        last, suppressed = self._warned.get((key, reason), (None, 0))
        if last is not None and t - last < self._warn_ns:
            self._warned[(key, reason)] = (last, suppressed + 1)
            return
        self._warned[(key, reason)] = (t, 0)
        more = f" ({suppressed} more since the last warning)" if suppressed else ""
        log.warning(
            "%s: rejected a %s from source %r on %s: %s%s",
            self.name,
            type(sample).__name__,
            sample.stamp.source_id,
            key,
            _describe(reason, sample, now_ns),
            more,
        )


def _finite_or_not(sample: object) -> _Admitted:
    return sample if _finite_any(sample) else "non_finite"  # type: ignore[return-value]


def _describe(reason: RejectReason, sample: Sample, now_ns: int) -> str:
    dt_s = (sample.stamp.capture_ns - now_ns) / 1e9
    match reason:
        case "future_stamp":
            return f"captured {dt_s:.3g} s ahead of this clock (future_stamp); check the sender's clock"
        case "stale_stamp":
            return f"captured {-dt_s:.3g} s ago (stale_stamp); check the sender's clock"
        case "non_monotonic":
            return "captured before the last sample admitted there (non_monotonic)"
        case "non_finite":
            return "NaN or inf in its values (non_finite)"
        case "bad_quaternion":
            return "orientation is not a normalizable quaternion (bad_quaternion)"
        case _:
            return "a value is out of range (out_of_range)"
