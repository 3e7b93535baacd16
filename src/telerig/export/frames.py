"""One episode resampled onto a dataset's frame grid: the single resampling policy every export uses.

The recorder keeps every stream at its native rate (seed 000: raw first, alignment at export). A
dataset needs one row per frame at a fixed rate, so this module builds a regular grid from the
anchor camera's first recorded frame at the dataset rate, and takes each stream's value at each
grid time by its policy:

- ``joint_state`` and ``gripper_state`` (measured, smooth): ``linear`` between the samples either
  side;
- ``joint_command_sent``, ``gripper_command_sent``, ``base_command_sent`` (commands, held by the
  robot until the next): ``zoh``, the last command at or before the frame;
- camera images: the nearest recorded frame.

The per-frame distance to the sample a value comes from is kept per source
(:attr:`EpisodeFrames.alignment_error_ms`), so a dataset carries how well each frame is aligned
instead of pretending the grid times were measured.
"""

from __future__ import annotations

import functools
import math
import re
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import av
import numpy as np
import numpy.typing as npt
from pydantic import ValidationError

from telerig.bus.catalogue import (
    BASE_SENT,
    CAMERA_FRAMES,
    GRIPPER_SENT,
    JOINT_SENT,
    JOINT_STATE,
)
from telerig.bus.topics import Topic, node_of, stream_of
from telerig.errors import ExportError, RecordingError
from telerig.export.language import FrameLanguage, frame_language, read_segments_of
from telerig.export.schema import CameraSpec, DatasetSchema, JointSpec, Vector
from telerig.record.align import AlignedStream, Policy, StreamData, StreamPolicy, align, load_streams
from telerig.store.episodes import EpisodeManifest
from telerig.store.label_file import LabelRecord, read_label
from telerig.store.manifest_extra import EpisodeExtra
from telerig.store.qa_file import QaRecord, read_qa

__all__ = [
    "DEFAULT_POLICIES",
    "GRIPPER_STATE",
    "CameraTrack",
    "EpisodeFrames",
    "episode_schema",
    "load_episode",
    "read_episode_qa",
    "read_manifest",
]

Int64Array = npt.NDArray[np.int64]
Float32Array = npt.NDArray[np.float32]
Float64Array = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
UInt8Array = npt.NDArray[np.uint8]

#: The measured gripper opening stream (recorded where the driver reports it).
GRIPPER_STATE = "gripper_state"

#: Resampling policy per stream name (the rig's default; ``telerig export --resample`` overrides).
DEFAULT_POLICIES: Mapping[str, Policy] = {
    JOINT_STATE: "linear",
    GRIPPER_STATE: "linear",
    JOINT_SENT: "zoh",
    GRIPPER_SENT: "zoh",
    BASE_SENT: "zoh",
}

#: Rate used when an episode has no camera to take the rate from [Hz].
_FPS_WITHOUT_CAMERA = 30
#: Smallest tolerance [ms]; a stream's tolerance is at least 1.5 of its own sample period, so a
#: 100 Hz command held by zoh (up to 10 ms old by design) is not "missing" between two ticks.
_MIN_TOLERANCE_MS = 5.0
_PERIODS_OF_TOLERANCE = 1.5
_CAMERA_COMPONENT = re.compile(r"^(\d+)x(\d+)@(\d+)")
_BASE_FIELDS = ("vx", "vy", "wz")


@dataclass(frozen=True, slots=True)
class CameraTrack:
    """One camera's frames at the dataset's grid.

    Attributes:
        spec: The camera's schema entry.
        path: The recorded video (``<episode>/cameras/<key>.mp4``).
        source_index: Index in the recorded video of the frame used at each dataset frame. Shape (F,).
        error_ms: |recorded frame time - dataset frame time| [ms]. Shape (F,).
        one_to_one: Every recorded frame is used exactly once, in order, at the dataset rate: the
            video's packets can be copied with new timestamps instead of decoded and re-encoded.
    """

    spec: CameraSpec
    path: Path
    source_index: Int64Array
    error_ms: Float32Array
    one_to_one: bool

    def frames(self) -> Iterator[UInt8Array]:
        """Decode the video once and yield the image of every dataset frame, in order.

        Yields:
            RGB frames, ``uint8``, shape (height, width, 3); a recorded frame used by several
            dataset frames is yielded for each.

        Raises:
            ExportError: The video cannot be decoded or holds fewer frames than the recording says.
        """
        wanted = self.source_index
        k = 0
        try:
            with av.open(str(self.path)) as container:
                stream = container.streams.video[0]
                stream.thread_type = "AUTO"
                for j, frame in enumerate(container.decode(stream)):
                    if k >= wanted.size:
                        return
                    if wanted[k] != j:
                        continue
                    image = frame.to_ndarray(format="rgb24")
                    while k < wanted.size and wanted[k] == j:
                        yield image
                        k += 1
        except (av.FFmpegError, OSError) as exc:
            raise ExportError(f"{self.path}: cannot decode the video ({exc}); run `telerig repair`") from None
        if k < wanted.size:
            raise ExportError(
                f"{self.path} holds fewer frames than the recording lists (needs frame "
                f"{int(wanted[k])}); the video is truncated: run `telerig repair`"
            )


