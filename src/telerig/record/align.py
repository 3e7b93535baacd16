"""Frame-centric alignment: every recorded stream matched to camera frame times, with its error measured."""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, get_args

import numpy as np
import numpy.typing as npt
from pydantic import JsonValue

from telerig.bus.catalogue import CAMERA_FRAMES
from telerig.bus.topics import node_of, stream_of
from telerig.errors import RecordingError
from telerig.ir.mcap_log import iter_raw, read_log
from telerig.ir.types import CameraFrame, FloatArray, Sample

__all__ = [
    "DEFAULT_TOLERANCE_MS",
    "AlignedEpisode",
    "AlignedStream",
    "AlignmentStats",
    "CaptureTimes",
    "Policy",
    "StreamData",
    "StreamPolicy",
    "align",
    "align_episode",
    "alignment_report",
    "load_streams",
    "slerp",
]

_log = logging.getLogger("telerig.record.align")

Int64Array = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]

#: How a stream's value at a frame time is chosen: the nearest sample; linear interpolation between
#: the samples either side (slerp for quaternions); zero-order hold (the last sample at or before).
Policy = Literal["nearest", "linear", "zoh"]
_POLICIES: tuple[str, ...] = get_args(Policy)

#: Default tolerance [ms]: a frame whose matched sample is farther than this is missing for that
#: stream (seed 004: streams in sync to 5 ms).
DEFAULT_TOLERANCE_MS = 5.0

#: Fields holding (w, x, y, z) unit quaternions in the last axis; linear policy slerps them.
_QUATERNION_FIELDS = frozenset({"orientation", "wrist_orientation", "orientations"})
_NO_SAMPLE = np.iinfo(np.int64).max


@dataclass(frozen=True, slots=True)
class StreamPolicy:
    """Alignment policy of one stream.

    Attributes:
        policy: ``nearest``, ``linear`` or ``zoh`` (see :data:`Policy`).
        tolerance_ms: Largest allowed |sample time - frame time| [ms] (> 0); ``None`` uses the
            default of the call.
    """

    policy: Policy = "nearest"
    tolerance_ms: float | None = None

    def __post_init__(self) -> None:
        if self.policy not in _POLICIES:
            raise ValueError(
                f"alignment policy {self.policy!r} does not exist. Available: {', '.join(_POLICIES)}"
            )
        if self.tolerance_ms is not None and not self.tolerance_ms > 0:
            raise ValueError(f"tolerance_ms must be > 0 ms, got {self.tolerance_ms}")


@dataclass(frozen=True, slots=True)
class StreamData:
    """One recorded stream as arrays, sorted by capture time.

    Attributes:
        topic: Bus topic, e.g. ``telerig/v1/demo/ur5e/joint_state``.
        sample_type: IR type name, e.g. ``JointState``.
        time_ns: Capture times, common clock [ns], non-decreasing. Shape (S,).
        fields: Numeric sample fields by name, float64. Shape (S, *field shape), e.g.
            ``positions`` (S, n) of a JointState, ``orientation`` (S, 4) of a Pose, ``opening`` (S,).
        discrete: Names of integer fields (``frame_index``...): never interpolated.
        names: Entry names of the vector fields, from the first sample's ``names`` (the joint
            names of a ``JointState`` / ``JointCommand``); empty for other types.
    """

    topic: str
    sample_type: str
    time_ns: Int64Array
    fields: Mapping[str, FloatArray]
    discrete: frozenset[str] = frozenset()
    names: tuple[str, ...] = ()


@dataclass(frozen=True, slots=True)
class AlignmentStats:
    """Distribution of |sample time - frame time| of one stream over the anchor frames.

    The error of a frame is the distance to the sample its value comes from: the nearest sample
    (``nearest``), the held sample (``zoh``), the nearer of the two bracketing samples
    (``linear``). Frames with no candidate sample (a ``zoh`` frame before the first sample, an
    empty stream) have no error and count in ``no_sample``; every other frame, within tolerance
    or not, is in the percentiles.

    Attributes:
        frames: Anchor frames. ``valid + beyond_tolerance + no_sample == frames``.
        valid: Frames whose sample is within tolerance.
        beyond_tolerance: Frames whose sample is farther than the tolerance.
        no_sample: Frames with no candidate sample.
        p50_ms: Median error [ms]; NaN when no frame has an error.
        p99_ms: 99th percentile error [ms]; NaN when no frame has an error.
        max_ms: Largest error [ms]; NaN when no frame has an error.
    """

    frames: int
    valid: int
    beyond_tolerance: int
    no_sample: int
    p50_ms: float
    p99_ms: float
    max_ms: float


