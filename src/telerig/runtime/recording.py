"""Recording one episode on a station: the draft, the recorder, devices and cameras, the manifest."""

from __future__ import annotations

import contextlib
import logging
import math
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

from pydantic import JsonValue

from telerig import priority
from telerig.bus.metrics import LatencySummary, LatencyTracker, StreamSummary
from telerig.bus.topics import Topic
from telerig.config.schema import DeviceConfig, RigConfig, SessionCommand
from telerig.errors import RecordingError
from telerig.ir.types import now_ns
from telerig.record.recorder import Recorder
from telerig.runtime import streams
from telerig.runtime.broker_supervisor import BrokerSupervisor
from telerig.runtime.camera_node import CameraEpisode
from telerig.runtime.nodes import StationNodes, quietly
from telerig.runtime.process_settings import Terminated
from telerig.runtime.robot_host import LatencyNs, RobotHost, SafetyCounts, StartDevices, Stats, StopDevices
from telerig.runtime.robot_record import robot_joints_record
from telerig.runtime.rollout import policy_record
from telerig.runtime.safety_log import SafetyLog
from telerig.runtime.station_session import ProgressCallback, StationSession
from telerig.runtime.storage import StationStorage
from telerig.runtime.task import TaskEpisodes, TaskResult
from telerig.store.episodes import EpisodeDraft, EpisodeStore
from telerig.store.manifest_extra import (
    CameraRecord,
    EpisodeExtra,
    FingerprintRecord,
    OutageRecord,
    RobotJointsRecord,
)
from telerig.voice.instructions import InstructionsRecord, count_instructions, write_episode_instructions

__all__ = ["EpisodeRecording", "EpisodeResult", "expected_rates"]

log = logging.getLogger(__name__)


def _instructions(mcap: Path, episode_id: str) -> InstructionsRecord | None:
    """The episode's operator instructions counted from its finished MCAP (for the manifest); None
    (logged) when they cannot be counted, which never fails the episode."""
    try:
        return count_instructions(mcap, episode_id)
    except RecordingError as exc:
        log.warning("episode %s: operator instructions not counted: %s", episode_id, exc)
        return None


def _count_instructions(directory: Path, record: InstructionsRecord | None) -> None:
    """Write the episode's operator instructions beside it (``instructions.json``, seed 002's metric,
    :mod:`telerig.voice.instructions`); a failure is logged, never fatal to the episode."""
    try:
        write_episode_instructions(directory, record)
    except RecordingError as exc:
        log.warning("episode %s: operator instructions not counted: %s", directory.name, exc)


#: Session commands that throw the running episode away (to the incomplete partition).
_DISCARDING = frozenset(
    {SessionCommand.RESTART_EPISODE, SessionCommand.STOP_COLLECTION, SessionCommand.DISCARD_EPISODE}
)


@dataclass(frozen=True, slots=True)
class EpisodeResult:
    """What one recorded episode produced.

    Attributes:
        status: ``complete`` (committed) or ``incomplete`` (discarded by the operator).
        filed_path: Where the episode was filed when it ended; :attr:`path` is where it lies now.
        command: The operator's session command that ended the episode early, if any.
        store: The store it is in (for :attr:`path`).
    """

    episode_id: str
    status: str
    filed_path: Path
    duration_s: float
    streams: list[StreamSummary]
    latency: LatencySummary
    camera_frames: dict[str, int] = field(default_factory=dict)
    command: SessionCommand | None = None
    store: EpisodeStore | None = field(default=None, repr=False, compare=False)

    @property
    def path(self) -> Path:
        """The episode's directory now: the quality gates run after commit may have moved it to
        ``failures/`` (and a recheck back)."""
        if self.filed_path.is_dir() or self.store is None:
            return self.filed_path
        return self.store.locate(self.episode_id) or self.filed_path


