"""An episode as the gates read it: manifest, the robots' streams as arrays, residuals and status words."""

from __future__ import annotations

import dataclasses
import json
import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pydantic import JsonValue

from telerig.bus.catalogue import (
    BASE_POSE,
    BASE_SENT,
    GRIPPER_SENT,
    GRIPPER_STATE,
    JOINT_SENT,
    JOINT_STATE,
    RESIDUAL,
    STATUS,
    WRENCH,
)
from telerig.bus.topics import Topic
from telerig.errors import RecordingError, WireError
from telerig.ir import wire
from telerig.ir.mcap_log import decode_residual, iter_tagged, residual_source
from telerig.ir.types import FloatArray, JointCommand, JointState, Sample
from telerig.qa.robots import RobotInfo, robot_info
from telerig.record.align import StreamData
from telerig.store.episodes import EpisodeManifest
from telerig.store.manifest_extra import EpisodeExtra

__all__ = [
    "EpisodeData",
    "RobotData",
    "load_episode",
]

_ROBOT_IR_STREAMS = (JOINT_STATE, JOINT_SENT, GRIPPER_SENT, BASE_SENT, BASE_POSE, GRIPPER_STATE, WRENCH)
_log = logging.getLogger("telerig.qa")
_MANIFEST = "manifest.json"
_MCAP = "episode.mcap"


@dataclass(frozen=True, slots=True)
class RobotData:
    """One robot's recorded streams.

    Attributes:
        info: Its model and limits.
        streams: IR streams by stream name (``joint_state``, ``joint_command_sent``, ``wrench``...).
        names: Joint names of ``joint_state`` and ``joint_command_sent`` samples, by stream name.
        residual: Per control tick ``(capture time [ns], flagged)`` of the IK residual, by time.
        status: ``(receive time [ns], status word)`` of each safety status change, by time.
    """

    info: RobotInfo
    streams: Mapping[str, StreamData]
    names: Mapping[str, tuple[str, ...]]
    residual: tuple[tuple[int, bool], ...] = ()
    status: tuple[tuple[int, str], ...] = ()

    @property
    def robot(self) -> str:
        """Robot id."""
        return self.info.robot


@dataclass(frozen=True, slots=True)
class EpisodeData:
    """What the gates read of one committed episode.

    Attributes:
        path: The episode directory.
        manifest: Its manifest.
        extra: The manifest's typed ``extra``.
        robots: Every robot that recorded a stream, by id.
        capture_times: Capture times [ns] of every IR topic of the log, sorted (sync reads them).
        start_ns: Episode start, common clock [ns] (times in verdicts count from here).
        end_ns: Episode end [ns].
        residual_errors: The worst ``*_error_m`` metric of each residual message that has one, of
            every robot, in log order [m] (:meth:`~telerig.ir.types.RetargetResidual.worst_error_m`;
            the score's tracking).
    """

    path: Path
    manifest: EpisodeManifest
    extra: EpisodeExtra
    robots: Mapping[str, RobotData] = field(default_factory=dict)
    capture_times: Mapping[str, np.ndarray] = field(default_factory=dict)
    start_ns: int = 0
    end_ns: int = 0
    residual_errors: tuple[float, ...] = ()

    @property
    def streams(self) -> dict[str, StreamData]:
        """Every robot's streams, by topic."""
        return {data.topic: data for robot in self.robots.values() for data in robot.streams.values()}

    @property
    def duration_s(self) -> float:
        """Episode length [s]."""
        return (self.end_ns - self.start_ns) / 1e9

    def seconds(self, time_ns: np.ndarray | int) -> FloatArray:
        """Times [ns] as seconds from the episode start."""
        out: FloatArray = (np.asarray(time_ns, dtype=np.int64) - self.start_ns) / 1e9
        return out

    def at(self, time_ns: int) -> float:
        """One time [ns] as seconds from the episode start."""
        return (time_ns - self.start_ns) / 1e9

    @property
    def mcap_path(self) -> Path:
        """The episode's MCAP log."""
        return self.path / _MCAP


