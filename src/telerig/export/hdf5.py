"""HDF5 export (seed 004 step 4): one self-describing file per episode, ``<out>/episodes/<id>.hdf5``.

Layout of one episode file (F frames on the dataset grid, S state and A action entries)::

    /                        attrs: format, format_version, episode_id, schema_file
    /observations/state      float32 (F, S)        attrs: names (joint names, in order), parts (JSON)
    /observations/images/<camera>  uint8 (F, H, W, 3) RGB, one chunk per frame, gzip level 1
    /observations/timestamp  float64 (F,)  [s] from the first frame, exactly k / fps
    /observations/frame_ns   int64 (F,)    grid time of each frame, common clock [ns]
    /actions                 float32 (F, A)        attrs: names, parts (JSON)
    /metadata                attrs: rig, fingerprint, fps, task, operator, outcome, quality, ...
    /metadata/schema         JSON text: the dataset's joint order and limits (= robot_schema.json)
    /metadata/manifest       JSON text: the episode's manifest (streams, clock, safety log, and
                             the calibration once the recorder stores one: none does today)
    /metadata/rates, gates, fingerprint_components   JSON text
    /debug/valid             bool (F,)  every stream and camera within its tolerance at that frame
    /debug/alignment_error_ms/<node>/<stream>  float32 (F,) [ms]; NaN where the stream had none
    /debug/raw_time_ns/<node>/<stream>         int64 (F,) capture time of the sample used; -1 none
    /debug/camera_source_index/<camera>        int64 (F,) recorded video frame used at each frame
    /debug/residual/<robot>/...                the IK residual per control tick (native rate)
    /language/subtask        utf-8 (F,)  the active segment's label per frame, "" where none
    /language/instruction    utf-8 (F,)  its description (else "label: task"), the task where none
    /language                attrs: segments (JSON: id, label, start_s, end_s on the video's
                             timeline, confidence, source, status, description); only for an
                             episode with a ``segments.json`` (see :mod:`telerig.export.language`)

``<out>/robot_schema.json`` is the joint-order file every export writes; each episode file names it
(``schema_file``, relative to the file) and embeds the same JSON, so a file copied alone still says
what its columns are.

Crash safety: an episode file is written under ``<out>/.tmp-<pid>/`` and renamed into
``episodes/`` once closed and synced, so a killed export leaves only whole episode files.
"""

from __future__ import annotations

import json
import os
import shutil
import zlib
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import h5py
import numpy as np
import numpy.typing as npt
from pydantic import JsonValue

from telerig.bus.topics import Topic
from telerig.errors import ExportError, RecordingError
from telerig.export.base import ValidationReport, write_atomic
from telerig.export.frames import CameraTrack, EpisodeFrames
from telerig.export.schema import SCHEMA_FILE, DatasetSchema, Vector
from telerig.ir.mcap_log import read_residuals
from telerig.ir.types import RetargetResidual
from telerig.store.manifest_extra import EpisodeExtra

if TYPE_CHECKING:
    from telerig.export.config import Hdf5ExportConfig

__all__ = [
    "CHANNEL_ORDER",
    "COMPRESS_THREADS",
    "EPISODES_DIR",
    "FORMAT",
    "FORMAT_VERSION",
    "IMAGE_COMPRESSION",
    "IMAGE_COMPRESSION_LEVEL",
    "Hdf5Exporter",
    "episode_gates",
    "write_episode_file",
]