@dataclass(frozen=True, slots=True)
class EpisodeFrames:
    """One episode resampled at the dataset's frame grid.

    Attributes:
        episode_id: The telerig episode id.
        directory: The recorded episode's directory (its MCAP log, videos and manifest).
        manifest: The episode's manifest (``EpisodeExtra.of(manifest)`` for the typed extra).
        task: The task instruction.
        schema: What each frame holds (identical for every episode of a dataset).
        frame_ns: Grid time of each frame, common clock [ns]: the anchor camera's first frame time
            plus ``k * 1e9 / fps`` (later times where idle spans were cut). Shape (F,).
        timestamp: Seconds from the episode's first dataset frame, exactly ``k / fps``. Shape (F,).
        state: Measured state at each frame, in ``schema.state`` order. Shape (F, S).
        action: Commanded action at each frame, in ``schema.action`` order. Shape (F, A).
        valid: Whether every stream and camera had a sample within tolerance. Shape (F,).
        alignment_error_ms: Source (``arm0/joint_state``, ``scene/frames``) → distance [ms] from
            each frame to the sample its value comes from; NaN where the stream had none. Shape (F,).
        raw_time_ns: Source → capture time of the sample used, common clock [ns]; -1 where none.
            Shape (F,).
        cameras: Camera key → its frames, sorted by key.
        trimmed_s: Spans cut from the episode as idle, [start, end) seconds from the episode's
            start (``manifest.start_ns``); empty when nothing was cut.
        qa: The episode's quality record (gate verdicts, score); ``None`` when its gates have not
            run.
        label: The success/failure label set after recording (``label.json``); ``None`` when none.
        language: Per-frame subtask labels and instructions from the episode's ``segments.json``
            (:mod:`telerig.export.language`); ``None`` when it has none (exports then write what
            they wrote before segments existed).
    """

    episode_id: str
    directory: Path
    manifest: EpisodeManifest
    task: str
    schema: DatasetSchema
    frame_ns: Int64Array
    timestamp: Float64Array
    state: Float32Array
    action: Float32Array
    valid: BoolArray
    alignment_error_ms: Mapping[str, Float32Array]
    raw_time_ns: Mapping[str, Int64Array]
    cameras: Mapping[str, CameraTrack]
    trimmed_s: tuple[tuple[float, float], ...] = ()
    qa: QaRecord | None = None
    label: LabelRecord | None = None
    language: FrameLanguage | None = None

    @property
    def length(self) -> int:
        """Number of frames (F)."""
        return int(self.frame_ns.size)

    @property
    def extra(self) -> EpisodeExtra:
        """The typed manifest extra."""
        return EpisodeExtra.of(self.manifest)

    @property
    def outcome(self) -> Literal["success", "failure"] | None:
        """The success/failure label (``label.json``), else the operator's mark while recording."""
        return self.label.outcome if self.label is not None else self.extra.outcome

    @property
    def quality(self) -> float | None:
        """The quality score in [0, 1]; ``None`` when not scored."""
        return None if self.qa is None else self.qa.score_total

    @property
    def gates(self) -> dict[str, bool | None]:
        """Gate name → passed (``None``: not applicable); empty when the gates have not run."""
        return {} if self.qa is None else {v.gate: v.passed for v in self.qa.verdicts}


