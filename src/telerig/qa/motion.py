"""Gates on the robots' measured motion: joint limits, calibration drift, idle time, falls, F/T spikes."""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np
import numpy.typing as npt

from telerig.bus.catalogue import (
    BASE_POSE,
    BASE_SENT,
    GRIPPER_SENT,
    GRIPPER_STATE,
    JOINT_SENT,
    JOINT_STATE,
    WRENCH,
)
from telerig.config.qa import QaThresholds
from telerig.ir.types import FloatArray
from telerig.qa.episode import EpisodeData, RobotData
from telerig.qa.report import GateVerdict
from telerig.record.align import StreamData

__all__ = [
    "MAX_EVENTS",
    "IdleTime",
    "calibration_drift",
    "fall",
    "force_spike",
    "idle_gate",
    "idle_time",
    "joint_limits",
    "joint_speeds",
    "rising_edges",
]

BoolArray = npt.NDArray[np.bool_]

#: At most this many event times per verdict (the first ones): a plot needs where trouble starts.
MAX_EVENTS = 50
#: Calibration drift needs each joint still for at least this long [s] (25 samples at 50 Hz, 50 at
#: 100 Hz) for its median offset to stand for the episode rather than one pause.
_MIN_STILL_S = 0.5
#: Idle is judged on a grid at this rate [Hz]: 20 ms, finer than any pause worth trimming.
_IDLE_GRID_HZ = 50.0


def rising_edges(mask: BoolArray, times_s: FloatArray) -> tuple[float, ...]:
    """Times where ``mask`` turns True (its first sample counts when True), at most :data:`MAX_EVENTS`."""
    if mask.size == 0:
        return ()
    starts = np.flatnonzero(mask & ~np.concatenate(([False], mask[:-1])))
    return tuple(round(float(times_s[i]), 4) for i in starts[:MAX_EVENTS])


def joint_speeds(state: StreamData) -> FloatArray:
    """Measured joint speeds [rad/s] of a ``joint_state`` stream: its recorded velocities, or the
    time derivative of its positions where it has none. Shape (S, n)."""
    q = state.fields["positions"]
    v = state.fields.get("velocities")
    if v is not None and v.shape == q.shape and np.all(np.isfinite(v)):
        return v
    if q.shape[0] < 2:
        return np.zeros_like(q)
    t = state.time_ns / 1e9
    out: FloatArray = np.gradient(q, t, axis=0) if np.all(np.diff(t) > 0) else np.zeros_like(q)
    return out


# --- joint limits --------------------------------------------------------------------------------


def joint_limits(episode: EpisodeData, thresholds: QaThresholds) -> GateVerdict:
    """Fail when a measured joint position is beyond its limit by more than ``joint_limit_margin``
    of its range, or its speed above ``(1 + joint_limit_margin)`` times its velocity limit.

    ``value`` is the worst excess as a fraction (position: of the joint's range; speed: of its limit).
    """
    margin = thresholds.joint_limit_margin
    worst = -math.inf
    worst_text = ""
    events: list[float] = []
    unknown: list[str] = []
    checked = 0
    for robot in episode.robots.values():
        state = robot.streams.get(JOINT_STATE)
        if state is None or state.time_ns.size == 0:
            continue
        names = robot.names.get(JOINT_STATE, ())
        lower, upper, vmax = robot.info.limits_for(names)
        if np.all(np.isnan(lower) & np.isnan(upper) & np.isnan(vmax)):
            unknown.append(robot.robot)
            continue
        checked += 1
        times = episode.seconds(state.time_ns)
        q = state.fields["positions"]
        with np.errstate(invalid="ignore", divide="ignore"):
            span = upper - lower
            pos_excess = np.fmax(q - upper, lower - q) / np.where(span > 0, span, np.nan)
            vel_excess = np.abs(joint_speeds(state)) / vmax - 1.0
        for kind, raw in (("position", pos_excess), ("velocity", vel_excess)):
            excess = np.where(np.isfinite(raw), raw, -np.inf)
            if excess.size == 0:
                continue
            i, j = np.unravel_index(int(np.argmax(excess)), excess.shape)
            for k in range(excess.shape[1]):
                events.extend(rising_edges(excess[:, k] > margin, times))
            if excess[i, j] > worst:
                worst = float(excess[i, j])
                worst_text = _limit_text(robot, names[j], kind, q[i, j], lower[j], upper[j], worst, times[i])
    if checked == 0:
        why = f"no joint limits known for {', '.join(unknown)}" if unknown else "no joint state recorded"
        return GateVerdict("joint_limits", None, None, margin, "fraction", f"{why}; nothing to check")
    passed = worst <= margin
    detail = worst_text if not passed else f"within limits; closest: {worst_text}"
    if unknown:
        detail += f" (no limits known for {', '.join(unknown)})"
    return GateVerdict(
        "joint_limits",
        passed,
        max(worst, 0.0),
        margin,
        "fraction",
        detail,
        tuple(sorted(events)[:MAX_EVENTS]),
    )