class EpisodeRecording:
    """Records episodes of one station: everything its nodes (and robot hosts) publish, its cameras'
    videos, and a manifest with stream statistics, latency, safety events, clock and health.

    Args:
        config: The rig.
        station: This station's id.
        storage: Where episodes go.
        recorder: The station's recorder.
        session: The station's link to the session.
        nodes: The nodes this process runs.
        hosts: The robot host processes of this station.
        broker: The broker supervisor (its restarts are listed in the manifest).
        tasks: The station's randomized tasks, judged from the scene at each episode's end.
    """

    def __init__(
        self,
        config: RigConfig,
        station: str,
        *,
        storage: StationStorage,
        recorder: Recorder,
        session: StationSession,
        nodes: StationNodes,
        hosts: Mapping[str, RobotHost],
        broker: BrokerSupervisor,
        tasks: TaskEpisodes | None = None,
    ) -> None:
        self._config = config
        self._tasks = tasks
        self._station = station
        self._storage = storage
        self._recorder = recorder
        self._session = session
        self._nodes = nodes
        self._hosts = hosts
        self._broker = broker
        self._safety_log = SafetyLog(recorder.bus, config.name)

    def record(
        self,
        episode_id: str,
        task: str,
        operator: str,
        duration_s: float | None,
        progress: ProgressCallback | None,
    ) -> EpisodeResult:
        """Record the started episode until ``duration_s`` passes or a session command ends it.

        On any exception (Ctrl-C included) the devices stop, the robots hold, and the episode
        moves to the incomplete partition with the reason; earlier episodes are never touched.
        """
        session, recorder = self._session, self._recorder
        draft = self._storage.store.begin(
            rig=self._config.name,
            task=task,
            operator=operator,
            extra=EpisodeExtra(fingerprint=self._fingerprint(), station=self._station).to_json(),
            episode_id=episode_id,
        )
        session.recording(True)
        try:
            counts_before = self._safety_counts()
            inputs_before = self._input_counts()
            self._safety_log.begin()
            recorder.start(draft.mcap_path, since_ns=draft.start_ns)
            clock = session.agent().clock_record()
            recorder.add_metadata("clock", {k: str(v) for k, v in clock.items()})
            with self._cameras_recording(draft.camera_path) as videos:
                self._start_devices()
                try:
                    command = session.wait(duration_s, progress)
                    # The episode's end: what follows (devices stop, the robots' and cameras' last
                    # samples arrive, the log closes) is the stop sequence, 0.1 s on an idle host
                    # and over a second on a full one; the manifest's end is not moved by it.
                    window_end_ns = now_ns()
                    # The episode's safety and input record ends with its recording window, before
                    # the devices stop: a stopped operator makes each robot's watchdog stop it
                    # (250 ms later), which is the episode's end, not a fault in it. Read after
                    # the log is closed, a long episode's counts took that stop in.
                    counts_after = self._safety_counts()
                    safety_log = self._safety_log.end()
                    inputs_after = self._input_counts()
                    tasks = self._tasks.finish() if self._tasks is not None else []
                finally:
                    self._stop_devices()
            _await_tails(recorder, window_end_ns)
            self._await_frame_records(recorder, videos)
            stream_stats = recorder.stop()
            if recorder.write_error is not None:
                raise RecordingError(recorder.write_error)  # the episode ends incomplete with it
            latency = self._latency()
            instructions = _instructions(draft.mcap_path, episode_id)
            missing = self._missing_streams(stream_stats)
            extra = self._manifest_extra(draft, stream_stats, latency, videos, clock).model_copy(
                update={
                    "safety_events": _since(counts_before, counts_after),
                    "safety_log": safety_log,
                    **_input_record(_since(inputs_before, inputs_after)),
                    "missing_streams": missing,
                    **self._policy(),
                    "instructions": None
                    if instructions is None
                    else instructions.model_dump(mode="json", exclude={"episode_id"}),
                    **_task_record(tasks, self._session.outcome),
                }
            )
            session.recording(False)
            discard = command in _DISCARDING
            session.end_episode(discard=discard)
            if command is not None and discard:
                manifest = draft.abandon(
                    f"discarded by the operator ({command.value})", extra.to_json(), end_ns=window_end_ns
                )
            elif missing:
                manifest = draft.abandon(_missing_reason(missing), extra.to_json(), end_ns=window_end_ns)
            else:
                manifest = draft.commit(extra.to_json(), end_ns=window_end_ns)
        except BaseException as exc:
            if self._tasks is not None:
                self._tasks.abort()
            session.recording(False)
            session.end_episode(discard=True)
            quietly(recorder.stop)
            _abandon(draft, exc)
            raise
        # Before archive: it queues the upload.
        _count_instructions(self._storage.directory(manifest), instructions)
        directory = self._storage.archive(manifest)
        return EpisodeResult(
            manifest.id,
            manifest.status,
            directory,
            manifest.duration_s or 0.0,
            stream_stats,
            latency,
            {name: v.video.frames for name, v in videos.items()},
            command,
            self._storage.store,
        )

    def _start_devices(self) -> None:
        self._nodes.start_devices()
        for host in self._hosts.values():
            host.call(StartDevices())

    def _stop_devices(self) -> None:
        for host in self._hosts.values():
            host.call(StopDevices())
        self._nodes.stop_devices()

    def _fingerprint(self) -> FingerprintRecord:
        fingerprint = self._storage.fingerprint
        return FingerprintRecord(digest=fingerprint.digest, components=dict(fingerprint.components))

    def _manifest_extra(
        self,
        draft: EpisodeDraft,
        stream_stats: list[StreamSummary],
        latency: LatencySummary,
        videos: Mapping[str, CameraEpisode],
        clock: Mapping[str, int | float | bool | str],
    ) -> EpisodeExtra:
        recorder, status = self._recorder, self._session.agent().status
        alignment: JsonValue = None
        if videos:
            try:
                alignment = recorder.capture_times.report()
            except RecordingError as exc:  # e.g. no camera frame was recorded
                alignment = {"error": str(exc)}
        camera_cfgs = {c.id: c for c in self._config.cameras}
        extra = EpisodeExtra(
            fingerprint=self._fingerprint(),
            station=self._station,
            streams=[_json(s) for s in stream_stats],
            cameras={
                name: CameraRecord(
                    file=f"cameras/{name}.mp4",
                    frames=v.video.frames,
                    dropped=v.video.dropped,
                    width=camera_cfgs[name].width,
                    height=camera_cfgs[name].height,
                    fps=camera_cfgs[name].fps,
                    codec=camera_cfgs[name].codec,
                    skipped=v.skipped,
                    late=v.late,
                    callback_errors=v.callback_errors,
                )
                for name, v in videos.items()
            },
            robot_joints=self._robot_joints(),
            priorities=priority.applied(),
            latency_ms=_json(latency),
            safety_events=self._safety_counts(),
            robots=[r.model if isinstance(r, _Modelled) else r.type for r in self._config.robots],
            session_id=status.session_id if status is not None else None,
            outcome=self._session.outcome,
            broker_outages=[
                OutageRecord(down_ns=d, up_ns=u) for d, u in self._broker.outages_since(draft.start_ns)
            ],
            clock=dict(clock),
            malformed_messages=dict(recorder.malformed),
            samples_before_start=recorder.before_start,
            health=recorder.health.summary(),
        )
        if videos:
            extra = extra.model_copy(update={"alignment": alignment})
        return extra

    def _policy(self) -> dict[str, JsonValue]:
        """The manifest's ``policy`` section when a policy drove (:mod:`telerig.runtime.rollout`)."""
        nodes = self._nodes
        handovers = {rid: n.handover.state() for rid, n in nodes.controls.items() if n.handover is not None}
        return policy_record({did: n.device for did, n in nodes.devices.items()}, handovers)

    def _robot_joints(self) -> dict[str, RobotJointsRecord]:
        """Robot id → its driver's joints and limits, for this station's robots (local or hosted)."""
        configs = {r.id: r for r in self._config.robots}
        joints = {rid: robot_joints_record(configs[rid], n.robot) for rid, n in self._nodes.controls.items()}
        for rid, host in self._hosts.items():
            if host.info.robot_joints is not None:
                joints[rid] = host.info.robot_joints
        return joints

    def _missing_streams(self, stream_stats: list[StreamSummary]) -> dict[str, str]:
        """Bound device streams and robot states of this station that delivered nothing: topic → the
        address the device waited on (``""`` when it has none), each with a warning naming it."""
        cfg, station = self._config, self._station
        received = {s.name: s.messages for s in stream_stats}
        devices = {d.id: d for d in cfg.devices if d.station == station}
        wanted: dict[str, str] = {}
        for binding in cfg.bindings:
            if (device := devices.get(binding.device)) is not None:
                wanted[str(Topic(cfg.name, device.id, binding.part))] = _address(device)
        for robot in (r for r in cfg.robots if r.station == station):
            wanted[str(Topic(cfg.name, robot.id, streams.JOINT_STATE))] = ""
        missing = {topic: where for topic, where in wanted.items() if not received.get(topic)}
        for topic, where in missing.items():
            node = topic.split("/")[-2]
            waited = (
                f"; it waited on {where}: is its sender (app, bridge, server) running there?" if where else ""
            )
            log.warning("episode: %s delivered no data on %s%s", node, topic, waited)
        return missing

    def _safety_counts(self) -> dict[str, dict[str, int]]:
        counts = {rid: dict(n.safety.counts) for rid, n in self._nodes.controls.items()}
        for rid, host in self._hosts.items():
            hosted: dict[str, int] = host.call(SafetyCounts())
            counts[rid] = hosted
        return counts

    def _input_counts(self) -> dict[str, dict[str, int]]:
        """Robot → running totals of rejected input samples per reason, plus ``tick_faults``."""
        counts: dict[str, dict[str, int]] = {}
        for rid, node in self._nodes.controls.items():
            counts[rid] = {**node.stats.rejected, _TICK_FAULTS: node.stats.tick_faults}
        for rid, host in self._hosts.items():
            stats = host.call(Stats())
            counts[rid] = {**stats.rejected, _TICK_FAULTS: stats.tick_faults}
        return counts

    def _latency(self) -> LatencySummary:
        merged = LatencyTracker()
        for node in self._nodes.controls.values():
            for value in node.latency.values_ns():
                merged.add(int(value))
        for host in self._hosts.values():
            for value in host.call(LatencyNs()):
                merged.add(int(value))
        return merged.summary()

    def _await_frame_records(self, recorder: Recorder, videos: Mapping[str, CameraEpisode]) -> None:
        """Wait, at most :data:`_FRAME_RECORDS_WAIT_S`, until the recorder holds the ``frames`` record
        of every frame each camera's video kept. A camera publishes a frame's record after its encoder
        took the frame, so the last one can still be on its way (from a robot's process, through the
        broker) when the video is finished; closing the log then left a frame in the video without
        its record (found by the demo's frame-count test on a loaded host: 98 frames, 97 records)."""
        deadline = time.monotonic() + _FRAME_RECORDS_WAIT_S
        for name, episode in videos.items():
            topic = str(Topic(self._config.name, name, streams.CAMERA_FRAMES))
            while (
                recorder.newest(streams.CAMERA_FRAMES).get(topic, (0, 0))[1] < episode.video.frames
                and time.monotonic() < deadline
            ):
                time.sleep(0.005)

    @contextlib.contextmanager
    def _cameras_recording(self, camera_path: Callable[[str], Path]) -> Iterator[dict[str, CameraEpisode]]:
        """Record every camera for the duration of the block; the dict holds their results afterwards."""
        results: dict[str, CameraEpisode] = {}
        cameras = self._nodes.cameras
        try:
            for name, camera in cameras.items():
                camera.begin(camera_path(name))
            for host in self._hosts.values():
                host.begin_cameras({name: camera_path(name) for name in host.plan.cameras})
            yield results
        finally:
            for name, camera in cameras.items():
                result = camera.end()
                if result is not None:
                    results[name] = result
            for host in self._hosts.values():
                results.update(host.end_cameras())