def read_manifest(episode_dir: Path) -> EpisodeManifest:
    """The manifest of a committed episode directory.

    Raises:
        ExportError: One line naming the directory when it is not an episode.
    """
    path = Path(episode_dir) / "manifest.json"
    try:
        return EpisodeManifest.model_validate_json(path.read_bytes())
    except FileNotFoundError:
        raise ExportError(
            f"{episode_dir} is not an episode (no manifest.json); pass an episode directory"
        ) from None
    except (OSError, ValidationError) as exc:
        first = str(exc).splitlines()[0]
        raise ExportError(f"{path}: unreadable manifest ({first}); run `telerig repair`") from None


@dataclass(frozen=True, slots=True)
class _Robot:
    id: str
    model: str
    joints: tuple[str, ...]
    lower: tuple[float, ...]
    upper: tuple[float, ...]
    velocity: tuple[float, ...]


def episode_schema(
    episode_dir: Path,
    *,
    fps: int | None = None,
    normalized: bool = False,
    streams: Mapping[str, StreamData] | None = None,
) -> DatasetSchema:
    """The dataset schema an episode exports to (what :func:`load_episode` fills).

    Args:
        episode_dir: A committed episode directory.
        fps: Dataset rate [Hz]; the anchor camera's configured rate when ``None`` (30 Hz without a
            camera).
        normalized: Whether exports map state and action to [-1, 1] from the limits.
        streams: The episode's streams if already loaded (:func:`load_streams`).

    Raises:
        ExportError: The episode lacks what a dataset needs (fingerprint, robot joint states).
    """
    episode_dir = Path(episode_dir)
    manifest = read_manifest(episode_dir)
    extra = _extra(manifest)
    if streams is None:
        streams = _load(episode_dir, manifest, extra)
    return _schema(manifest, extra, streams, episode_dir, fps, normalized)


def load_episode(
    episode_dir: Path,
    *,
    fps: int | None = None,
    normalized: bool = False,
    policies: Mapping[str, Policy] | None = None,
    trim_s: Sequence[tuple[float, float]] = (),
) -> EpisodeFrames:
    """Resample a committed episode at the dataset grid.

    Args:
        episode_dir: A committed episode directory (manifest.json, episode.mcap, cameras/*.mp4).
        fps: Dataset rate [Hz]; the anchor camera's configured rate when ``None``.
        normalized: Map state and action to [-1, 1] from the limits.
        policies: Stream name (``joint_state``) → policy, over :data:`DEFAULT_POLICIES`.
        trim_s: Spans to cut, [start, end) seconds from the episode's start (idle heads, tails,
            pauses from the quality gates); the recording itself is untouched.

    Raises:
        ExportError: One line naming the episode and what it lacks.
    """
    episode_dir = Path(episode_dir)
    manifest = read_manifest(episode_dir)
    extra = _extra(manifest)
    streams = _load(episode_dir, manifest, extra)
    schema = _schema(manifest, extra, streams, episode_dir, fps, normalized)
    cameras = _camera_topics(manifest, streams)
    grid = _grid(manifest, streams, cameras, schema.fps)
    policy = {**DEFAULT_POLICIES, **(policies or {})}

    state_cols: list[Float64Array] = []
    action_cols: list[Float64Array] = []
    errors: dict[str, Float32Array] = {}
    raw: dict[str, Int64Array] = {}
    valid = np.ones(grid.size, dtype=np.bool_)
    wanted = _wanted_streams(schema, manifest.rig)
    used = {topic: streams[topic] for topic in wanted if topic in streams}
    aligned = align(used, grid, policies=_stream_policies(used, extra, policy))
    for topic, (vector, field) in wanted.items():
        stream = aligned.get(topic)
        if stream is None:
            raise ExportError(
                f"episode {manifest.id} has no {topic} stream, which the dataset's "
                f"{vector} needs; record it or export this episode into another dataset"
            )
        values = _filled(stream, field, manifest.id)
        (state_cols if vector == "state" else action_cols).append(values.reshape(grid.size, -1))
        key = _source(topic)
        if key not in errors:
            errors[key] = _error_ms(stream)
            raw[key] = _raw_times(stream, streams[topic])
            valid &= stream.valid

    tracks: dict[str, CameraTrack] = {}
    for spec in schema.cameras:
        topic = cameras[spec.key]
        track = _camera_track(episode_dir, manifest, spec, streams[topic], grid, schema.fps)
        tracks[spec.key] = track
        errors[f"{spec.key}/{CAMERA_FRAMES}"] = track.error_ms
        raw[f"{spec.key}/{CAMERA_FRAMES}"] = _camera_raw(streams[topic], track.source_index)
        valid &= track.error_ms <= 1e3 / (2 * spec.fps) + 1e-3

    state = _columns(state_cols, grid.size)
    action = _columns(action_cols, grid.size)
    if normalized:
        state = schema.normalize(state, "state")
        action = schema.normalize(action, "action")

    keep = _keep_mask(grid, manifest.start_ns, trim_s)
    if not keep.any():
        raise ExportError(f"episode {manifest.id}: trimming idle spans leaves no frame; export it untrimmed")
    timestamp = np.arange(int(keep.sum()), dtype=np.float64) / schema.fps
    kept_tracks = {k: _trimmed(t, keep, schema.fps) for k, t in sorted(tracks.items())}
    kept_raw = {k: v[keep] for k, v in raw.items()}
    segments, notes = read_segments_of(episode_dir)
    language = None
    if segments is not None:
        language = frame_language(
            segments,
            notes,
            task=manifest.task,
            frame_ns=grid[keep],
            start_ns=manifest.start_ns,
            source_index={k: t.source_index for k, t in kept_tracks.items()},
            raw_time_ns=kept_raw,
            camera_fps={k: t.spec.fps for k, t in kept_tracks.items()},
        )
    return EpisodeFrames(
        episode_id=manifest.id,
        directory=episode_dir,
        manifest=manifest,
        task=manifest.task,
        schema=schema,
        frame_ns=grid[keep],
        timestamp=timestamp,
        state=np.ascontiguousarray(state[keep], dtype=np.float32),
        action=np.ascontiguousarray(action[keep], dtype=np.float32),
        valid=valid[keep],
        alignment_error_ms={k: v[keep] for k, v in errors.items()},
        raw_time_ns=kept_raw,
        cameras=kept_tracks,
        trimmed_s=tuple((float(a), float(b)) for a, b in trim_s),
        qa=read_episode_qa(episode_dir),
        label=_read_label(episode_dir),
        language=language,
    )


