"""``telerig view``: an episode (or an exported dataset) as a Rerun recording (``.rrd``) to look at.

What one episode becomes, on the timeline ``capture_time`` (the common-clock capture time of each
sample, as the recorder stamped it):

- ``cameras/<key>``: the recorded MP4 as an :class:`rerun.AssetVideo` (the file's bytes, not
  re-encoded), with one :class:`rerun.VideoFrameReference` per recorded frame at that frame's capture
  time (the video's pts are capture times relative to its first frame, so the two agree exactly);
- ``robots/<robot>/joints/<joint>/{requested,sent,measured}``: one scalar series per joint and
  kind (the IK's requested command, the command the safety chain sent, the measured joint state);
  ``robots/<robot>/gripper/{requested,sent,measured}`` the gripper opening; ``robots/<robot>/residual``
  the IK position residual [m]; ``robots/<robot>/wrench/...`` the measured force [N] and torque [N m]
  components and the force's norm, where the robot records a wrench;
- ``robots/<robot>/ee_path``: the end effector's path (a 3D line strip, robot base frame [m]) and
  ``robots/<robot>/ee`` its position over time, by forward kinematics of the measured joint
  positions through the robot's model (:func:`telerig.robots.models.arm.build_arm_kinematics`);
  robots without an arm model get none (one note);
- ``qa/<gate>``: the quality-gate verdicts of the episode's ``qa.json`` (:mod:`telerig.store.qa_file`:
  value, threshold, detail), each a text marker at the events the gate names (where each violation
  begins; at the first sample when it names none), warnings for failed gates; ``qa/idle_segments``
  the idle stretches; ``events/safety`` the safety log of the manifest.

Nothing is shown: the stream is saved to a file (no viewer spawned, no network); open it with
``rerun FILE.rrd``. The MCAP episode log itself stays what it is and keeps opening in Foxglove.
"""

from __future__ import annotations

import math
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from telerig.bus.topics import Topic
from telerig.errors import ExportError, RecordingError, TelerigError
from telerig.export.view_base import ViewSummary, end_effector_path
from telerig.ir.mcap_log import read_log, read_residuals
from telerig.ir.types import CameraFrame, GripperCommand, JointCommand, JointState, Wrench
from telerig.store.episodes import EpisodeManifest, EpisodeStore
from telerig.store.qa_file import QA_FILE, read_qa

__all__ = [
    "QA_FILE",
    "TIMELINE",
    "ViewSummary",
    "end_effector_path",
    "resolve_source",
    "view",
    "view_episode",
]

#: The timeline every entity is logged on: capture time, common clock.
TIMELINE = "capture_time"
_APPLICATION_ID = "telerig"
_JOINT_KINDS = {
    "joint_command_requested": "requested",
    "joint_command_sent": "sent",
    "joint_state": "measured",
}
_GRIPPER_KINDS = {
    "gripper_command_requested": "requested",
    "gripper_command_sent": "sent",
    "gripper_state": "measured",
}

#: Entities of a wrench (F/T) stream under ``robots/<robot>/wrench/``: components and the force's norm.
_WRENCH = ("force_x", "force_y", "force_z", "torque_x", "torque_y", "torque_z", "force_norm")

Int64Array = npt.NDArray[np.int64]
Float64Array = npt.NDArray[np.float64]


def resolve_source(source: str | Path, data_root: Path) -> Path:
    """The episode directory of an episode id or directory, or an export directory.

    Raises:
        ExportError: ``source`` is none of them.
    """
    path = Path(source)
    if path.is_dir() and ((path / "manifest.json").is_file() or _is_dataset(path)):
        return path
    name = str(source)
    if "/" not in name:
        store = EpisodeStore(data_root)
        try:
            return store.episode_dir(name)
        except TelerigError as exc:
            raise ExportError(
                f"{name!r} is neither an episode of {data_root} nor an episode or dataset directory "
                f"({exc}); pass --data-root or a path"
            ) from None
    raise ExportError(
        f"{source} is neither an episode directory (manifest.json) nor an export directory "
        "(robot_schema.json); pass an episode id with --data-root, or a path"
    )