def _since(
    before: Mapping[str, Mapping[str, int]], now: Mapping[str, Mapping[str, int]]
) -> dict[str, dict[str, int]]:
    """Per robot and code, the safety events counted between two snapshots of the running totals."""
    return {
        robot: {code: n - before.get(robot, {}).get(code, 0) for code, n in counts.items()}
        for robot, counts in now.items()
    }


def _await_tails(recorder: Recorder, end_ns: int) -> None:
    """Wait, at most :data:`_TAIL_WAIT_S`, until the recorder holds each robot's joint state captured
    after the recording window ended at ``end_ns`` [ns] (a control loop publishes it every tick, also
    after its device stopped). A station short of CPU receives its streams late; closing the log
    as the window ends cut each stream's last part off (the sync gate fails a stream that stops more
    than a second early). A robot whose state stopped arriving (its process died, its driver faulted)
    is not waited for: once nothing new arrived for :data:`_TAIL_QUIET_S`."""
    deadline = time.monotonic() + _TAIL_WAIT_S
    seen: dict[str, tuple[int, float]] = {}  # topic -> (count, when it last grew)
    while time.monotonic() < deadline:
        now = time.monotonic()
        waiting = False
        for topic, (newest, count) in recorder.newest(streams.JOINT_STATE).items():
            last = seen.get(topic)
            if last is None or count > last[0]:
                seen[topic] = last = (count, now)
            if newest < end_ns and now - last[1] < _TAIL_QUIET_S:
                waiting = True
        if not waiting:
            return
        time.sleep(0.01)


