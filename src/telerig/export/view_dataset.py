"""``telerig view DATASET``: an exported dataset's episodes as one Rerun recording.

The format is found through the exporter registry (the registered format whose schema file,
:meth:`~telerig.export.base.Exporter.schema_path`, is in the directory), the joint order from that
``robot_schema.json``. Per episode, under ``episodes/<telerig episode id>/``, on the timeline
``dataset_time`` (seconds from the episode's first frame, the dataset's own ``timestamp``):

- ``state/<name>`` and ``action/<name>``: one scalar series per entry of the state and action
  vectors, named as the schema names them;
- ``cameras/<key>``: LeRobot: a :class:`rerun.VideoFrameReference` per frame into the dataset's MP4
  file (logged once as an :class:`rerun.AssetVideo` under ``videos/<key>/<file>``, not re-encoded);
  HDF5 and robomimic: the stored images, one every ``1 / IMAGE_RATE_HZ`` s, JPEG-compressed; RLDS:
  the stored JPEG/PNG step images as they are, at the same reduced rate;
- ``ee_path``: the end effector's path by forward kinematics of the state's arm joints.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from telerig.errors import ExportError
from telerig.export.schema import DatasetSchema
from telerig.export.view_base import ViewSummary, end_effector_path

__all__ = ["DATASET_TIMELINE", "IMAGE_RATE_HZ", "dataset_format", "view_dataset"]

#: Timeline of a dataset's episodes: seconds from each episode's first frame.
DATASET_TIMELINE = "dataset_time"
#: Rate [Hz] at which stored images (HDF5, robomimic, RLDS) are shown; LeRobot videos show every frame.
IMAGE_RATE_HZ = 5.0

Float64Array = npt.NDArray[np.float64]


@dataclass(slots=True)
class _DatasetEpisode:
    episode_id: str
    timestamp: Float64Array
    state: Float64Array
    action: Float64Array
    videos: dict[str, tuple[str, float]] = field(default_factory=dict)  # key -> (video entity, from_ts)
    images: dict[str, Any] = field(default_factory=dict)  # key -> (F, H, W, 3) array-like (h5py dataset)
    encoded: dict[str, tuple[list[bytes], str]] = field(default_factory=dict)  # key -> (images, media type)


def dataset_format(out: Path) -> tuple[str, DatasetSchema]:
    """The registered format of the export directory ``out`` and its schema: a format whose schema
    file is there and whose exporter finds episodes there (formats may share a schema file name).

    Raises:
        ExportError: no registered format has its schema file in ``out``.
    """
    from telerig.export.run import build_exporter
    from telerig.registry import EXPORTERS

    found: list[tuple[str, Path]] = []
    for fmt in EXPORTERS.names():
        try:
            exporter = build_exporter(fmt)
            path = exporter.schema_path(out)
            if not path.is_file():
                continue
            holds = bool(exporter.existing_episodes(out))
        except (ExportError, OSError):
            continue
        found.insert(0 if holds else len(found), (fmt, path))  # formats holding episodes first
    if found:
        fmt, path = found[0]
        return fmt, DatasetSchema.loads(path.read_bytes())
    raise ExportError(
        f"{out} is not a dataset of any registered format ({', '.join(EXPORTERS.names())}): "
        "no schema file; pass the directory `telerig export --out` wrote"
    )


def view_dataset(out_dir: Path, rrd: Path) -> ViewSummary:
    """Write ``rrd`` for the dataset in ``out_dir``; see the module docstring.

    Raises:
        ExportError: not a dataset of a registered format, or one this viewer cannot read; one line.
    """
    import rerun as rr

    fmt, schema = dataset_format(out_dir)
    readers = {"lerobot": _lerobot, "hdf5": _hdf5, "robomimic": _robomimic, "rlds": _rlds}
    if fmt not in readers:
        raise ExportError(f"{out_dir}: telerig view reads {', '.join(readers)} datasets, not {fmt}")
    summary = ViewSummary(out=rrd, source=str(out_dir))
    rrd.parent.mkdir(parents=True, exist_ok=True)
    rec = rr.RecordingStream("telerig", recording_id=f"dataset-{out_dir.resolve().name}")
    rec.save(rrd)
    try:
        rec.send_recording_name(f"{fmt} dataset {out_dir.name} · {schema.rig}")
        rec.log(
            "dataset", rr.TextDocument(_describe(fmt, schema), media_type=rr.MediaType.MARKDOWN), static=True
        )
        summary.entities["dataset"] = 1
        for episode in readers[fmt](out_dir, schema, rec, summary):
            _log_episode(rec, schema, episode, summary)
        rec.flush()
    finally:
        rec.disconnect()
    return summary


def _describe(fmt: str, schema: DatasetSchema) -> str:
    return (
        f"# {fmt} dataset of rig {schema.rig}\n"
        f"- fps: {schema.fps}\n- robots: {', '.join(f'{k} ({v})' for k, v in schema.robots.items())}\n"
        f"- state: {', '.join(schema.state_names)}\n- action: {', '.join(schema.action_names)}\n"
        f"- cameras: {', '.join(f'{c.key} {c.width}x{c.height}' for c in schema.cameras) or '-'}\n"
        f"- normalized: {schema.normalized}\n"
    )


def _time(seconds: Float64Array) -> Any:
    import rerun as rr

    return rr.TimeColumn(DATASET_TIMELINE, duration=np.asarray(seconds, dtype=np.float64))


def _log_episode(rec: Any, schema: DatasetSchema, ep: _DatasetEpisode, summary: ViewSummary) -> None:
    import rerun as rr

    base = f"episodes/{ep.episode_id}"
    t = ep.timestamp
    for vector, names, values in (
        ("state", schema.state_names, ep.state),
        ("action", schema.action_names, ep.action),
    ):
        if values.shape != (len(t), len(names)):
            raise ExportError(
                f"episode {ep.episode_id}: {vector} has shape {values.shape}, the schema names "
                f"{len(names)} entries for {len(t)} frames"
            )
        for j, name in enumerate(names):
            path = f"{base}/{vector}/{name}"
            rec.log(path, rr.SeriesLines(names=name), static=True)
            rec.send_columns(path, indexes=[_time(t)], columns=rr.Scalars.columns(scalars=values[:, j]))
            summary.entities[path] = len(t)
    for key, (video_entity, from_ts) in ep.videos.items():
        path = f"{base}/cameras/{key}"
        ts_ns = np.round((from_ts + t) * 1e9).astype(np.int64)
        rec.send_columns(
            path,
            indexes=[_time(t)],
            columns=rr.VideoFrameReference.columns(
                timestamp=ts_ns, video_reference=[video_entity] * len(ts_ns)
            ),
        )
        summary.entities[path] = len(t)
        summary.video = "asset"
    step = max(1, round(schema.fps / IMAGE_RATE_HZ))
    for key, images in ep.images.items():
        path = f"{base}/cameras/{key}"
        for i in range(0, len(t), step):
            rec.set_time(DATASET_TIMELINE, duration=float(t[i]))
            rec.log(path, rr.Image(np.asarray(images[i]), color_model="RGB").compress(jpeg_quality=80))
        summary.entities[path] = len(range(0, len(t), step))
        summary.video = f"frames at {schema.fps / step:g} Hz"
    for key, (encoded, media_type) in ep.encoded.items():
        path = f"{base}/cameras/{key}"
        for i in range(0, min(len(t), len(encoded)), step):
            rec.set_time(DATASET_TIMELINE, duration=float(t[i]))
            rec.log(path, rr.EncodedImage(contents=encoded[i], media_type=media_type))
        summary.entities[path] = len(range(0, min(len(t), len(encoded)), step))
        summary.video = f"frames at {schema.fps / step:g} Hz"
    rec.reset_time()
    _log_ee_path(rec, schema, ep, base, summary)


def _log_ee_path(
    rec: Any, schema: DatasetSchema, ep: _DatasetEpisode, base: str, summary: ViewSummary
) -> None:
    import rerun as rr

    from telerig.robots.models import ARM_MODELS

    for robot, model in schema.robots.items():
        columns = [i for i, s in enumerate(schema.state) if s.robot == robot and s.part == "joints"]
        if model not in ARM_MODELS or not columns:
            summary.notes.append(f"robot {robot}: no end-effector path (model {model} is not an arm model)")
            continue
        names = tuple(schema.state[i].name.split(".")[-1] for i in columns)
        q = ep.state[:, columns]
        if schema.normalized:
            q = np.asarray(schema.denormalize(ep.state.astype(np.float32), "state"), dtype=np.float64)[
                :, columns
            ]
        path = end_effector_path(model, names, q)
        keep = np.all(np.isfinite(path), axis=1)
        if keep.any():
            entity = f"{base}/robots/{robot}/ee_path"
            rec.log(entity, rr.LineStrips3D([path[keep]], radii=0.002), static=True)
            summary.entities[entity] = 1


# --- readers ---------------------------------------------------------------------------------------


def _lerobot(out: Path, schema: DatasetSchema, rec: Any, summary: ViewSummary) -> Iterator[_DatasetEpisode]:
    import pyarrow.parquet as pq
    import rerun as rr

    info = json.loads((out / "meta" / "info.json").read_text())
    video_keys = [k for k, f in info["features"].items() if f.get("dtype") == "video"]
    logged: set[str] = set()
    for meta_file in sorted((out / "meta" / "episodes").glob("chunk-*/file-*.parquet")):
        for row in pq.read_table(meta_file).to_pylist():
            data_file = out / info["data_path"].format(
                chunk_index=row["data/chunk_index"], file_index=row["data/file_index"]
            )
            index = row["episode_index"]
            table = pq.read_table(data_file, filters=[("episode_index", "=", index)])
            episode = _DatasetEpisode(
                episode_id=str(row.get("telerig/episode_id") or f"episode_{index:06d}"),
                timestamp=np.asarray(table.column("timestamp").to_numpy(), dtype=np.float64),
                state=_matrix(table.column("observation.state").to_pylist()),
                action=_matrix(table.column("action").to_pylist()),
            )
            for key in video_keys:
                chunk, file = row[f"videos/{key}/chunk_index"], row[f"videos/{key}/file_index"]
                video = out / info["video_path"].format(video_key=key, chunk_index=chunk, file_index=file)
                entity = f"videos/{key}/chunk-{chunk:03d}/file-{file:03d}"
                if entity not in logged:
                    rec.log(entity, rr.AssetVideo(path=video), static=True)
                    summary.entities[entity] = 1
                    logged.add(entity)
                episode.videos[key.rsplit(".", 1)[-1]] = (entity, float(row[f"videos/{key}/from_timestamp"]))
            yield episode


def _matrix(rows: list[Any]) -> Float64Array:
    return np.asarray(rows, dtype=np.float64).reshape(len(rows), -1)


def _hdf5(out: Path, schema: DatasetSchema, rec: Any, summary: ViewSummary) -> Iterator[_DatasetEpisode]:
    import h5py

    for path in sorted((out / "episodes").glob("*.hdf5")):
        with h5py.File(path, "r") as f:
            obs = f["observations"]
            episode = _DatasetEpisode(
                episode_id=str(f.attrs.get("episode_id", path.stem)),
                timestamp=np.asarray(obs["timestamp"][()], dtype=np.float64),
                state=np.asarray(obs["state"][()], dtype=np.float64),
                action=np.asarray(f["actions"][()], dtype=np.float64),
            )
            images = obs.get("images")
            for key in images if images is not None else ():
                episode.images[key] = images[key]
            yield episode  # logged while the file is open: images are read frame by frame


def _robomimic(out: Path, schema: DatasetSchema, rec: Any, summary: ViewSummary) -> Iterator[_DatasetEpisode]:
    import h5py

    with h5py.File(out / "robomimic.hdf5", "r") as f:
        demos = sorted(f["data"], key=lambda name: int(name.rsplit("_", 1)[-1]))
        for name in demos:
            demo = f["data"][name]
            episode = _DatasetEpisode(
                episode_id=str(demo.attrs.get("episode_id", name)),
                timestamp=np.asarray(demo["timestamp"][()], dtype=np.float64),
                state=np.asarray(demo["obs"]["state"][()], dtype=np.float64),
                action=np.asarray(demo["actions"][()], dtype=np.float64),
            )
            for camera in schema.cameras:
                key = f"{camera.key}_image"
                if key in demo["obs"]:
                    episode.images[camera.key] = demo["obs"][key]
            yield episode


def _rlds(out: Path, schema: DatasetSchema, rec: Any, summary: ViewSummary) -> Iterator[_DatasetEpisode]:
    from telerig.export.rlds import dataset_dir, read_episodes

    directory = dataset_dir(out)
    if directory is None:
        raise ExportError(f"{out}: no RLDS builder directory (<name>/<version>/dataset_info.json)")
    state_width, action_width = len(schema.state), len(schema.action)
    for features in read_episodes(directory):
        t = np.asarray(features["steps/timestamp"].as_array("steps/timestamp", "float"), dtype=np.float64)
        n = len(t)
        episode = _DatasetEpisode(
            episode_id=features["episode_metadata/episode_id"].as_bytes("episode_id")[0].decode(),
            timestamp=t,
            state=np.asarray(
                features["steps/observation/state"].as_array("state", "float"), dtype=np.float64
            ).reshape(n, state_width),
            action=np.asarray(features["steps/action"].as_array("action", "float"), dtype=np.float64).reshape(
                n, action_width
            ),
        )
        for camera in schema.cameras:
            key = f"steps/observation/image_{camera.key}"
            if key in features:
                encoded = features[key].as_bytes(key)
                media = "image/png" if encoded and encoded[0][:4] == b"\x89PNG" else "image/jpeg"
                episode.encoded[camera.key] = (encoded, media)
        yield episode