#: ``format`` attribute of every episode file, and its layout version.
FORMAT = "telerig-hdf5"
FORMAT_VERSION = 1
#: Folder of the episode files inside the dataset directory.
EPISODES_DIR = "episodes"
#: Channel order of every image dataset (HDF5 image spec: ``IMAGE_TRUECOLOR``, pixel interlace).
CHANNEL_ORDER = "RGB"
#: Image compression. Measured on the demo rig's 640x480 MuJoCo frames (149 frames, 137 MB raw,
#: one chunk per frame, loaded 2-core host): gzip 1 wrote 89-93 frames/s at 8.8x smaller, lzf 54-71
#: frames/s at 6.3x, gzip 4 35-54 frames/s at 10.1x, gzip 6 30 frames/s at 10.8x; gzip also opens
#: in every HDF5 reader (lzf only where h5py's filter is installed).
IMAGE_COMPRESSION = "gzip"
IMAGE_COMPRESSION_LEVEL = 1
#: Threads deflating image chunks (a pinned single core gets no faster; a workstation does).
COMPRESS_THREADS = max(1, min(4, len(os.sched_getaffinity(0))))

#: Metadata attributes every episode file has (``validate`` checks them).
_REQUIRED_METADATA = ("rig", "fingerprint", "fps", "task", "operator", "episode_id", "start_ns")
_REQUIRED_METADATA_TEXT = ("schema", "manifest", "rates", "gates")

AnyArray = npt.NDArray[Any]


class Hdf5Exporter:
    """Writes and validates the per-episode HDF5 dataset (exporter ``hdf5``)."""

    format: ClassVar[str] = "hdf5"

    def __init__(self, config: Hdf5ExportConfig) -> None:
        self.config = config

    def schema_path(self, out: Path) -> Path:
        """``<out>/robot_schema.json``."""
        return Path(out) / SCHEMA_FILE

    def existing_episodes(self, out: Path) -> set[str]:
        """Episode ids with a file in ``<out>/episodes/`` (only whole files are ever there)."""
        folder = Path(out) / EPISODES_DIR
        return {p.stem for p in folder.glob("*.hdf5")} if folder.is_dir() else set()

    def write(
        self,
        out: Path,
        schema: DatasetSchema,
        episodes: Iterable[EpisodeFrames],
        progress: Callable[[EpisodeFrames], None],
    ) -> int:
        """Write one file per episode (appending to the dataset at ``out``); return the frames written.

        Raises:
            ExportError: An episode's video cannot be decoded, or the disk refused a write.
        """
        out = Path(out)
        folder = out / EPISODES_DIR
        folder.mkdir(parents=True, exist_ok=True)
        # The schema goes first: every episode file names it. An existing dataset's schema is the same
        # (export() refused any other), so rewriting it changes nothing a reader sees.
        write_atomic(self.schema_path(out), schema.dumps())
        frames = 0
        with scratch_dir(out) as tmp:
            for episode in episodes:
                part = tmp / f"{episode.episode_id}.hdf5"
                write_episode_file(part, episode)
                os.replace(part, folder / part.name)
                fsync_dir(folder)
                frames += episode.length
                progress(episode)
        return frames

    def validate(self, out: Path) -> ValidationReport:
        """Re-read every episode file: columns and joint order against ``robot_schema.json``, image
        shapes and channel order, lengths, monotonic timestamps, metadata present."""
        out = Path(out)
        try:
            schema = DatasetSchema.loads(self.schema_path(out).read_bytes())
        except FileNotFoundError:
            return ValidationReport(0, 0, (f"{SCHEMA_FILE} is missing; re-run the export",))
        except ExportError as exc:
            return ValidationReport(0, 0, (str(exc),))
        files = sorted((out / EPISODES_DIR).glob("*.hdf5"))
        if not files:
            return ValidationReport(0, 0, (f"{EPISODES_DIR}/ holds no episode file; re-run the export",))
        problems: list[str] = []
        frames = 0
        for path in files:
            where = f"{EPISODES_DIR}/{path.name}"
            try:
                with h5py.File(path, "r") as f:
                    found, length = _check_episode_file(f, schema, path.stem)
            except (OSError, KeyError, ValueError, ExportError) as exc:
                found, length = [f"cannot read it ({exc}); delete it and re-run the export"], 0
            problems += [f"{where}: {p}" for p in found]
            frames += length
        return ValidationReport(len(files), frames, tuple(problems))


# --- writing one episode -------------------------------------------------------------------------