def view(
    source: str | Path, out: Path | None = None, *, data_root: Path = Path("telerig-data")
) -> ViewSummary:
    """Write the Rerun recording of an episode (id or directory) or of an export directory.

    Args:
        source: Episode id (looked up under ``data_root``), episode directory, or export directory.
        out: The ``.rrd`` to write; default ``<source name>.rrd`` in the current directory.
        data_root: Where episode ids are looked up.

    Raises:
        ExportError: the source is not found or not readable; one line.
    """
    path = resolve_source(source, data_root)
    out = Path(out) if out is not None else Path(f"{path.name}.rrd")
    if _is_dataset(path):
        from telerig.export.view_dataset import view_dataset  # reads the formats' files

        return view_dataset(path, out)
    return view_episode(path, out)


def _is_dataset(path: Path) -> bool:
    from telerig.export.view_dataset import dataset_format

    try:
        dataset_format(path)
    except ExportError:
        return False
    return True


# --- one episode ---------------------------------------------------------------------------------


@dataclass(slots=True)
class _Series:
    """Samples of one stream: capture times [ns] and one row of values per sample."""

    names: tuple[str, ...] = ()
    t_ns: list[int] = field(default_factory=list)
    rows: list[npt.NDArray[np.float64]] = field(default_factory=list)

    def arrays(self) -> tuple[Int64Array, Float64Array]:
        t = np.asarray(self.t_ns, dtype=np.int64)
        width = max((len(r) for r in self.rows), default=0)
        values = np.full((len(self.rows), width), np.nan)
        for i, row in enumerate(self.rows):
            values[i, : len(row)] = row
        return t, values


@dataclass(slots=True)
class _Episode:
    joints: dict[tuple[str, str], _Series] = field(default_factory=lambda: defaultdict(_Series))
    grippers: dict[tuple[str, str], _Series] = field(default_factory=lambda: defaultdict(_Series))
    frames: dict[str, list[tuple[int, int]]] = field(default_factory=lambda: defaultdict(list))
    residual: dict[str, _Series] = field(default_factory=lambda: defaultdict(_Series))
    wrench: dict[str, _Series] = field(default_factory=lambda: defaultdict(_Series))


def _read_episode(mcap: Path) -> _Episode:
    episode = _Episode()
    for entry in read_log(mcap):
        try:
            topic = Topic.parse(entry.topic)
        except ValueError:
            continue
        sample = entry.sample
        if isinstance(sample, (JointState, JointCommand)) and topic.stream in _JOINT_KINDS:
            series = episode.joints[(topic.node, _JOINT_KINDS[topic.stream])]
            series.names = series.names or sample.names
            series.t_ns.append(sample.stamp.capture_ns)
            series.rows.append(_reorder(sample.positions, sample.names, series.names))
        elif isinstance(sample, GripperCommand) and topic.stream in _GRIPPER_KINDS:
            series = episode.grippers[(topic.node, _GRIPPER_KINDS[topic.stream])]
            series.t_ns.append(sample.stamp.capture_ns)
            series.rows.append(np.array([sample.opening]))
        elif isinstance(sample, JointState) and topic.stream in _GRIPPER_KINDS:  # a gripper's state
            series = episode.grippers[(topic.node, _GRIPPER_KINDS[topic.stream])]
            series.t_ns.append(sample.stamp.capture_ns)
            series.rows.append(np.asarray(sample.positions[:1], dtype=np.float64))
        elif isinstance(sample, Wrench):
            series = episode.wrench[topic.node]
            series.t_ns.append(sample.stamp.capture_ns)
            series.rows.append(np.concatenate([sample.force, sample.torque, [np.linalg.norm(sample.force)]]))
        elif isinstance(sample, CameraFrame):
            episode.frames[sample.camera_id].append((sample.frame_index, sample.stamp.capture_ns))
    for name, residual, _ in read_residuals(mcap):  # typed, or the JSON of earlier episodes
        try:
            topic = Topic.parse(name)
        except ValueError:
            continue
        err = residual.get("position_error_m")
        if not math.isnan(err):
            series = episode.residual[topic.node]
            series.t_ns.append(residual.stamp.capture_ns)
            series.rows.append(np.array([err]))
    return episode