def _limit_text(
    robot: RobotData, joint: str, kind: str, q: float, lower: float, upper: float, excess: float, t: float
) -> str:
    where = f"{robot.robot} joint {joint}"
    if kind == "velocity":
        return f"{where} at {1.0 + excess:.2f}x its velocity limit at t={t:.2f} s"
    side, limit = ("upper", upper) if q > upper or (q - upper) > (lower - q) else ("lower", lower)
    if excess <= 0:
        return f"{where} {abs(q - limit):.3f} inside its {side} limit {limit:.3f} at t={t:.2f} s"
    return (
        f"{where} at {q:.3f}, {abs(q - limit):.3f} beyond its {side} limit {limit:.3f} "
        f"({excess * 100:.1f} % of its range) at t={t:.2f} s"
    )


# --- calibration drift ---------------------------------------------------------------------------


def calibration_drift(episode: EpisodeData, thresholds: QaThresholds) -> GateVerdict:
    """Fail when a joint's measured position sits persistently off what was sent to it.

    Per joint, the offset is the median of (sent - measured) over the measured samples where both
    the joint and its command are still (speed below ``idle_velocity_rad_s``), with the sent
    command held from its last sample: tracking lag while moving does not count, a calibration
    offset shows in every pause. A joint still for less than 0.5 s in the episode is not judged.
    """
    limit = thresholds.drift_rad
    still_speed = thresholds.idle_velocity_rad_s
    worst = -1.0
    worst_text = ""
    events: list[float] = []
    too_busy: list[str] = []
    judged = 0
    for robot in episode.robots.values():
        state, sent = robot.streams.get(JOINT_STATE), robot.streams.get(JOINT_SENT)
        if state is None or sent is None or state.time_ns.size < 2 or sent.time_ns.size < 2:
            continue
        names = robot.names.get(JOINT_STATE, ())
        sent_names = robot.names.get(JOINT_SENT, ())
        index = {n: k for k, n in enumerate(sent_names)}
        held = np.searchsorted(sent.time_ns, state.time_ns, side="right") - 1
        valid = held >= 0
        if not np.any(valid):
            continue
        times = episode.seconds(state.time_ns[valid])
        q = state.fields["positions"][valid]
        v = np.abs(joint_speeds(state)[valid])
        q_sent_all = sent.fields["positions"]
        v_sent_all = np.abs(_derivative(q_sent_all, sent.time_ns))
        dt = float(np.median(np.diff(state.time_ns))) / 1e9
        for j, name in enumerate(names):
            k = index.get(name)
            if k is None:
                continue
            q_sent = q_sent_all[held[valid], k]
            still = (v[:, j] < still_speed) & (v_sent_all[held[valid], k] < still_speed)
            if still.sum() * dt < _MIN_STILL_S:
                too_busy.append(f"{robot.robot}/{name}")
                continue
            judged += 1
            offset = float(np.median(q_sent[still] - q[still, j]))
            if abs(offset) > limit:
                events.extend(rising_edges(still & (np.abs(q_sent - q[:, j]) > limit), times))
            if abs(offset) > worst:
                worst = abs(offset)
                worst_text = (
                    f"{robot.robot} joint {name} measured {offset:+.3f} rad "
                    f"({math.degrees(offset):+.1f} deg) "
                    f"off what was sent, median over {still.sum() * dt:.1f} s still"
                )
    if judged == 0:
        why = (
            f"no joint was still for {_MIN_STILL_S} s ({', '.join(too_busy[:4])}): an offset cannot be told "
            "from tracking lag"
            if too_busy
            else "no measured and sent joint positions recorded for one robot"
        )
        return GateVerdict("calibration_drift", None, None, limit, "rad", why)
    passed = worst <= limit
    detail = worst_text if not passed else f"largest offset: {worst_text}"
    return GateVerdict(
        "calibration_drift", passed, worst, limit, "rad", detail, tuple(sorted(events)[:MAX_EVENTS])
    )


def _derivative(values: FloatArray, time_ns: np.ndarray) -> FloatArray:
    t = time_ns / 1e9
    if values.shape[0] < 2 or not np.all(np.diff(t) > 0):
        return np.zeros_like(values)
    out: FloatArray = np.gradient(values, t, axis=0)
    return out


# --- idle ----------------------------------------------------------------------------------------