def write_episode_file(path: Path, episode: EpisodeFrames) -> None:
    """Write ``episode`` as one HDF5 file at ``path`` (synced to disk before it returns).

    Raises:
        ExportError: The video cannot be decoded, or the file cannot be written.
    """
    schema = episode.schema
    try:
        with h5py.File(path, "w") as f:
            f.attrs["format"] = FORMAT
            f.attrs["format_version"] = FORMAT_VERSION
            f.attrs["episode_id"] = episode.episode_id
            f.attrs["schema_file"] = f"../{SCHEMA_FILE}"
            obs = f.create_group("observations")
            _vector(obs, "state", episode.state, schema, "state")
            obs.create_dataset("timestamp", data=episode.timestamp).attrs["unit"] = "s"
            obs.create_dataset("frame_ns", data=episode.frame_ns).attrs["unit"] = "ns"
            images = obs.create_group("images")
            for key, track in episode.cameras.items():
                write_images(images, key, track, episode.length)
            _vector(f, "actions", episode.action, schema, "action")
            _metadata(f.create_group("metadata"), episode)
            _debug(f.create_group("debug"), episode)
            write_language(f, episode)
        with open(path, "rb") as synced:
            os.fsync(synced.fileno())
    except OSError as exc:
        raise ExportError(
            f"{path}: cannot write the episode file ({exc}); free disk space and re-run"
        ) from None


def write_images(group: Any, name: str, track: CameraTrack, length: int) -> Any:
    """Decode ``track`` into ``group[name]``: uint8 (F, H, W, 3) RGB, one gzip-compressed chunk per
    frame, written frame by frame (one episode's images are never all in memory).

    Raises:
        ExportError: The video yields frames of another size than the schema, or too few.
    """
    spec = track.spec
    data = group.create_dataset(
        name,
        shape=(length, *spec.shape),
        dtype=np.uint8,
        chunks=(1, *spec.shape),
        compression=IMAGE_COMPRESSION,
        compression_opts=IMAGE_COMPRESSION_LEVEL,
    )
    data.attrs["CLASS"] = np.bytes_("IMAGE")
    data.attrs["IMAGE_SUBCLASS"] = np.bytes_("IMAGE_TRUECOLOR")
    data.attrs["INTERLACE_MODE"] = np.bytes_("INTERLACE_PIXEL")
    data.attrs["channel_order"] = CHANNEL_ORDER
    data.attrs["camera_fps"] = spec.fps
    data.attrs["codec"] = spec.codec
    # Chunks are deflated here (zlib: the stream HDF5's gzip filter reads) and written raw, so that
    # - a recorded frame filling several dataset frames (a camera behind the dataset rate: 14.7 fps
    #   against 30 on the loaded test host, half the frames) is compressed once, not once per frame;
    # - frames compress on COMPRESS_THREADS threads (zlib releases the GIL) while the next decode.
    count = 0
    pending: deque[tuple[int, Future[bytes]]] = deque()
    previous: tuple[int, Future[bytes]] | None = None
    with ThreadPoolExecutor(COMPRESS_THREADS, thread_name_prefix="hdf5-deflate") as pool:
        for count, image in enumerate(track.frames(), start=1):
            if image.shape != spec.shape:
                raise ExportError(
                    f"{track.path}: frame of shape {image.shape}, the camera's is {spec.shape}; "
                    "the video does not match its manifest: run `telerig repair`"
                )
            source = int(track.source_index[count - 1])
            if previous is None or previous[0] != source:
                previous = (source, pool.submit(_deflate, image))
            pending.append((count - 1, previous[1]))
            while len(pending) > 2 * COMPRESS_THREADS:
                _write_chunk(data, *pending.popleft())
        while pending:
            _write_chunk(data, *pending.popleft())
    if count != length:
        raise ExportError(
            f"{track.path}: {count} frames decoded for {length} dataset frames; run `telerig repair`"
        )
    return data


def _deflate(image: AnyArray) -> bytes:
    return zlib.compress(np.ascontiguousarray(image, dtype=np.uint8).data, IMAGE_COMPRESSION_LEVEL)


