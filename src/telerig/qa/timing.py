"""Gates on the recording itself and the operator's session: stream sync, teleoperation faults."""

from __future__ import annotations

import math

import numpy as np
from pydantic import JsonValue

from telerig.bus.catalogue import BASE_REQUESTED, CAMERA_FRAMES, GRIPPER_REQUESTED, JOINT_REQUESTED, RESIDUAL
from telerig.config.qa import QaThresholds
from telerig.qa.episode import EpisodeData
from telerig.qa.motion import MAX_EVENTS
from telerig.qa.report import GateVerdict
from telerig.record.align import DEFAULT_TOLERANCE_MS, StreamData, align

__all__ = ["END_SLACK_S", "FAULT_CODES", "sync", "teleop_faults"]

#: Safety codes that stop a robot mid-demonstration: e-stops (the safety chain's, an operator's),
#: a driver fault, a measured joint beyond its limits, the input watchdog stopping the robot.
FAULT_CODES = frozenset({"estop", "operator_estop", "driver_fault", "joint_limit_fault", "watchdog_stop"})
_STOPPED_WORDS = frozenset({"estopped", "stopped"})


#: How long before the episode's end a stream may stop [s]. The end is the recording window's (the
#: operator's stop, the duration run out); the stop sequence after it (devices stop, the robots
#: hold, the recorder takes the streams' tails and closes) is not part of the episode, however long
#: a full host makes it. A stream whose last sample was captured earlier than this stopped
#: mid-episode, or the recorder had not caught up with it when the episode closed (a station short
#: of CPU receives its streams seconds late, and what it had not received by then is not in it).
END_SLACK_S = 1.0

#: Streams whose samples carry the stamp of the input they were made from (one per control tick
#: with fresh input): their sequence gaps are inputs the control node skipped, not lost data, and
#: their times repeat the input stream's, which the gate judges itself. The residual (typed since
#: issue 18, so now among the recorded IR streams) is one per solved input sample, the same way.
_DERIVED = frozenset({JOINT_REQUESTED, GRIPPER_REQUESTED, BASE_REQUESTED, RESIDUAL})


def sync(episode: EpisodeData, thresholds: QaThresholds) -> GateVerdict:
    """Fail when a recorded stream lost more than ``max_missing_fraction`` of its samples, paused
    longer than ``max_gap_ms``, or left more than ``max_missing_fraction`` of the camera frames
    without a sample near them; or a bound stream delivered nothing.

    A stream also fails when its last sample was captured more than :data:`END_SLACK_S` before the
    episode's end: the rate and gaps between its samples say nothing about the time after them.

    Losses come from the recorder's per-stream statistics: sequence-number drops, and a rate below
    the expected one (a camera delivering 13 of 30 frames a second loses 57 %). Gaps are measured on
    the logged capture times, so their places are events. A camera frame misses a stream when the
    stream's nearest sample is farther than the alignment tolerance (``alignment_tolerance_ms``,
    else the recorder's) and farther than the stream's own median sample interval: a 100 Hz
    stream's nearest sample is up to 5 ms away by its rate alone, and more with jitter, which is
    not a fault; a frame falling into a hole of the stream is. ``value`` is the worst missing
    fraction of any stream (samples lost, or frames missed).
    """
    limit = thresholds.max_missing_fraction
    times = episode.capture_times
    # (rank, line): a loss ranks by its fraction, a gap after a loss of half the samples.
    problems: list[tuple[float, str]] = []
    events: list[float] = []
    worst = 0.0
    worst_text = ""
    stats = [
        s
        for s in episode.extra.streams
        if _num(s.get("expected_hz")) > 0 and _stream(str(s.get("name", ""))) not in _DERIVED
    ]
    for s in stats:
        name = str(s.get("name", ""))
        messages, drops = _num(s.get("messages")), _num(s.get("drops"))
        expected, measured = _num(s.get("expected_hz")), _num(s.get("measured_hz"))
        lost = max(drops / (messages + drops) if messages + drops > 0 else 1.0, 1.0 - measured / expected)
        if lost > worst:
            worst, worst_text = lost, f"{_short(name)} lost {lost * 100:.1f} %"
        if lost > limit:
            line = (
                f"{_short(name)} lost {lost * 100:.1f} % of its samples "
                f"({measured:.1f} of {expected:g} Hz, {drops:.0f} drops){_camera_counts(episode, name)}"
            )
            problems.append((lost, line))
        stream_times = times.get(name)
        gap_text, gap_events = _gaps(
            episode, stream_times, _num(s.get("max_gap_ms")), gap_limit_ms(thresholds.max_gap_ms, expected)
        )
        if gap_text:
            problems.append((0.5, f"{_short(name)} {gap_text}{_camera_counts(episode, name)}"))
            events.extend(gap_events)
        early = _stopped_early(episode, name, stream_times)
        if early is not None:
            share, line, at = early
            if share > worst:
                worst, worst_text = share, f"{_short(name)} stopped {share * 100:.1f} % early"
            problems.append((max(share, 0.75), line))
            events.append(at)
    for topic, where in episode.extra.missing_streams.items():
        worst, worst_text = 1.0, f"{_short(topic)} delivered nothing"
        problems.append((1.0, f"{_short(topic)} delivered nothing{f' (waited on {where})' if where else ''}"))
    missed = _missed_frames(episode, thresholds.alignment_tolerance_ms)
    for topic, (share, tolerance_ms) in missed.items():
        if share > worst:
            worst, worst_text = share, f"{_short(topic)} missed {share * 100:.1f} % of the camera frames"
        if share > limit:
            line = (
                f"{_short(topic)} has no sample within {tolerance_ms:.3g} ms "
                f"of {share * 100:.1f} % of the camera frames"
            )
            problems.append((share, line))
    if not stats and not missed and not episode.extra.missing_streams:
        return GateVerdict("sync", None, None, limit, "fraction", "no stream statistics in the manifest")
    if problems:
        ranked = [text for _, text in sorted(problems, key=lambda p: -p[0])]
        more = f" (+{len(ranked) - 3} more)" if len(ranked) > 3 else ""
        detail = "; ".join(ranked[:3]) + more
    else:
        detail = f"every stream within {limit * 100:g} % loss and {thresholds.max_gap_ms:g} ms gaps"
        detail += f"; worst: {worst_text}" if worst_text else ""
    return GateVerdict(
        "sync", not problems, worst, limit, "fraction", detail, tuple(sorted(events)[:MAX_EVENTS])
    )