def load_episode(episode_dir: Path) -> EpisodeData:
    """Read an episode's manifest and its robots' streams (not device samples nor camera frames).

    Raises:
        RecordingError: the manifest or the log is missing or unreadable (one line, with the path).
        DependencyError: a robot model's package or MuJoCo is missing.
    """
    path = Path(episode_dir)
    try:
        manifest = EpisodeManifest.model_validate_json((path / _MANIFEST).read_bytes())
    except OSError as exc:
        raise RecordingError(
            f"cannot read {path / _MANIFEST}: {exc.strerror}; is it an episode directory?"
        ) from None
    except ValueError as exc:
        raise RecordingError(
            f"{path / _MANIFEST} is not a valid manifest: {str(exc).splitlines()[0]}"
        ) from None
    extra = EpisodeExtra.of(manifest)
    mcap = path / _MCAP
    if not mcap.is_file():
        raise RecordingError(f"{mcap} is missing; the episode has no log to check")
    log = _read_log(mcap)
    capture_times, streams, names = log.capture_times, log.streams, log.names
    json_streams, residuals = log.status, log.residuals
    by_robot: dict[str, dict[str, StreamData]] = {}
    for topic, data in streams.items():
        node, stream = _split(topic)
        if stream in _ROBOT_IR_STREAMS:
            by_robot.setdefault(node, {})[stream] = data
    ids = sorted({*by_robot, *(node for node, _ in json_streams), *residuals, *extra.robot_joints})
    robots: dict[str, RobotData] = {}
    for robot in ids:
        own = by_robot.get(robot, {})
        if not own and robot not in extra.robot_joints:
            continue  # a node that published only a status word, not a robot we know of
        joint_names = {s: names[own[s].topic] for s in (JOINT_STATE, JOINT_SENT) if s in own}
        residual = residuals.get(robot, [])
        status = tuple((t, v) for t, v in json_streams.get((robot, STATUS), []) if isinstance(v, str))
        robots[robot] = RobotData(robot_info(robot, extra), own, joint_names, tuple(sorted(residual)), status)
    end_ns = manifest.end_ns if manifest.end_ns is not None else _last_time(streams, manifest.start_ns)
    return EpisodeData(
        path, manifest, extra, robots, capture_times, manifest.start_ns, end_ns, tuple(log.residual_errors)
    )


def _split(topic: str) -> tuple[str, str]:
    try:
        parsed = Topic.parse(topic)
    except ValueError:
        return "", ""
    return parsed.node, parsed.stream


@dataclass
class _Log:
    """What :func:`load_episode` reads from an episode's log."""

    capture_times: dict[str, np.ndarray]  # every IR topic's capture times [ns], sorted
    streams: dict[str, StreamData]  # the robots' IR streams as arrays
    names: dict[str, tuple[str, ...]]  # joint names of their joint streams
    status: dict[tuple[str, str], list[tuple[int, JsonValue]]]  # (robot, "status") -> (log ns, value)
    residuals: dict[str, list[tuple[int, bool]]]  # robot -> (capture ns, flagged) of each residual
    residual_errors: list[float]  # the worst *_error_m of each residual with one, in log order