def _write_chunk(data: Any, index: int, chunk: Future[bytes]) -> None:
    data.id.write_direct_chunk((index, 0, 0, 0), chunk.result())


def _vector(group: Any, name: str, values: AnyArray, schema: DatasetSchema, vector: Vector) -> None:
    data = group.create_dataset(name, data=values.astype(np.float32, copy=False))
    data.attrs["names"] = list(schema.names(vector))
    data.attrs["parts"] = json.dumps({k: list(v) for k, v in schema.parts(vector).items()})
    data.attrs["normalized"] = schema.normalized


def _metadata(group: Any, episode: EpisodeFrames) -> None:
    manifest, schema = episode.manifest, episode.schema
    extra = episode.extra
    attrs = group.attrs
    attrs["episode_id"] = episode.episode_id
    attrs["rig"] = manifest.rig
    attrs["fingerprint"] = schema.fingerprint
    attrs["fps"] = schema.fps
    attrs["task"] = episode.task
    attrs["operator"] = manifest.operator
    attrs["station"] = extra.station or ""
    attrs["start_ns"] = manifest.start_ns
    attrs["duration_s"] = float("nan") if manifest.duration_s is None else manifest.duration_s
    attrs["outcome"] = episode.outcome or ""
    attrs["quality"] = float("nan") if episode.quality is None else episode.quality
    attrs["passed_qa"] = "" if episode.qa is None else str(episode.qa.passed).lower()
    attrs["normalized"] = schema.normalized
    attrs["schema_file"] = f"../{SCHEMA_FILE}"
    attrs["trimmed_s"] = json.dumps([list(span) for span in episode.trimmed_s])
    _text(group, "schema", schema.dumps())
    _text(group, "manifest", manifest.model_dump_json(indent=1))
    _text(group, "rates", json.dumps(_rates(episode, extra)))
    _text(group, "gates", json.dumps(episode_gates(episode)))
    if extra.fingerprint is not None:
        _text(group, "fingerprint_components", json.dumps(extra.fingerprint.components))


def _rates(episode: EpisodeFrames, extra: EpisodeExtra) -> dict[str, JsonValue]:
    """Dataset rate, camera rates and each recorded stream's expected and measured rate [Hz]."""
    return {
        "dataset_hz": episode.schema.fps,
        "cameras_hz": {c.key: c.fps for c in episode.schema.cameras},
        "streams": list(extra.streams),
    }


def episode_gates(episode: EpisodeFrames) -> dict[str, JsonValue]:
    """The quality gates' verdicts on the episode (its ``qa.json``): ``passed`` (``None`` when its
    gates have not run), ``gates``: gate → passed (``None``: not applicable), ``score`` (the quality
    score's parts) and ``report`` (each verdict's value, threshold, unit and detail)."""
    qa = episode.qa
    if qa is None:
        return {"passed": None, "gates": {}, "score": None, "report": None}
    gates: dict[str, JsonValue] = dict(episode.gates)
    return {"passed": qa.passed, "gates": gates, "score": qa.score, "report": qa.report}


def _debug(group: Any, episode: EpisodeFrames) -> None:
    group.create_dataset("valid", data=episode.valid)
    errors = group.create_group("alignment_error_ms")
    for source, values in episode.alignment_error_ms.items():
        errors.create_dataset(source, data=values.astype(np.float32, copy=False)).attrs["unit"] = "ms"
    raw = group.create_group("raw_time_ns")
    for source, times in episode.raw_time_ns.items():
        raw.create_dataset(source, data=times.astype(np.int64, copy=False)).attrs["unit"] = "ns"
    index = group.create_group("camera_source_index")
    for key, track in episode.cameras.items():
        index.create_dataset(key, data=track.source_index.astype(np.int64, copy=False))
    residuals = group.create_group("residual")
    for robot, columns in episode_residuals(episode).items():
        sub = residuals.create_group(robot)
        for column, values in columns.items():
            sub.create_dataset(column, data=values)