_TICK_FAULTS = "tick_faults"
#: Longest wait for every robot's joint state from after the recording window [s] (_await_tails).
_TAIL_WAIT_S = 2.0
#: A robot's state that grew no sample in this long is no longer waited for [s].
_TAIL_QUIET_S = 0.25
#: Longest wait for the last camera frames' records after the videos are finished [s].
_FRAME_RECORDS_WAIT_S = 1.0


def _input_record(counts: Mapping[str, Mapping[str, int]]) -> dict[str, object]:
    """The episode's ``input_rejected`` (non-zero reasons only) and ``tick_faults`` per robot."""
    return {
        "input_rejected": {
            robot: {r: n for r, n in c.items() if r != _TICK_FAULTS and n} for robot, c in counts.items()
        },
        "tick_faults": {robot: c.get(_TICK_FAULTS, 0) for robot, c in counts.items()},
    }


def _task_record(tasks: list[TaskResult], marked: str | None) -> dict[str, object]:
    """The manifest's ``task`` and ``outcome``: judged from the scene unless the operator marked it."""
    if not tasks:
        return {}
    task = tasks[0]
    return {"task": task.record, "outcome": marked or ("success" if task.success else "failure")}


def _missing_reason(missing: Mapping[str, str]) -> str:
    """The incomplete episode's reason: the streams with no data, and where their devices waited."""
    parts = [
        "/".join(topic.split("/")[-2:]) + (f" (waited on {where})" if where else "")
        for topic, where in missing.items()
    ]
    return "no data on bound stream(s): " + ", ".join(parts)