@dataclass(frozen=True, slots=True)
class AlignedStream:
    """One stream resampled at the anchor frame times.

    Attributes:
        topic: Bus topic of the stream.
        sample_type: IR type name.
        policy: Policy used.
        tolerance_ms: Tolerance used [ms].
        samples: Samples the stream has (S).
        fields: Field values at each frame, float64, NaN where ``valid`` is False. Shape
            (F, *field shape), F = number of anchor frames.
        valid: Whether the stream has a value within tolerance at each frame. Shape (F,).
        source_index: Index into the stream's samples of the value used (the lower bracketing
            sample for ``linear``); -1 where there is no candidate sample. Shape (F,).
        error_ns: |sample time - frame time| [ns] as defined in :class:`AlignmentStats`; -1 where
            there is no candidate sample. Shape (F,).
        stats: The error distribution.
    """

    topic: str
    sample_type: str
    policy: Policy
    tolerance_ms: float
    samples: int
    fields: Mapping[str, FloatArray]
    valid: BoolArray
    source_index: Int64Array
    error_ns: Int64Array
    stats: AlignmentStats


@dataclass(frozen=True, slots=True)
class AlignedEpisode:
    """Every stream of an episode aligned to one camera's frames.

    Attributes:
        anchor: Topic of the anchor camera's frames.
        frame_ns: Anchor frame capture times, common clock [ns], non-decreasing. Shape (F,).
        frame_index: Index of each anchor frame in the camera's video file. Shape (F,).
        streams: Aligned streams by topic (the anchor itself excluded).
    """

    anchor: str
    frame_ns: Int64Array
    frame_index: Int64Array
    streams: Mapping[str, AlignedStream]

    @property
    def valid(self) -> BoolArray:
        """Frames where every stream has a value within tolerance. Shape (F,)."""
        mask = np.ones(self.frame_ns.shape, dtype=np.bool_)
        for stream in self.streams.values():
            mask &= stream.valid
        return mask

    def report(self) -> dict[str, JsonValue]:
        """The alignment-error report (see :func:`alignment_report`)."""
        return _report(
            self.anchor,
            self.frame_ns,
            {t: (s.policy, s.tolerance_ms, s.stats, s.samples) for t, s in self.streams.items()},
            self.valid,
        )


# --- quaternions ---------------------------------------------------------------------------------


def slerp(q0: FloatArray, q1: FloatArray, u: FloatArray | float) -> FloatArray:
    """Spherical linear interpolation of (w, x, y, z) unit quaternions along the shorter arc.

    Args:
        q0: Start quaternions. Shape (..., 4).
        q1: End quaternions. Shape (..., 4), same as ``q0``.
        u: Interpolation parameter in [0, 1] (0 gives ``q0``). Shape broadcastable to ``q0[..., 0]``.

    Returns:
        Unit quaternions, sign chosen to lie on the arc starting at ``q0``. Shape (..., 4).
    """
    a = np.asarray(q0, dtype=np.float64)
    b = np.asarray(q1, dtype=np.float64)
    t = np.broadcast_to(np.asarray(u, dtype=np.float64), a.shape[:-1])
    dot = np.einsum("...i,...i->...", a, b)
    b = np.where((dot < 0)[..., None], -b, b)
    dot = np.clip(np.abs(dot), 0.0, 1.0)
    theta = np.arccos(dot)
    sin_theta = np.sin(theta)
    # Nearly equal quaternions: sin(theta) -> 0; the normalized lerp is exact to first order there.
    near = sin_theta < 1e-9
    safe = np.where(near, 1.0, sin_theta)
    w0 = np.where(near, 1.0 - t, np.sin((1.0 - t) * theta) / safe)
    w1 = np.where(near, t, np.sin(t * theta) / safe)
    out = w0[..., None] * a + w1[..., None] * b
    norm = np.linalg.norm(out, axis=-1, keepdims=True)
    result: FloatArray = out / np.where(norm > 0, norm, 1.0)
    return result