def episode_residuals(episode: EpisodeFrames) -> dict[str, dict[str, AnyArray]]:
    """Robot → the IK residual per control tick at its native rate: ``capture_ns`` (int64, common
    clock [ns]), ``flagged`` (bool) and one float64 column per metric (NaN in ticks without it);
    empty where none was recorded. Typed residuals and the JSON of earlier episodes alike
    (:func:`~telerig.ir.mcap_log.read_residuals`).

    Raises:
        ExportError: The log cannot be read.
    """
    mcap = episode.directory / "episode.mcap"
    rows: dict[str, list[RetargetResidual]] = {}
    try:
        for topic, residual, _ in read_residuals(mcap):
            parsed = Topic.try_parse(topic)
            if parsed is not None:
                rows.setdefault(parsed.node, []).append(residual)
    except RecordingError as exc:
        raise ExportError(f"episode {episode.episode_id}: {exc}") from None
    return {robot: _columns(ticks) for robot, ticks in sorted(rows.items())}


def _columns(ticks: list[RetargetResidual]) -> dict[str, AnyArray]:
    names = sorted({n for t in ticks for n in t.names} - {"capture_ns", "flagged"})
    out: dict[str, AnyArray] = {
        "capture_ns": np.array([t.stamp.capture_ns for t in ticks], dtype=np.int64),
        "flagged": np.array([t.flagged for t in ticks], dtype=np.bool_),
    }
    for name in names:
        out[name] = np.array([t.get(name) for t in ticks], dtype=np.float64)
    return out


def write_language(group: Any, episode: EpisodeFrames) -> None:
    """The ``language`` group (per-frame subtask and instruction, the segments as JSON) under
    ``group``; nothing for an episode without segments (its file stays as before)."""
    lang = episode.language
    if lang is None:
        return
    out = group.create_group("language")
    text = h5py.string_dtype("utf-8")
    out.create_dataset("subtask", data=np.array(lang.subtask, dtype=object), dtype=text)
    out.create_dataset("instruction", data=np.array(lang.instruction, dtype=object), dtype=text)
    segments = [
        {
            "id": s.id,
            "label": s.label,
            "start_s": s.start_s,
            "end_s": s.end_s,
            "confidence": s.confidence,
            "source": s.source,
            "status": s.status,
            "description": lang.descriptions.get(s.id),
        }
        for s in lang.segments
    ]
    out.attrs["segments"] = json.dumps(segments)


def _text(group: Any, name: str, text: str) -> None:
    group.create_dataset(name, data=text, dtype=h5py.string_dtype("utf-8"))


def read_text(group: Any, name: str) -> str:
    """A JSON text dataset written by this module, as ``str``."""
    value = group[name][()]
    return value.decode() if isinstance(value, bytes) else str(value)


# --- validation ----------------------------------------------------------------------------------


def _check_episode_file(f: Any, schema: DatasetSchema, stem: str) -> tuple[list[str], int]:
    """Problems of one episode file against the dataset schema, and its frame count."""
    problems: list[str] = []
    for name in ("observations/state", "observations/timestamp", "actions", "metadata"):
        if name not in f:
            return [f"/{name} is missing; delete the file and re-run the export"], 0
    length = int(f["observations/timestamp"].shape[0])
    if length < 1:
        return ["holds no frame; delete it and re-export the episode untrimmed"], 0
    if f.attrs.get("episode_id") != stem:
        problems.append(f"episode_id attribute {f.attrs.get('episode_id')!r} differs from the file name")
    problems += check_vector(
        f["observations/state"], len(schema.state), length, "observations/state", "joints"
    )
    problems += check_vector(f["actions"], len(schema.action), length, "actions", "DoF")
    problems += check_names(f["observations/state"], schema.state_names, "observations/state")
    problems += check_names(f["actions"], schema.action_names, "actions")
    problems += check_timestamps(f["observations/timestamp"][()], "observations/timestamp")
    images = f.get("observations/images")
    for cam in schema.cameras:
        if images is None or cam.key not in images:
            problems.append(f"/observations/images/{cam.key} is missing (the schema lists camera {cam.key})")
            continue
        problems += check_images(images[cam.key], cam.shape, length, f"observations/images/{cam.key}")
    meta = f["metadata"]
    missing = [k for k in _REQUIRED_METADATA if k not in meta.attrs] + [
        k for k in _REQUIRED_METADATA_TEXT if k not in meta
    ]
    if missing:
        problems.append(f"/metadata lacks {', '.join(missing)}; re-export the episode")
    elif DatasetSchema.loads(read_text(meta, "schema")).to_json() != schema.to_json():
        problems.append(f"/metadata/schema differs from {SCHEMA_FILE}: the file belongs to another dataset")
    return problems, length