def _stream(topic: str) -> str:
    return topic.rsplit("/", 1)[-1]


def _short(topic: str) -> str:
    """``node/stream`` of a topic."""
    return "/".join(topic.split("/")[-2:])


def _stopped_early(
    episode: EpisodeData, topic: str, times: np.ndarray | None
) -> tuple[float, str, float] | None:
    """For a stream whose last sample was captured more than :data:`END_SLACK_S` before the
    episode's end: (the share of the episode after it, one line, the time of that sample [s]);
    ``None`` otherwise, and for an episode without an end."""
    if times is None or times.size == 0 or episode.end_ns <= episode.start_ns:
        return None
    last_ns = int(times.max())
    early_s = (episode.end_ns - last_ns) / 1e9
    if early_s <= END_SLACK_S:
        return None
    at = episode.at(last_ns)
    line = (
        f"{_short(topic)} stopped {early_s:.2f} s before the episode's end (last sample at t={at:.2f} "
        f"of {episode.duration_s:.2f} s): its source stopped, or the recorder fell behind it"
    )
    return early_s / episode.duration_s, line, round(at, 4)


def _camera_counts(episode: EpisodeData, topic: str) -> str:
    """What the camera itself counted in the episode, for a line about its ``frames`` stream:
    ``" (the camera skipped 2 frames, 1 late)"``; ``""`` for other streams and for episodes recorded
    before cameras counted them. Skipped frames point at the camera (a simulated camera's host
    descheduled it, a device dropped frames), none at what came after it."""
    node, _, stream = topic.rpartition("/")
    camera = episode.extra.cameras.get(node.rpartition("/")[2])
    if stream != CAMERA_FRAMES or camera is None or camera.skipped is None:
        return ""
    return f" (the camera skipped {camera.skipped} frames, {camera.late} late)"


def _num(value: JsonValue) -> float:
    return float(value) if isinstance(value, int | float) and not isinstance(value, bool) else 0.0


def sample_interval_ms(times_ns: np.ndarray) -> float:
    """A stream's median interval between samples [ms]; messages within 0.1 ms of each other are one
    sample (a task robot publishes each object's pose in the same tick: 2 objects at 100 Hz are 200
    messages a second, 10 ms apart as samples, not 5)."""
    steps = np.diff(np.sort(times_ns))
    steps = steps[steps > 100_000]
    return float(np.median(steps)) / 1e6 if steps.size else 0.0


def gap_limit_ms(max_gap_ms: float, expected_hz: float) -> float:
    """The longest interval between two samples of a stream at ``expected_hz`` that is not a gap
    [ms]: ``max_gap_ms``, or one and a half sample periods for a stream slower than that allows
    (a 15 Hz camera's frames are 67 ms apart; one frame missing makes 133 ms)."""
    return max(max_gap_ms, 1500.0 / expected_hz) if expected_hz > 0 else max_gap_ms


def _gaps(
    episode: EpisodeData, times: np.ndarray | None, recorded_ms: float, limit_ms: float
) -> tuple[str, list[float]]:
    """One line and the start times [s] of the gaps longer than ``limit_ms``, or ``("", [])``."""
    if times is None or times.size < 2:
        if recorded_ms > limit_ms:
            return f"paused {recorded_ms:.0f} ms (limit {limit_ms:g} ms)", []
        return "", []
    gaps_ms = np.diff(times) / 1e6
    long = np.flatnonzero(gaps_ms > limit_ms)
    if long.size == 0:
        return "", []
    i = int(long[np.argmax(gaps_ms[long])])
    at = episode.at(int(times[i]))
    text = f"paused {gaps_ms[i]:.0f} ms at t={at:.2f} s (limit {limit_ms:g} ms; {long.size} gap(s))"
    return text, [round(episode.at(int(times[k])), 4) for k in long[:MAX_EVENTS]]