# --- matching ------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class _Match:
    lo: Int64Array  # sample index used (lower bracket for linear), clipped into range
    hi: Int64Array  # upper bracket for linear, == lo otherwise
    weight: FloatArray  # linear weight of hi in [0, 1]
    nearest: Int64Array  # nearest sample index (for discrete fields under linear)
    error_ns: Int64Array  # _NO_SAMPLE where no candidate
    valid: BoolArray


def _match(time_ns: Int64Array, frame_ns: Int64Array, policy: str, tolerance_ns: int) -> _Match:
    """Vectorized matching of F frame times against S sorted sample times (O((S + F) log S))."""
    n_frames = frame_ns.size
    n = time_ns.size
    if n == 0:
        zeros = np.zeros(n_frames, dtype=np.int64)
        none = np.full(n_frames, _NO_SAMPLE, dtype=np.int64)
        return _Match(zeros, zeros, np.zeros(n_frames), zeros, none, np.zeros(n_frames, dtype=np.bool_))
    after = np.searchsorted(time_ns, frame_ns, side="right")  # first sample strictly after the frame
    before = after - 1  # last sample at or before the frame; -1 if none
    lo = np.clip(before, 0, n - 1)
    hi = np.clip(after, 0, n - 1)
    d_lo = np.where(before >= 0, frame_ns - time_ns[lo], _NO_SAMPLE)
    d_hi = np.where(after < n, time_ns[hi] - frame_ns, _NO_SAMPLE)
    nearest = np.where(d_hi < d_lo, hi, lo)
    if policy == "zoh":
        error, used_lo, used_hi = d_lo, lo, lo
        weight = np.zeros(n_frames)
    elif policy == "nearest":
        error, used_lo, used_hi = np.minimum(d_lo, d_hi), nearest, nearest
        weight = np.zeros(n_frames)
    else:  # linear; outside the recorded span it holds the end sample
        error = np.minimum(d_lo, d_hi)
        both = (before >= 0) & (after < n)
        used_lo = np.where(before >= 0, lo, hi)
        used_hi = np.where(after < n, hi, lo)
        span = (time_ns[used_hi] - time_ns[used_lo]).astype(np.float64)
        weight = np.where(both, (frame_ns - time_ns[used_lo]) / np.where(span > 0, span, 1.0), 0.0)
    valid = error <= tolerance_ns
    return _Match(used_lo, used_hi, weight, nearest, error, valid)


def _resample(data: StreamData, m: _Match, policy: str) -> dict[str, FloatArray]:
    out: dict[str, FloatArray] = {}
    invalid = ~m.valid
    for name, values in data.fields.items():
        if values.shape[0] == 0:
            out[name] = np.full((m.valid.size, *values.shape[1:]), np.nan)
            continue
        if policy != "linear" or name in data.discrete:
            resampled = values[m.nearest if policy == "linear" else m.lo].copy()
        elif name in _QUATERNION_FIELDS and values.shape[-1] == 4:
            u = m.weight.reshape((-1,) + (1,) * (values.ndim - 2))
            resampled = slerp(values[m.lo], values[m.hi], u)
        else:
            u = m.weight.reshape((-1,) + (1,) * (values.ndim - 1))
            a = values[m.lo]
            resampled = a + u * (values[m.hi] - a)
        resampled[invalid] = np.nan
        out[name] = resampled
    return out


def _stats(m: _Match) -> AlignmentStats:
    has = m.error_ns != _NO_SAMPLE
    errors_ms = m.error_ns[has] / 1e6
    valid = int(m.valid.sum())
    if errors_ms.size:
        p50, p99 = np.percentile(errors_ms, [50, 99])
        dist = (float(p50), float(p99), float(errors_ms.max()))
    else:
        dist = (math.nan, math.nan, math.nan)
    return AlignmentStats(int(m.valid.size), valid, int(has.sum()) - valid, int((~has).sum()), *dist)


def _resolve(
    topic: str, policy: Policy, tolerance_ms: float, policies: Mapping[str, Policy | StreamPolicy]
) -> tuple[Policy, float]:
    chosen = policies.get(topic)
    if chosen is None:
        chosen = policies.get(topic.rsplit("/", 1)[-1])
    if chosen is None:
        return policy, tolerance_ms
    sp = chosen if isinstance(chosen, StreamPolicy) else StreamPolicy(chosen)
    return sp.policy, sp.tolerance_ms if sp.tolerance_ms is not None else tolerance_ms