def _reorder(
    values: npt.NDArray[np.float64], names: tuple[str, ...], order: tuple[str, ...]
) -> npt.NDArray[np.float64]:
    if names == order:
        return np.asarray(values, dtype=np.float64)
    index = {n: i for i, n in enumerate(names)}
    return np.array([values[index[n]] if n in index else math.nan for n in order])


def view_episode(episode_dir: Path, out: Path) -> ViewSummary:
    """Write ``out`` (``.rrd``) for the episode in ``episode_dir``; see the module docstring.

    Raises:
        ExportError: the episode has no manifest or no MCAP log; one line.
    """
    import rerun as rr

    manifest_path = episode_dir / "manifest.json"
    if not manifest_path.is_file():
        raise ExportError(f"{episode_dir} has no manifest.json: not an episode directory")
    manifest = EpisodeManifest.model_validate_json(manifest_path.read_text())
    mcap = episode_dir / "episode.mcap"
    if not mcap.is_file():
        raise ExportError(f"episode {manifest.id} has no episode.mcap")
    episode = _read_episode(mcap)

    summary = ViewSummary(out=out, source=manifest.id)
    out.parent.mkdir(parents=True, exist_ok=True)
    rec = rr.RecordingStream(_APPLICATION_ID, recording_id=manifest.id, send_properties=True)
    rec.save(out)
    try:
        rec.send_recording_name(f"{manifest.id} · {manifest.rig} · {manifest.task or 'no task'}")
        _log_episode(rec, episode_dir, manifest, episode, summary)
        rec.flush()
    finally:
        rec.disconnect()
    return summary


def _time(t_ns: Int64Array) -> Any:
    import rerun as rr

    return rr.TimeColumn(TIMELINE, timestamp=t_ns.astype("datetime64[ns]"))


def _log_episode(
    rec: Any, episode_dir: Path, manifest: EpisodeManifest, episode: _Episode, summary: ViewSummary
) -> None:
    import rerun as rr

    rec.log(
        "episode",
        rr.TextDocument(_describe(manifest), media_type=rr.MediaType.MARKDOWN),
        static=True,
    )
    summary.entities["episode"] = 1
    _log_videos(rec, episode_dir, manifest, episode, summary)
    for (robot, kind), series in sorted(episode.joints.items()):
        t, values = series.arrays()
        for j, joint in enumerate(series.names):
            path = f"robots/{robot}/joints/{joint}/{kind}"
            _scalars(rec, path, kind, t, values[:, j], summary)
    for (robot, kind), series in sorted(episode.grippers.items()):
        t, values = series.arrays()
        _scalars(rec, f"robots/{robot}/gripper/{kind}", kind, t, values[:, 0], summary)
    for robot, series in sorted(episode.residual.items()):
        t, values = series.arrays()
        _scalars(rec, f"robots/{robot}/residual", "IK position residual [m]", t, values[:, 0], summary)
    for robot, series in sorted(episode.wrench.items()):
        t, values = series.arrays()
        for j, name in enumerate(_WRENCH):
            _scalars(rec, f"robots/{robot}/wrench/{name}", name, t, values[:, j], summary)
    models = _robot_models(manifest)
    for (robot, kind), series in sorted(episode.joints.items()):
        if kind == "measured":
            _log_ee_path(rec, robot, models.get(robot), series, summary)
    _log_qa(rec, episode_dir, manifest, episode, summary)
    _log_safety(rec, manifest, summary)


def _describe(manifest: EpisodeManifest) -> str:
    extra = manifest.extra
    lines = [
        f"# {manifest.id}",
        f"- rig: {manifest.rig}",
        f"- task: {manifest.task or '-'}",
        f"- operator: {manifest.operator or '-'}",
        f"- status: {manifest.status}" + (f" ({manifest.reason})" if manifest.reason else ""),
        f"- duration: {manifest.duration_s:.2f} s" if manifest.duration_s is not None else "- duration: -",
        f"- outcome: {extra.get('outcome') or '-'}",
        f"- quality: {extra.get('quality') if extra.get('quality') is not None else '-'}",
    ]
    return "\n".join(lines) + "\n"