def read_episode_qa(episode_dir: Path) -> QaRecord | None:
    """The episode's quality record (``qa.json``), ``None`` when its gates have not run.

    Raises:
        ExportError: The record is unreadable (re-run ``telerig qa`` on the episode).
    """
    try:
        return read_qa(Path(episode_dir))
    except RecordingError as exc:
        raise ExportError(str(exc)) from None


def _read_label(episode_dir: Path) -> LabelRecord | None:
    try:
        return read_label(Path(episode_dir))
    except RecordingError as exc:
        raise ExportError(str(exc)) from None


def _columns(blocks: list[Float64Array], frames: int) -> Float32Array:
    if not blocks:
        return np.zeros((frames, 0), dtype=np.float32)
    return np.concatenate(blocks, axis=1).astype(np.float32)


# --- schema --------------------------------------------------------------------------------------


def _extra(manifest: EpisodeManifest) -> EpisodeExtra:
    try:
        return EpisodeExtra.of(manifest)
    except RecordingError as exc:
        raise ExportError(str(exc)) from None


#: The streams a dataset reads (the rest of the log, e.g. device samples, is not decoded).
_DATASET_STREAMS = frozenset({JOINT_STATE, JOINT_SENT, GRIPPER_STATE, GRIPPER_SENT, BASE_SENT, CAMERA_FRAMES})


def _load(episode_dir: Path, manifest: EpisodeManifest, extra: EpisodeExtra) -> dict[str, StreamData]:
    """The dataset's streams of the episode; decoding only them takes a third of decoding all."""
    listed = [e.get("name") for e in extra.streams] + [
        _topic(manifest.rig, key, CAMERA_FRAMES) for key in extra.cameras
    ]
    topics = [t for t in listed if isinstance(t, str) and stream_of(t) in _DATASET_STREAMS]
    try:
        return load_streams(episode_dir / "episode.mcap", topics=topics or None)
    except RecordingError as exc:
        raise ExportError(f"{episode_dir}: {exc}") from None