def _check(policy: Policy, tolerance_ms: float) -> None:
    StreamPolicy(policy, tolerance_ms)  # raises ValueError naming what is wrong


def align(
    streams: Mapping[str, StreamData],
    frame_ns: Int64Array,
    *,
    policy: Policy = "nearest",
    tolerance_ms: float = DEFAULT_TOLERANCE_MS,
    policies: Mapping[str, Policy | StreamPolicy] | None = None,
) -> dict[str, AlignedStream]:
    """Resample streams at given frame times.

    Args:
        streams: Streams by topic (from :func:`load_streams`).
        frame_ns: Anchor times, common clock [ns], non-decreasing. Shape (F,).
        policy: Default policy.
        tolerance_ms: Default tolerance [ms] (> 0).
        policies: Per-stream overrides keyed by topic or by stream name (``joint_state``).

    Returns:
        Aligned streams by topic, in the order of ``streams``.
    """
    _check(policy, tolerance_ms)
    frames = np.asarray(frame_ns, dtype=np.int64)
    if frames.size > 1 and np.any(np.diff(frames) < 0):
        raise ValueError("frame_ns must be non-decreasing; sort the anchor frame times")
    out: dict[str, AlignedStream] = {}
    for topic, data in streams.items():
        pol, tol_ms = _resolve(topic, policy, tolerance_ms, policies or {})
        m = _match(data.time_ns, frames, pol, round(tol_ms * 1e6))
        has = m.error_ns != _NO_SAMPLE
        out[topic] = AlignedStream(
            topic,
            data.sample_type,
            pol,
            tol_ms,
            int(data.time_ns.size),
            _resample(data, m, pol),
            m.valid,
            np.where(has, m.lo, -1),
            np.where(has, m.error_ns, -1),
            _stats(m),
        )
    return out


# --- reading episodes ----------------------------------------------------------------------------


class _Collector:
    """Accumulates the numeric fields of one topic's samples."""

    def __init__(self, topic: str, first: Sample) -> None:
        self.topic = topic
        self.type = type(first)
        self.times: list[int] = []
        self.discrete: set[str] = set()
        self.names: list[str] = []
        labels = getattr(first, "names", ())
        self.labels: tuple[str, ...] = tuple(labels) if isinstance(labels, tuple) else ()
        for f in dataclasses.fields(first):
            value = getattr(first, f.name)
            if isinstance(value, np.ndarray):
                self.names.append(f.name)
            elif isinstance(value, bool):
                continue
            elif isinstance(value, int):
                self.names.append(f.name)
                self.discrete.add(f.name)
            elif isinstance(value, float):
                self.names.append(f.name)
        self.values: dict[str, list[object]] = {name: [] for name in self.names}

    def add(self, sample: Sample) -> None:
        if type(sample) is not self.type:
            raise RecordingError(
                f"topic {self.topic} mixes {self.type.__name__} and {type(sample).__name__} samples; "
                "each stream must carry one IR type"
            )
        self.times.append(sample.stamp.capture_ns)
        for name in self.names:
            self.values[name].append(getattr(sample, name))

    def finish(self) -> StreamData:
        times = np.asarray(self.times, dtype=np.int64)
        order = np.argsort(times, kind="stable")
        fields: dict[str, FloatArray] = {}
        for name, values in self.values.items():
            try:
                arr = np.asarray(values, dtype=np.float64)
            except ValueError:  # ragged: e.g. velocities () in some samples, (n,) in others
                shapes = sorted({np.asarray(v).shape for v in values})
                _log.warning("%s: field %s skipped, its shape varies (%s)", self.topic, name, shapes)
                continue
            fields[name] = arr[order]
        return StreamData(
            self.topic, self.type.__name__, times[order], fields, frozenset(self.discrete), self.labels
        )