def _missed_frames(episode: EpisodeData, tolerance_ms: float | None) -> dict[str, tuple[float, float]]:
    """Topic -> (share of the anchor camera's frames the stream has no sample near, the distance
    used [ms]) for every stream of the recorder's alignment report."""
    report = episode.extra.alignment
    recorded = _streams_of(report)
    anchor = report.get("anchor") if isinstance(report, dict) else None
    anchor_topic = anchor.get("topic") if isinstance(anchor, dict) else None
    frames = episode.capture_times.get(anchor_topic) if isinstance(anchor_topic, str) else None
    if frames is None or frames.size == 0:
        return {}
    out: dict[str, tuple[float, float]] = {}
    for topic, s in recorded.items():
        times = episode.capture_times.get(topic)
        if _stream(topic) in _DERIVED or times is None or times.size == 0:
            continue
        rig_ms = (
            tolerance_ms if tolerance_ms is not None else _num(s.get("tolerance_ms")) or DEFAULT_TOLERANCE_MS
        )
        allowed_ms = max(rig_ms, sample_interval_ms(times))
        data = {topic: StreamData(topic, "", times, {})}
        aligned = align(data, frames, policy="nearest", tolerance_ms=allowed_ms)[topic]
        out[topic] = (1.0 - aligned.stats.valid / frames.size, allowed_ms)
    return out


def _streams_of(report: JsonValue) -> dict[str, dict[str, JsonValue]]:
    """The ``streams`` part of an alignment report (see :func:`telerig.record.align.alignment_report`)."""
    streams = report.get("streams") if isinstance(report, dict) else None
    if not isinstance(streams, dict):
        return {}
    return {t: s for t, s in streams.items() if isinstance(s, dict)}


def teleop_faults(episode: EpisodeData, thresholds: QaThresholds) -> GateVerdict:
    """Fail on an IK residual flagged without a break for longer than ``residual_flag_s``, a safety
    stop or e-stop in the episode's safety log or status words, or a control tick that raised.

    ``value`` is the longest flagged stretch of any robot [s].
    """
    limit = thresholds.residual_flag_s
    problems: list[str] = []
    events: list[float] = []
    longest = 0.0
    longest_text = ""
    any_residual = False
    for robot in episode.robots.values():
        if not robot.residual:
            continue
        any_residual = True
        for start_ns, length_s in _flagged_runs(robot.residual):
            if length_s > longest:
                longest = length_s
                longest_text = (
                    f"{robot.robot} IK residual flagged for {length_s:.2f} s "
                    f"from t={episode.at(start_ns):.2f} s"
                )
            if length_s > limit:
                events.append(round(episode.at(start_ns), 4))
        if longest > limit and longest_text.startswith(robot.robot):
            problems.append(longest_text)
        for t_ns, word in robot.status:
            if word in _STOPPED_WORDS:
                problems.append(f"{robot.robot} {word} at t={episode.at(t_ns):.2f} s")
                events.append(round(episode.at(t_ns), 4))
                break
    for entry in episode.extra.safety_log:
        if entry.code in FAULT_CODES:
            who = entry.robot or "rig"
            problems.append(f"{who} {entry.code} at t={episode.at(entry.t_ns):.2f} s: {entry.reason}")
            events.append(round(episode.at(entry.t_ns), 4))
    logged = {(e.robot, e.code) for e in episode.extra.safety_log}
    for robot_id, counts in episode.extra.safety_events.items():
        for code in sorted(FAULT_CODES & set(counts)):
            if counts[code] > 0 and (robot_id, code) not in logged:
                problems.append(f"{robot_id} {code} x{counts[code]}")
    for robot_id, n in episode.extra.tick_faults.items():
        if n > 0:
            problems.append(f"{robot_id} {n} control tick(s) raised")
    detail = "; ".join(dict.fromkeys(problems))  # each line once
    if not problems:
        detail = "no safety stop, e-stop or tick fault"
        detail += (
            f"; longest flagged IK residual {longest:.2f} s" if any_residual else "; no IK residual recorded"
        )
    value = longest if any_residual else None
    if not math.isfinite(longest):
        value = None
    return GateVerdict(
        "teleop_faults", not problems, value, limit, "s", detail, tuple(sorted(set(events))[:MAX_EVENTS])
    )


def _flagged_runs(residual: tuple[tuple[int, bool], ...]) -> list[tuple[int, float]]:
    """``(start [ns], length [s])`` of each stretch of flagged ticks: from the first flagged tick to
    the next unflagged one (or the last flagged tick at the end of the log)."""
    runs: list[tuple[int, float]] = []
    start: int | None = None
    last = 0
    for t_ns, flagged in residual:
        if flagged and start is None:
            start = t_ns
        elif not flagged and start is not None:
            runs.append((start, (t_ns - start) / 1e9))
            start = None
        last = t_ns
    if start is not None:
        runs.append((start, (last - start) / 1e9))
    return runs