def _schema(
    manifest: EpisodeManifest,
    extra: EpisodeExtra,
    streams: Mapping[str, StreamData],
    episode_dir: Path,
    fps: int | None,
    normalized: bool,
) -> DatasetSchema:
    if extra.fingerprint is None:
        raise ExportError(
            f"episode {manifest.id} has no rig fingerprint, so nothing says which dataset it may join; "
            "it was recorded by an older telerig: re-record it"
        )
    rig = manifest.rig
    robots = _robots(manifest, extra, streams)
    state: list[JointSpec] = []
    action: list[JointSpec] = []
    several = len(robots) > 1
    for robot in robots:
        prefix = f"{robot.id}." if several else ""
        joints = [
            JointSpec(f"{prefix}{name}", robot.id, "joints", lo, hi, vel)
            for name, lo, hi, vel in zip(robot.joints, robot.lower, robot.upper, robot.velocity, strict=True)
        ]
        gripper = JointSpec(f"{prefix}gripper", robot.id, "gripper", 0.0, 1.0)
        state += joints
        if _topic(rig, robot.id, GRIPPER_STATE) in streams:
            state.append(gripper)
        if _topic(rig, robot.id, JOINT_SENT) in streams:  # a gripper alone: its gripper commands only
            action += joints
        if _topic(rig, robot.id, GRIPPER_SENT) in streams:
            action.append(gripper)
        if _topic(rig, robot.id, BASE_SENT) in streams:
            action += [JointSpec(f"{prefix}base_{f}", robot.id, "base") for f in _BASE_FIELDS]
    cameras = tuple(
        _camera_spec(manifest, extra, key, episode_dir) for key in sorted(_camera_topics(manifest, streams))
    )
    if fps is None:
        fps = cameras[0].fps if cameras else _FPS_WITHOUT_CAMERA
    return DatasetSchema(
        rig=rig,
        fingerprint=extra.fingerprint.digest,
        fps=fps,
        robots={r.id: r.model for r in robots},
        state=tuple(state),
        action=tuple(action),
        cameras=cameras,
        normalized=normalized,
    )


def _robots(
    manifest: EpisodeManifest, extra: EpisodeExtra, streams: Mapping[str, StreamData]
) -> list[_Robot]:
    """Robots with joint states, in the rig's order where the manifest records it."""
    recorded = {node_of(t): s for t, s in streams.items() if stream_of(t) == JOINT_STATE}
    if not recorded:
        raise ExportError(
            f"episode {manifest.id} has no robot joint_state stream; a dataset needs the robot's "
            "measured state (was the robot connected?)"
        )
    records = extra.robot_joints
    order = [r for r in records if r in recorded] + sorted(r for r in recorded if r not in records)
    robots: list[_Robot] = []
    for robot_id in order:
        names = recorded[robot_id].names
        record = records.get(robot_id)
        if record is not None:
            bounds = zip(
                (-math.inf if v is None else v for v in record.lower),
                (math.inf if v is None else v for v in record.upper),
                record.velocity,
                strict=True,
            )
            limits = dict(zip(record.joints, bounds, strict=True))
            model = record.model or record.type
        else:  # recorded before manifests carried the driver's limits
            model = extra.robots[0] if len(recorded) == 1 and len(extra.robots) == 1 else robot_id
            limits = _model_limits(model)
        inf = (-math.inf, math.inf, math.inf)
        lower, upper, velocity = (
            zip(*(limits.get(n, inf) for n in names), strict=True) if names else ((), (), ())
        )
        robots.append(_Robot(robot_id, model, names, tuple(lower), tuple(upper), tuple(velocity)))
    return robots


@functools.cache
def _model_limits(model: str) -> dict[str, tuple[float, float, float]]:
    """Joint limits of a shipped arm model (episodes recorded before the manifest carried them)."""
    from telerig.robots.models import ARM_MODELS
    from telerig.robots.models.arm import build_arm_kinematics

    if model not in ARM_MODELS:
        return {}
    scene = build_arm_kinematics(model)
    arm = ARM_MODELS[model]
    out: dict[str, tuple[float, float, float]] = {}
    for name, velocity in zip(arm.joints, arm.velocity, strict=True):
        lo, hi = scene.model.joint(name).range
        out[name] = (float(lo), float(hi), float(velocity))
    return out


def _camera_topics(manifest: EpisodeManifest, streams: Mapping[str, StreamData]) -> dict[str, str]:
    """Camera key → its frames topic, for cameras whose video the episode holds."""
    files = {f.path for f in manifest.files}
    out: dict[str, str] = {}
    for topic in streams:
        if stream_of(topic) == CAMERA_FRAMES and f"cameras/{node_of(topic)}.mp4" in files:
            out[node_of(topic)] = topic
    return out