def _scalars(
    rec: Any, path: str, name: str, t: Int64Array, values: Float64Array, summary: ViewSummary
) -> None:
    import rerun as rr

    keep = np.isfinite(values)
    if not keep.any():
        return
    rec.log(path, rr.SeriesLines(names=name), static=True)
    rec.send_columns(path, indexes=[_time(t[keep])], columns=rr.Scalars.columns(scalars=values[keep]))
    summary.entities[path] = int(keep.sum())


def _log_videos(
    rec: Any, episode_dir: Path, manifest: EpisodeManifest, episode: _Episode, summary: ViewSummary
) -> None:
    import rerun as rr

    cameras = manifest.extra.get("cameras")
    files: dict[str, Path] = {}
    if isinstance(cameras, dict):
        for key, record in cameras.items():
            if isinstance(record, dict) and isinstance(record.get("file"), str):
                files[key] = episode_dir / str(record["file"])
    for entry in manifest.files:  # cameras/<key>.mp4 listed but not in extra (older manifests)
        p = Path(entry.path)
        if p.parts[0] == "cameras" and p.suffix == ".mp4":
            files.setdefault(p.stem, episode_dir / p)
    for key, path in sorted(files.items()):
        if not path.is_file():
            summary.notes.append(f"camera {key}: {path.name} is missing")
            continue
        video = rr.AssetVideo(path=path)
        pts_ns = np.asarray(video.read_frame_timestamps_nanos(), dtype=np.int64)
        entity = f"cameras/{key}"
        rec.log(entity, video, static=True)
        records = [(i, t) for i, t in episode.frames.get(key, []) if 0 <= i < len(pts_ns)]
        if not records or not len(pts_ns):
            summary.notes.append(f"camera {key}: no frame records in the MCAP log; video not on the timeline")
            continue
        # The video's pts are capture times relative to its first frame (the encoder's rule), so
        # every frame's capture time is known even where its frame record did not reach the log.
        offsets = np.array([t - pts_ns[i] for i, t in records], dtype=np.int64)
        capture = int(np.median(offsets)) + pts_ns
        if len(records) != len(pts_ns):
            summary.notes.append(
                f"camera {key}: {len(pts_ns)} video frames, {len(records)} frame records in the MCAP "
                "log; every video frame shown at its capture time from the video's pts"
            )
        rec.send_columns(
            entity,
            indexes=[_time(capture)],
            columns=rr.VideoFrameReference.columns_nanos(pts_ns),
        )
        summary.entities[entity] = len(pts_ns)
        summary.video = "asset"


def _robot_models(manifest: EpisodeManifest) -> dict[str, str]:
    """Robot id → model name, from the manifest's robot joints record or its fingerprint."""
    models: dict[str, str] = {}
    joints = manifest.extra.get("robot_joints")
    if isinstance(joints, dict):
        for robot, record in joints.items():
            if isinstance(record, dict) and isinstance(record.get("model"), str):
                models[robot] = str(record["model"])
    fingerprint = manifest.extra.get("fingerprint")
    components = fingerprint.get("components") if isinstance(fingerprint, dict) else None
    if isinstance(components, dict):
        for name, value in components.items():
            parts = name.split(" ")
            if len(parts) == 2 and parts[0] == "robot" and isinstance(value, str) and " " in value:
                models.setdefault(parts[1], value.split(" ")[-1])
    return models


def _log_ee_path(rec: Any, robot: str, model: str | None, series: _Series, summary: ViewSummary) -> None:
    import rerun as rr

    from telerig.robots.models import ARM_MODELS

    if model is None or model not in ARM_MODELS:
        summary.notes.append(
            f"robot {robot}: no end-effector path (model {model or 'unknown'} is not an arm model)"
        )
        return
    t, q = series.arrays()
    path = end_effector_path(model, series.names, q)
    keep = np.all(np.isfinite(path), axis=1)
    t, path = t[keep], path[keep]
    if len(path) == 0:
        return
    strip = f"robots/{robot}/ee_path"
    rec.log(strip, rr.LineStrips3D([path], radii=0.002), static=True)
    summary.entities[strip] = 1
    point = f"robots/{robot}/ee"
    rec.send_columns(point, indexes=[_time(t)], columns=rr.Points3D.columns(positions=path))
    summary.entities[point] = len(path)