def check_vector(data: Any, width: int, length: int, name: str, what: str) -> list[str]:
    """A (length, width) float32 vector dataset; one line per mismatch."""
    if data.ndim != 2 or data.shape[1] != width:
        return [f"/{name} has shape {data.shape}, the schema's {what} count is {width}"]
    if data.shape[0] != length:
        return [f"/{name} has {data.shape[0]} rows for {length} frames"]
    if data.dtype != np.float32:
        return [f"/{name} is {data.dtype}, expected float32"]
    return []


def check_names(data: Any, names: tuple[str, ...], name: str) -> list[str]:
    """The ``names`` attribute lists the schema's entries in order."""
    found = tuple(str(n) for n in data.attrs.get("names", ()))
    if found != names:
        return [f"/{name} names {list(found)[:8]} differ from the schema's {list(names)[:8]} (joint order)"]
    return []


def check_timestamps(values: AnyArray, name: str) -> list[str]:
    """Finite, strictly increasing timestamps."""
    if not np.all(np.isfinite(values)):
        return [f"/{name} holds non-finite values"]
    if values.size > 1 and not np.all(np.diff(values) > 0):
        i = int(np.argmin(np.diff(values)))
        return [f"/{name} is not strictly increasing (frame {i + 1}: {values[i + 1]} after {values[i]})"]
    return []


def check_images(data: Any, shape: tuple[int, int, int], length: int, name: str) -> list[str]:
    """uint8 (length, H, W, 3) images tagged RGB."""
    if data.dtype != np.uint8:
        return [f"/{name} is {data.dtype}, expected uint8"]
    if tuple(data.shape) != (length, *shape):
        return [f"/{name} has shape {tuple(data.shape)}, expected {(length, *shape)} (frames, H, W, C)"]
    order = data.attrs.get("channel_order")
    if order != CHANNEL_ORDER:
        return [f"/{name} channel order is {order!r}, expected {CHANNEL_ORDER!r}"]
    return []


# --- files ---------------------------------------------------------------------------------------


class scratch_dir:  # noqa: N801 - used like a function: `with scratch_dir(out) as tmp`
    """``<out>/.tmp-<pid>/`` for files being written, removed on exit; also removes the scratch
    folders of killed exports (their process is gone)."""

    def __init__(self, out: Path) -> None:
        self.path = Path(out) / f".tmp-{os.getpid()}"
        self._out = Path(out)

    def __enter__(self) -> Path:
        for stale in self._out.glob(".tmp-*"):
            if stale.is_dir() and not _alive(stale.name.removeprefix(".tmp-")):
                shutil.rmtree(stale, ignore_errors=True)
        self.path.mkdir(parents=True, exist_ok=True)
        return self.path

    def __exit__(self, *exc: object) -> None:
        shutil.rmtree(self.path, ignore_errors=True)


def _alive(pid: str) -> bool:
    if not pid.isdigit():
        return True  # not ours: leave it
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def fsync_dir(path: Path) -> None:
    """Make a rename in ``path`` durable."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def json_text(value: Mapping[str, JsonValue]) -> str:
    """Compact JSON for attributes."""
    return json.dumps(value, separators=(",", ":"))