def _camera_spec(manifest: EpisodeManifest, extra: EpisodeExtra, key: str, episode_dir: Path) -> CameraSpec:
    record = extra.cameras.get(key)
    if record is not None and record.width and record.height and record.fps and record.codec:
        return CameraSpec(key, record.height, record.width, round(record.fps), record.codec)
    width, height, fps, codec = _probe_camera(manifest, extra, key, episode_dir)
    return CameraSpec(key=key, height=height, width=width, fps=fps, codec=codec)


def _probe_camera(
    manifest: EpisodeManifest, extra: EpisodeExtra, key: str, episode_dir: Path
) -> tuple[int, int, int, str]:
    """Size and codec from the video; the configured rate from the rig fingerprint."""
    path = episode_dir / "cameras" / f"{key}.mp4"
    try:
        with av.open(str(path)) as container:
            ctx = container.streams.video[0].codec_context
            width, height, codec = int(ctx.width), int(ctx.height), str(ctx.name)
    except (av.FFmpegError, OSError, IndexError) as exc:
        raise ExportError(f"{path}: cannot read the video ({exc}); run `telerig repair`") from None
    component = extra.fingerprint.components.get(f"camera {key}", "") if extra.fingerprint else ""
    match = _CAMERA_COMPONENT.match(component)
    if match is None:
        raise ExportError(f"episode {manifest.id}: the rate of camera {key!r} is not recorded; pass --fps")
    return width, height, int(match.group(3)), codec


# --- resampling ----------------------------------------------------------------------------------