class IdleTime:
    """Where an episode has no meaningful motion (see :func:`idle_time`).

    Attributes:
        fraction: Idle share of the episode, in [0, 1].
        segments: Trimmable idle stretches ``(start, end)`` [s from the episode start].
        judged: Whether any motion stream was recorded (otherwise nothing is known).
    """

    __slots__ = ("fraction", "judged", "segments")

    def __init__(self, fraction: float, segments: tuple[tuple[float, float], ...], judged: bool) -> None:
        self.fraction = fraction
        self.segments = segments
        self.judged = judged


def idle_time(episode: EpisodeData, thresholds: QaThresholds) -> IdleTime:
    """The idle share and trimmable idle stretches of an episode.

    On a 50 Hz grid over the episode, a frame moves when any robot joint moves at least
    ``idle_velocity_rad_s`` (measured), a gripper's command or measured opening changes at least
    ``idle_gripper_per_s``, or a base is sent a velocity of at least ``idle_velocity_rad_s`` (m/s
    or rad/s); every other frame is idle. Segments: the idle head and tail, and idle stretches
    inside of at least ``idle_min_pause_s``.
    """
    duration = episode.duration_s
    n = max(math.floor(duration * _IDLE_GRID_HZ) + 1, 1)
    grid_s = np.arange(n) / _IDLE_GRID_HZ
    grid_ns = episode.start_ns + np.round(grid_s * 1e9).astype(np.int64)
    moving = np.zeros(n, dtype=np.bool_)
    judged = False
    for robot in episode.robots.values():
        for speed_time, speed, limit in _motion_signals(robot, thresholds):
            judged = True
            moving |= _held(speed_time, speed, grid_ns) >= limit
    if not judged:
        return IdleTime(0.0, (), False)
    idle = ~moving
    fraction = float(idle.mean())
    return IdleTime(fraction, _idle_segments(idle, grid_s, duration, thresholds.idle_min_pause_s), True)


def _motion_signals(
    robot: RobotData, thresholds: QaThresholds
) -> Iterable[tuple[np.ndarray, FloatArray, float]]:
    """(times [ns], speed per sample, threshold) of each motion signal of a robot."""
    state = robot.streams.get(JOINT_STATE)
    if state is not None and state.time_ns.size:
        speed = np.abs(joint_speeds(state))
        yield (
            state.time_ns,
            speed.max(axis=1) if speed.shape[1] else np.zeros(len(speed)),
            thresholds.idle_velocity_rad_s,
        )
    for name in (GRIPPER_SENT, GRIPPER_STATE):
        grip = robot.streams.get(name)
        if grip is not None and grip.time_ns.size > 1 and "opening" in grip.fields:
            rate = np.abs(_derivative(grip.fields["opening"][:, None], grip.time_ns))[:, 0]
            yield grip.time_ns, rate, thresholds.idle_gripper_per_s
    base = robot.streams.get(BASE_SENT)
    if base is not None and base.time_ns.size:
        f = base.fields
        speed = np.maximum(np.hypot(f["vx"], f["vy"]), np.abs(f["wz"]))
        yield base.time_ns, speed, thresholds.idle_velocity_rad_s


def _held(time_ns: np.ndarray, values: FloatArray, grid_ns: np.ndarray) -> FloatArray:
    """``values`` held from their last sample at each grid time (0 before the first sample)."""
    i = np.searchsorted(time_ns, grid_ns, side="right") - 1
    out: FloatArray = np.where(i >= 0, values[np.clip(i, 0, None)], 0.0)
    return out


def _idle_segments(
    idle: BoolArray, grid_s: FloatArray, duration: float, min_pause_s: float
) -> tuple[tuple[float, float], ...]:
    if not idle.any():
        return ()
    padded = np.concatenate(([False], idle, [False]))
    edges = np.flatnonzero(np.diff(padded.astype(np.int8)))
    step = 1.0 / _IDLE_GRID_HZ
    out: list[tuple[float, float]] = []
    for a, b in zip(edges[::2], edges[1::2], strict=True):
        start = float(grid_s[a])
        end = min(float(grid_s[b - 1]) + step, duration) if b < idle.size else duration
        head_or_tail = a == 0 or b == idle.size
        if head_or_tail or end - start >= min_pause_s:
            out.append((round(start, 4), round(end, 4)))
    return tuple(out)