def load_streams(path: Path | str, *, topics: Iterable[str] | None = None) -> dict[str, StreamData]:
    """Read every IR stream of an episode MCAP log into arrays (decodes every message).

    Non-numeric fields (names, frame ids, controller button sets) are left out; a field whose
    shape changes within a stream is skipped with a warning.

    Args:
        path: The episode's MCAP file (truncated files are recovered, see :func:`read_log`).
        topics: Only these topics; all when ``None``.

    Returns:
        Streams by topic, sorted by topic.
    """
    collectors: dict[str, _Collector] = {}
    for entry in read_log(path, topics=topics):
        c = collectors.get(entry.topic)
        if c is None:
            c = collectors[entry.topic] = _Collector(entry.topic, entry.sample)
        c.add(entry.sample)
    return {topic: collectors[topic].finish() for topic in sorted(collectors)}


def _pick_anchor(path: Path | str, topics: Iterable[str], anchor: str | None) -> str:
    frames = sorted(t for t in topics if stream_of(t) == CAMERA_FRAMES)
    if anchor is None:
        if not frames:
            raise RecordingError(
                f"{path} has no camera frames topic (.../<camera>/{CAMERA_FRAMES}) to anchor on; "
                "record a camera or align with align() on your own frame times"
            )
        if len(frames) > 1:
            _log.info(
                "%s: %d cameras, anchoring on %s (pass anchor= to choose)", path, len(frames), frames[0]
            )
        return frames[0]
    for topic in frames:
        if anchor in (topic, node_of(topic)):
            return topic
    available = ", ".join(node_of(t) for t in frames) or "none"
    raise RecordingError(f"anchor camera {anchor!r} is not in {path}. Available: {available}")


def align_episode(
    path: Path | str,
    *,
    anchor: str | None = None,
    policy: Policy = "nearest",
    tolerance_ms: float = DEFAULT_TOLERANCE_MS,
    policies: Mapping[str, Policy | StreamPolicy] | None = None,
    topics: Iterable[str] | None = None,
) -> AlignedEpisode:
    """Build the frame-centric aligned view of an episode (seed 000: camera frames are the anchor).

    Args:
        path: The episode's MCAP file.
        anchor: Camera id or frames topic to anchor on; the first camera (by topic) when ``None``.
        policy: Default policy for every stream.
        tolerance_ms: Default tolerance [ms] (> 0).
        policies: Per-stream overrides keyed by topic or stream name, e.g.
            ``{"joint_state": "linear", "gripper_command_sent": StreamPolicy("zoh", 50.0)}``.
        topics: Only these streams (the anchor is always read); all when ``None``.

    Raises:
        RecordingError: the file cannot be read, has no camera frames, or ``anchor`` does not exist.
    """
    _check(policy, tolerance_ms)
    data = load_streams(path)
    anchor_topic = _pick_anchor(path, data, anchor)
    frames = data.pop(anchor_topic)
    if frames.sample_type != CameraFrame.__name__:
        raise RecordingError(
            f"{anchor_topic} carries {frames.sample_type}, not CameraFrame; choose another anchor"
        )
    if topics is not None:
        wanted = set(topics)
        data = {t: s for t, s in data.items() if t in wanted}
    aligned = align(data, frames.time_ns, policy=policy, tolerance_ms=tolerance_ms, policies=policies)
    index = frames.fields["frame_index"].astype(np.int64)
    return AlignedEpisode(anchor_topic, frames.time_ns, index, aligned)


def alignment_report(
    path: Path | str,
    *,
    anchor: str | None = None,
    policy: Policy = "nearest",
    tolerance_ms: float = DEFAULT_TOLERANCE_MS,
    policies: Mapping[str, Policy | StreamPolicy] | None = None,
) -> dict[str, JsonValue]:
    """Alignment-error distribution of every stream of an episode, as JSON data for the manifest.

    Reads only the times (MCAP publish time, which the recorder sets to the capture time), so it
    is fast enough to run at commit. Same arguments as :func:`align_episode`.

    Returns:
        ``{"anchor": {"topic", "frames", "fps", "interval_ms": {"p50", "max"}, "start_ns",
        "end_ns"}, "frames_all_valid", "streams": {topic: {"policy", "tolerance_ms", "samples",
        "valid", "beyond_tolerance", "no_sample", "error_ms": {"p50", "p99", "max"}}}}``; NaN
        values are ``null``.

    Raises:
        RecordingError: the file cannot be read, has no camera frames, or ``anchor`` does not exist.
    """
    times = CaptureTimes()
    for topic, _, _, publish_ns in iter_raw(path):
        times.add(topic, publish_ns)
    return _times_report(
        times.times, str(path), anchor=anchor, policy=policy, tolerance_ms=tolerance_ms, policies=policies
    )