# --- quality gates and safety events -------------------------------------------------------------


def _fmt(value: Any) -> str:
    return f"{value:.4g}" if isinstance(value, float) else str(value)


def _log_qa(
    rec: Any, episode_dir: Path, manifest: EpisodeManifest, episode: _Episode, summary: ViewSummary
) -> None:
    """One text marker per gate verdict of the episode's qa.json (:mod:`telerig.store.qa_file`) at
    each event it names (seconds from the episode start), or at the first sample when it names none;
    one per idle segment the gates found."""
    import rerun as rr

    try:
        record = read_qa(episode_dir)
    except RecordingError as exc:
        summary.notes.append(f"no gate markers: {exc}")
        return
    if record is None:
        return
    first = _first_time(manifest, episode)
    start = int(manifest.start_ns)
    rows = record.report.get("verdicts")
    for row in rows if isinstance(rows, list) else []:
        if not isinstance(row, dict) or not isinstance(row.get("gate"), str):
            continue
        gate, passed = str(row["gate"]), row.get("passed")
        verdict = "pass" if passed is True else "FAIL" if passed is False else "n/a"
        unit = f" {row['unit']}" if row.get("unit") else ""
        value = "-" if row.get("value") is None else f"{_fmt(row.get('value'))}{unit}"
        threshold = "-" if row.get("threshold") is None else f"{_fmt(row.get('threshold'))}{unit}"
        text = f"{gate}: {verdict}, value {value} (threshold {threshold})" + (
            f": {row['detail']}" if row.get("detail") else ""
        )
        events = row.get("events")
        seconds = (
            [float(e) for e in events if isinstance(e, (int, float))] if isinstance(events, list) else []
        )
        times = [start + round(e * 1e9) for e in seconds] or [first]
        level = rr.TextLogLevel.WARN if passed is False else rr.TextLogLevel.INFO
        path = f"qa/{gate}"
        rec.send_columns(
            path,
            indexes=[_time(np.asarray(times, dtype=np.int64))],
            columns=rr.TextLog.columns(text=[text] * len(times), level=[level] * len(times)),
        )
        summary.entities[path] = len(times)
    segments = record.report.get("idle_segments")
    spans: list[tuple[float, float]] = []
    for seg in segments if isinstance(segments, list) else []:
        if isinstance(seg, list) and len(seg) == 2:
            a, b = seg
            if isinstance(a, (int, float)) and isinstance(b, (int, float)):
                spans.append((float(a), float(b)))
    if spans:
        rec.send_columns(
            "qa/idle_segments",
            indexes=[_time(np.array([start + round(a * 1e9) for a, _ in spans], dtype=np.int64))],
            columns=rr.TextLog.columns(
                text=[f"idle for {b - a:.2f} s (until t={b:.2f} s)" for a, b in spans],
                level=[rr.TextLogLevel.DEBUG] * len(spans),
            ),
        )
        summary.entities["qa/idle_segments"] = len(spans)


def _first_time(manifest: EpisodeManifest, episode: _Episode) -> int:
    starts = [s.t_ns[0] for s in episode.joints.values() if s.t_ns]
    starts += [f[0][1] for f in episode.frames.values() if f]
    return min(starts) if starts else int(manifest.start_ns)


def _log_safety(rec: Any, manifest: EpisodeManifest, summary: ViewSummary) -> None:
    import rerun as rr

    log = manifest.extra.get("safety_log")
    events = log if isinstance(log, list) else []
    rows: list[tuple[int, str]] = []
    for e in events:
        t_ns = e.get("t_ns") if isinstance(e, dict) else None
        if isinstance(e, dict) and isinstance(t_ns, int):
            rows.append((t_ns, f"{e.get('robot') or 'rig'}: {e.get('code')} {e.get('reason') or ''}".strip()))
    if not rows:
        return
    t = np.array([r[0] for r in rows], dtype=np.int64)
    rec.send_columns(
        "events/safety",
        indexes=[_time(t)],
        columns=rr.TextLog.columns(text=[r[1] for r in rows], level=[rr.TextLogLevel.WARN] * len(rows)),
    )
    summary.entities["events/safety"] = len(rows)