def idle_gate(idle: IdleTime, thresholds: QaThresholds) -> GateVerdict:
    """Fail when the idle share exceeds ``idle_max_fraction``."""
    limit = thresholds.idle_max_fraction
    if not idle.judged:
        return GateVerdict("idle", None, None, limit, "fraction", "no joint, gripper or base motion recorded")
    trimmable = sum(b - a for a, b in idle.segments)
    detail = (
        f"{idle.fraction * 100:.0f} % of the episode without motion (joints under "
        f"{thresholds.idle_velocity_rad_s:g} rad/s); {trimmable:.1f} s in {len(idle.segments)} "
        "trimmable stretch(es)"
    )
    events = tuple(a for a, _ in idle.segments[:MAX_EVENTS])
    return GateVerdict("idle", idle.fraction <= limit, idle.fraction, limit, "fraction", detail, events)


# --- fall ----------------------------------------------------------------------------------------


def fall(episode: EpisodeData, thresholds: QaThresholds) -> GateVerdict:
    """Fail when a humanoid's pelvis or a mobile base is lower than ``fall_height_fraction`` of its
    standing height (its recorded ``base_pose`` stream, world z)."""
    fraction = thresholds.fall_height_fraction
    standing = [r for r in episode.robots.values() if r.info.standing]
    if not standing:
        fixed = ", ".join(episode.robots) or "none"
        return GateVerdict(
            "fall",
            None,
            None,
            fraction,
            "fraction",
            f"no humanoid or mobile base (robots: {fixed}): nothing can fall",
        )
    worst = math.inf
    worst_text = ""
    events: list[float] = []
    missing: list[str] = []
    for robot in standing:
        pose = robot.streams.get(BASE_POSE)
        height = robot.info.standing_height_m
        if pose is None or pose.time_ns.size == 0 or height is None or "position" not in pose.fields:
            what = "no base_pose stream" if pose is None or pose.time_ns.size == 0 else "no standing height"
            missing.append(f"{robot.robot} ({what})")
            continue
        z = pose.fields["position"][:, 2]
        ratio = z / height
        times = episode.seconds(pose.time_ns)
        i = int(np.argmin(ratio))
        events.extend(rising_edges(ratio < fraction, times))
        if ratio[i] < worst:
            worst = float(ratio[i])
            worst_text = (
                f"{robot.robot} pelvis/base at {z[i]:.3f} m, {ratio[i]:.2f} of its {height:.3f} m standing "
                f"height, at t={times[i]:.2f} s"
            )
    if not math.isfinite(worst):
        return GateVerdict(
            "fall",
            None,
            None,
            fraction,
            "fraction",
            f"height not recorded for {', '.join(missing)}: its pelvis or base is fixed, or the episode "
            "predates base poses",
        )
    passed = worst >= fraction
    detail = worst_text if not passed else f"lowest: {worst_text}"
    if missing:
        detail += f"; not recorded for {', '.join(missing)}"
    return GateVerdict(
        "fall", passed, worst, fraction, "fraction", detail, tuple(sorted(events)[:MAX_EVENTS])
    )


# --- force / torque ------------------------------------------------------------------------------


def force_spike(episode: EpisodeData, thresholds: QaThresholds) -> GateVerdict:
    """Fail when a recorded wrist force or torque magnitude exceeds ``force_spike_n`` / ``torque_spike_nm``.

    ``value`` is the largest force [N]; the torque is in the detail.
    """
    f_max, t_max = thresholds.force_spike_n, thresholds.torque_spike_nm
    peak_f, peak_t = -1.0, -1.0
    text_f = text_t = ""
    events: list[float] = []
    measured: list[str] = []
    for robot in episode.robots.values():
        wrench = robot.streams.get(WRENCH)
        if wrench is None or wrench.time_ns.size == 0 or "force" not in wrench.fields:
            continue
        measured.append(robot.robot)
        times = episode.seconds(wrench.time_ns)
        force = np.linalg.norm(wrench.fields["force"], axis=1)
        torque = np.linalg.norm(wrench.fields.get("torque", np.zeros((force.size, 3))), axis=1)
        events.extend(rising_edges((force > f_max) | (torque > t_max), times))
        i, k = int(np.argmax(force)), int(np.argmax(torque))
        if force[i] > peak_f:
            peak_f, text_f = float(force[i]), f"{robot.robot} force {force[i]:.1f} N at t={times[i]:.2f} s"
        if torque[k] > peak_t:
            peak_t, text_t = (
                float(torque[k]),
                f"{robot.robot} torque {torque[k]:.2f} N m at t={times[k]:.2f} s",
            )
    if not measured:
        return GateVerdict(
            "force_spike", None, None, f_max, "N", "no force/torque recorded (no robot has a wrench stream)"
        )
    passed = peak_f <= f_max and peak_t <= t_max
    detail = f"peak {text_f} (limit {f_max:g} N), {text_t} (limit {t_max:g} N m)"
    return GateVerdict("force_spike", passed, peak_f, f_max, "N", detail, tuple(sorted(events)[:MAX_EVENTS]))