@runtime_checkable
class _Modelled(Protocol):
    """A robot config that names its model (e.g. ``ur5e_robotiq85``)."""

    model: str


@runtime_checkable
class _Rated(Protocol):
    """A device config with a sample rate [Hz] (scripted and replayed devices, most trackers)."""

    rate_hz: float


@runtime_checkable
class _Listens(Protocol):
    """A device config with a network address it listens on or connects to."""

    host: str
    port: int


@runtime_checkable
class _ListensAt(Protocol):
    listen_host: str
    listen_port: int


@runtime_checkable
class _Connects(Protocol):
    url: str


def _address(device: DeviceConfig) -> str:
    """Where ``device`` waits for its data, e.g. ``127.0.0.1:9870``; ``""`` when it has no address."""
    if isinstance(device, _Connects):
        return device.url
    if isinstance(device, _Listens):
        return f"{device.host}:{device.port}"
    if isinstance(device, _ListensAt):
        return f"{device.listen_host}:{device.listen_port}"
    return ""


def _abandon(draft: EpisodeDraft, exc: BaseException) -> None:
    """Move the interrupted episode to the incomplete partition with the reason; re-raise as needed."""
    if isinstance(exc, Terminated):
        reason = "terminated (SIGTERM)"
    elif isinstance(exc, KeyboardInterrupt):
        reason = "interrupted by operator (Ctrl-C)"
    else:
        reason = str(exc)
    try:
        draft.abandon(reason or type(exc).__name__)
    except (OSError, RecordingError) as abandon_exc:
        raise RecordingError(
            f"episode {draft.id} could not be closed ({abandon_exc}); free disk space, then run "
            f"`telerig repair {draft.id}`"
        ) from exc
    if isinstance(exc, OSError):
        raise RecordingError(f"episode {draft.id} marked incomplete: {exc}") from exc