def _grid(
    manifest: EpisodeManifest, streams: Mapping[str, StreamData], cameras: Mapping[str, str], fps: int
) -> Int64Array:
    """Frame times [ns]: from the anchor camera's first frame (else the first joint state) to its last."""
    if cameras:
        times = streams[cameras[sorted(cameras)[0]]].time_ns
    else:
        times = np.concatenate([s.time_ns for t, s in streams.items() if stream_of(t) == JOINT_STATE])
        times.sort()
    if times.size == 0:
        raise ExportError(f"episode {manifest.id} has no recorded frame or joint state to anchor on")
    t0, t1 = int(times[0]), int(times[-1])
    count = int((t1 - t0) * fps // 1_000_000_000) + 1
    return t0 + np.round(np.arange(count, dtype=np.float64) * (1e9 / fps)).astype(np.int64)


def _wanted_streams(schema: DatasetSchema, rig: str) -> dict[str, tuple[Vector, str]]:
    """Topic → (vector, field) in vector order (``*base``: the base velocity's three fields)."""
    out: dict[str, tuple[Vector, str]] = {}
    vectors: tuple[tuple[Vector, tuple[JointSpec, ...]], ...] = (
        ("state", schema.state),
        ("action", schema.action),
    )
    for vector, specs in vectors:
        stream_of = {"joints": JOINT_STATE if vector == "state" else JOINT_SENT}
        stream_of["gripper"] = GRIPPER_STATE if vector == "state" else GRIPPER_SENT
        seen: set[tuple[str, str]] = set()
        for spec in specs:
            if (spec.robot, spec.part) in seen:
                continue
            seen.add((spec.robot, spec.part))
            if spec.part == "base":
                out[_topic(rig, spec.robot, BASE_SENT)] = (vector, "*base")
                continue
            field = "positions" if spec.part == "joints" else "opening"
            out[_topic(rig, spec.robot, stream_of[spec.part])] = (vector, field)
    return out


def _stream_policies(
    streams: Mapping[str, StreamData], extra: EpisodeExtra, policy: Mapping[str, Policy]
) -> dict[str, StreamPolicy]:
    rates: dict[str, float] = {}
    for entry in extra.streams:
        name, hz = entry.get("name"), entry.get("expected_hz")
        if isinstance(name, str) and isinstance(hz, int | float) and hz > 0:
            rates[name] = float(hz)
    out: dict[str, StreamPolicy] = {}
    for topic, data in streams.items():
        hz = rates.get(topic)
        if hz is None and data.time_ns.size > 1:
            hz = 1e9 / float(np.median(np.diff(data.time_ns)) or 1.0)
        tolerance = max(_MIN_TOLERANCE_MS, _PERIODS_OF_TOLERANCE * 1e3 / hz) if hz else _MIN_TOLERANCE_MS
        out[topic] = StreamPolicy(policy.get(stream_of(topic), "nearest"), tolerance)
    return out


def _filled(stream: AlignedStream, field: str, episode_id: str) -> Float64Array:
    """Field values at every frame, frames without a valid sample taking the nearest valid one."""
    if field == "*base":
        values = np.stack([stream.fields[f] for f in _BASE_FIELDS], axis=-1)
    else:
        values = np.asarray(stream.fields[field], dtype=np.float64)
    good = stream.valid & np.all(np.isfinite(values.reshape(values.shape[0], -1)), axis=1)
    if not good.any():
        raise ExportError(
            f"episode {episode_id}: {_source(stream.topic)} has no sample within "
            f"{stream.tolerance_ms:g} ms of any frame; check the episode's sync gate"
        )
    idx = np.arange(good.size)
    last = np.maximum.accumulate(np.where(good, idx, -1))
    first_good = int(np.argmax(good))
    src = np.where(last >= 0, last, first_good)
    return np.asarray(values[src], dtype=np.float64)


def _error_ms(stream: AlignedStream) -> Float32Array:
    return np.where(stream.error_ns >= 0, stream.error_ns / 1e6, np.nan).astype(np.float32)


def _raw_times(stream: AlignedStream, data: StreamData) -> Int64Array:
    idx = stream.source_index
    return np.where(idx >= 0, data.time_ns[np.clip(idx, 0, max(data.time_ns.size - 1, 0))], -1).astype(
        np.int64
    )


def _camera_track(
    episode_dir: Path,
    manifest: EpisodeManifest,
    spec: CameraSpec,
    frames: StreamData,
    grid: Int64Array,
    fps: int,
) -> CameraTrack:
    times = frames.time_ns
    if times.size == 0:
        raise ExportError(f"episode {manifest.id}: camera {spec.key} recorded no frame")
    right = np.clip(np.searchsorted(times, grid), 0, times.size - 1)
    left = np.clip(right - 1, 0, times.size - 1)
    nearer = np.where(np.abs(times[left] - grid) <= np.abs(times[right] - grid), left, right)
    video_index = frames.fields["frame_index"].astype(np.int64)[nearer]
    error = (np.abs(times[nearer] - grid) / 1e6).astype(np.float32)
    return CameraTrack(
        spec,
        episode_dir / "cameras" / f"{spec.key}.mp4",
        video_index,
        error,
        _one_to_one(video_index, error, fps, spec),
    )


def _one_to_one(video_index: Int64Array, error_ms: Float32Array, fps: int, spec: CameraSpec) -> bool:
    return bool(
        spec.fps == fps
        and np.array_equal(video_index, np.arange(video_index.size))
        and (error_ms.size == 0 or float(error_ms.max()) <= 1e3 / (2 * fps))
    )


def _camera_raw(frames: StreamData, video_index: Int64Array) -> Int64Array:
    by_index = dict(
        zip(frames.fields["frame_index"].astype(np.int64).tolist(), frames.time_ns.tolist(), strict=True)
    )
    return np.array([by_index.get(int(i), -1) for i in video_index], dtype=np.int64)


def _keep_mask(grid: Int64Array, start_ns: int, trim_s: Sequence[tuple[float, float]]) -> BoolArray:
    keep = np.ones(grid.size, dtype=np.bool_)
    offset_ns = grid - start_ns
    for start, end in trim_s:
        if not (math.isfinite(start) and math.isfinite(end)) or end < start:
            raise ExportError(
                f"idle span [{start}, {end}) s is not a span; it must be finite with end >= start"
            )
        # Compared in whole nanoseconds: in float seconds, a frame on a span's end (a whole second
        # after its start, say) fell inside or outside by the last bit of the episode's offsets.
        keep &= ~((offset_ns >= round(start * 1e9)) & (offset_ns < round(end * 1e9)))
    return keep


def _trimmed(track: CameraTrack, keep: BoolArray, fps: int) -> CameraTrack:
    if keep.all():
        return track
    index, error = track.source_index[keep], track.error_ms[keep]
    return CameraTrack(track.spec, track.path, index, error, _one_to_one(index, error, fps, track.spec))


# --- topics --------------------------------------------------------------------------------------


def _topic(rig: str, node: str, stream: str) -> str:
    return str(Topic(rig, node, stream))


def _source(topic: str) -> str:
    """``arm0/joint_state`` from ``telerig/v1/<rig>/arm0/joint_state``."""
    try:
        parsed = Topic.parse(topic)
    except ValueError:
        return topic
    return f"{parsed.node}/{parsed.stream}"