class CaptureTimes:
    """Capture times per topic gathered while recording, so the report needs no second read of the log.

    The recorder calls :meth:`add` for every IR message it writes (a list append); at the end of
    the episode :meth:`report` gives exactly what :func:`alignment_report` gives on the file.
    """

    def __init__(self) -> None:
        self.times: dict[str, list[int]] = {}

    def add(self, topic: str, capture_ns: int) -> None:
        """Record one message of ``topic`` captured at ``capture_ns`` (common clock [ns])."""
        bucket = self.times.get(topic)
        if bucket is None:
            bucket = self.times[topic] = []
        bucket.append(capture_ns)

    def report(
        self,
        *,
        anchor: str | None = None,
        policy: Policy = "nearest",
        tolerance_ms: float = DEFAULT_TOLERANCE_MS,
        policies: Mapping[str, Policy | StreamPolicy] | None = None,
    ) -> dict[str, JsonValue]:
        """The alignment report of the times so far (see :func:`alignment_report`).

        Raises:
            RecordingError: no camera frames were recorded, or ``anchor`` does not exist.
        """
        return _times_report(
            self.times,
            "this recording",
            anchor=anchor,
            policy=policy,
            tolerance_ms=tolerance_ms,
            policies=policies,
        )


def _times_report(
    times: Mapping[str, list[int]],
    where: str,
    *,
    anchor: str | None,
    policy: Policy,
    tolerance_ms: float,
    policies: Mapping[str, Policy | StreamPolicy] | None,
) -> dict[str, JsonValue]:
    _check(policy, tolerance_ms)
    anchor_topic = _pick_anchor(where, times, anchor)
    frame_ns = np.sort(np.asarray(times[anchor_topic], dtype=np.int64))
    streams = {
        t: StreamData(t, "", np.sort(np.asarray(v, dtype=np.int64)), {})
        for t, v in sorted(times.items())
        if t != anchor_topic
    }
    aligned = align(streams, frame_ns, policy=policy, tolerance_ms=tolerance_ms, policies=policies)
    valid = np.ones(frame_ns.shape, dtype=np.bool_)
    for s in aligned.values():
        valid &= s.valid
    return _report(
        anchor_topic,
        frame_ns,
        {t: (s.policy, s.tolerance_ms, s.stats, s.samples) for t, s in aligned.items()},
        valid,
    )


def _ms(value: float) -> float | None:
    return None if math.isnan(value) else round(value, 4)


def _report(
    anchor: str,
    frame_ns: Int64Array,
    streams: Mapping[str, tuple[str, float, AlignmentStats, int]],
    valid: BoolArray,
) -> dict[str, JsonValue]:
    intervals_ms = np.diff(frame_ns) / 1e6
    span_s = (frame_ns[-1] - frame_ns[0]) / 1e9 if frame_ns.size > 1 else 0.0
    anchor_json: dict[str, JsonValue] = {
        "topic": anchor,
        "frames": int(frame_ns.size),
        "fps": round((frame_ns.size - 1) / span_s, 3) if span_s > 0 else None,
        "interval_ms": {
            "p50": _ms(float(np.median(intervals_ms))) if intervals_ms.size else None,
            "max": _ms(float(intervals_ms.max())) if intervals_ms.size else None,
        },
        "start_ns": int(frame_ns[0]) if frame_ns.size else None,
        "end_ns": int(frame_ns[-1]) if frame_ns.size else None,
    }
    streams_json: dict[str, JsonValue] = {}
    for topic, (pol, tol_ms, st, samples) in streams.items():
        streams_json[topic] = {
            "policy": pol,
            "tolerance_ms": tol_ms,
            "samples": samples,
            "valid": st.valid,
            "beyond_tolerance": st.beyond_tolerance,
            "no_sample": st.no_sample,
            "error_ms": {"p50": _ms(st.p50_ms), "p99": _ms(st.p99_ms), "max": _ms(st.max_ms)},
        }
    return {"anchor": anchor_json, "frames_all_valid": int(valid.sum()), "streams": streams_json}