def expected_rates(
    config: RigConfig, station: str, nodes: StationNodes, hosts: Mapping[str, RobotHost]
) -> dict[str, float]:
    """Topic → the rate [Hz] the recorder expects of every stream this station's nodes publish."""
    rates: dict[str, float] = {}
    devices = {d.id: d for d in config.devices if d.station == station}
    for binding in config.bindings:
        if (device := devices.get(binding.device)) is not None:
            topic = str(Topic(config.name, binding.device, binding.part))
            rates[topic] = float(device.rate_hz) if isinstance(device, _Rated) else 0.0
    input_rates = dict(rates)
    for robot_cfg in (r for r in config.robots if r.station == station):
        rate = robot_cfg.control_rate()

        def expect(stream: str, hz: float, robot: str = robot_cfg.id) -> None:
            rates[str(Topic(config.name, robot, stream))] = hz

        expect(streams.JOINT_STATE, rate)
        bound: Mapping[str, str | None]
        sensed: tuple[str, ...]
        if robot_cfg.id in nodes.controls:
            bound = nodes.controls[robot_cfg.id].bound_topics
            sensed = nodes.controls[robot_cfg.id].sensed_streams
        elif robot_cfg.id in hosts:
            bound = hosts[robot_cfg.id].info.bound_topics
            sensed = hosts[robot_cfg.id].info.sensed_streams
        else:
            bound, sensed = {}, ()
        if bound.get("joints", "") is not None:  # a gripper alone sends its gripper commands only
            expect(streams.JOINT_SENT, rate)  # the loop ticks at the control rate, input or not
        for stream in sensed:  # gripper_state, wrench, base_pose: every tick, like joint_state
            expect(stream, rate * sensed.count(stream))  # object_pose: one sample per object
        # Retargeting runs per fresh input sample: the device's rate, at most the control rate.
        for part, requested_and_sent in (
            ("joints", (streams.JOINT_REQUESTED,)),
            ("gripper", (streams.GRIPPER_REQUESTED, streams.GRIPPER_SENT)),
            ("base", (streams.BASE_REQUESTED, streams.BASE_SENT)),
        ):
            source = bound.get(part)
            if source is None:
                continue
            hz = min(rate, input_rates.get(source, 0.0) or rate) if part != "base" else rate
            for stream in requested_and_sent:
                expect(stream, hz)
    for camera_cfg in (c for c in config.cameras if c.station == station):
        rates[str(Topic(config.name, camera_cfg.id, streams.CAMERA_FRAMES))] = camera_cfg.fps
    return rates


def _json(obj: Any) -> dict[str, JsonValue]:
    """A slotted stats dataclass as JSON values (NaN becomes null)."""
    out: dict[str, JsonValue] = {}
    for name in obj.__slots__:
        value = getattr(obj, name)
        out[name] = None if isinstance(value, float) and math.isnan(value) else value
    return out