def _read_log(mcap: Path) -> _Log:
    """One pass over the log: every IR topic's capture times, the robots' streams as arrays and the
    joint names of their joint streams, their status words and their residuals (typed, or the JSON
    of earlier episodes: :func:`~telerig.ir.mcap_log.decode_residual`). The file is parsed once: it
    was read three times (IR, status, residuals), and parsing its chunks is most of the gates'
    time (a fleet episode's gates: 0.97-1.02 s of CPU, against 1.34-1.42 s in three passes); the
    score reads what it needs from the same pass (:func:`telerig.qa.checker.check_episode`).
    """
    times: dict[str, list[int]] = {}
    samples: dict[str, list[Sample]] = {}
    status: dict[tuple[str, str], list[tuple[int, JsonValue]]] = {}
    residuals: dict[str, list[tuple[int, bool]]] = {}
    residual_errors: list[float] = []
    residual_seqs: dict[str, int] = {}
    malformed = not_residuals = 0
    parts: dict[str, tuple[str, str]] = {}  # topic -> (node, stream)
    for topic, data, log_ns, publish_ns, is_json in iter_tagged(mcap):
        node_stream = parts.get(topic)
        if node_stream is None:
            node_stream = parts[topic] = _split(topic)
        node, stream = node_stream
        if stream == RESIDUAL:
            # As read_residuals numbers them: the stamp's source is the topic's node, seq from 1.
            seq = residual_seqs[topic] = residual_seqs.get(topic, 0) + 1
            source = residual_source(topic)
            try:
                residual = decode_residual(
                    data, json_form=is_json, source_id=source, seq=seq, log_time_ns=log_ns
                )
            except WireError:
                not_residuals += 1
            else:
                if node:
                    residuals.setdefault(node, []).append((residual.stamp.capture_ns, residual.flagged))
                if (worst := residual.worst_error_m()) is not None:
                    residual_errors.append(worst)
        if is_json:
            if stream == STATUS:
                try:
                    value = json.loads(data)
                except (ValueError, RecursionError):  # a bare word, or absurd nesting: as read_json
                    continue
                status.setdefault((node, stream), []).append((log_ns, value))
            continue
        bucket = times.get(topic)
        if bucket is None:
            bucket = times[topic] = []
        bucket.append(publish_ns)
        if stream in _ROBOT_IR_STREAMS:
            try:
                samples.setdefault(topic, []).append(wire.decode(data))
            except WireError:
                malformed += 1  # the recorder checked every sample; a damaged file is the cause
    if malformed:
        _log.warning("%s: %d robot samples do not decode; left out", mcap, malformed)
    if not_residuals:
        _log.warning("%s: %d residual messages are not residuals; left out", mcap, not_residuals)
    streams = {t: _stream(t, s) for t, s in sorted(samples.items())}
    names = {t: s[0].names if isinstance(s[0], JointState | JointCommand) else () for t, s in samples.items()}
    capture_times = {t: np.sort(np.asarray(v, dtype=np.int64)) for t, v in times.items()}
    return _Log(capture_times, streams, names, status, residuals, residual_errors)


def _stream(topic: str, samples: list[Sample]) -> StreamData:
    """Numeric fields of one topic's samples as arrays sorted by capture time (see
    :class:`telerig.record.align.StreamData`); samples of another type than the first are left out."""
    kind = type(samples[0])
    same = [s for s in samples if type(s) is kind]
    order = np.argsort([s.stamp.capture_ns for s in same], kind="stable")
    ordered = [same[i] for i in order]
    fields: dict[str, FloatArray] = {}
    discrete: set[str] = set()
    for f in dataclasses.fields(samples[0]):
        value = getattr(samples[0], f.name)
        if isinstance(value, bool) or not isinstance(value, np.ndarray | int | float):
            continue
        try:
            fields[f.name] = np.asarray([getattr(s, f.name) for s in ordered], dtype=np.float64)
        except ValueError:  # ragged: e.g. velocities () in some samples, (n,) in others
            continue
        if isinstance(value, int):
            discrete.add(f.name)
    time_ns = np.asarray([s.stamp.capture_ns for s in ordered], dtype=np.int64)
    return StreamData(topic, kind.__name__, time_ns, fields, frozenset(discrete))


def _last_time(streams: Mapping[str, StreamData], default: int) -> int:
    ends = [int(s.time_ns[-1]) for s in streams.values() if s.time_ns.size]
    return max(ends, default=default)
