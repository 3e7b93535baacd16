"""RLDS / Open X-Embodiment export: TFRecord shards that ``tfds.builder_from_directory`` reads.

Layout (what TensorFlow Datasets writes for a generated dataset, so any RLDS / OXE loader reads it
without telerig)::

    <out>/<name>/<version>/                       the builder directory (version 1.0.0)
        dataset_info.json                         name, version, split "train": shard lengths, bytes
        features.json                             the feature tree (FeaturesDict of Dataset "steps")
        <name>-train.tfrecord-00000-of-000NN      one tf.train.Example per episode
        robot_schema.json                         joint order and limits (telerig.export.schema)
        telerig_episodes.json                     telerig episode ids and lengths per shard

Each example is one episode: ``steps`` (one step per dataset frame: ``is_first``, ``is_last``,
``is_terminal``, ``observation`` {``state``, ``image_<camera>`` JPEG or PNG}, ``action``,
``reward``, ``discount``, ``language_instruction``, plus ``timestamp``, ``frame_ns``,
``alignment_error_ms`` and ``valid``) and ``episode_metadata`` (telerig episode id, rig,
fingerprint, outcome, quality, gates). Sequence features are stored the way TFDS serializes a
``Dataset`` feature: each step field flattened over the steps into one list under ``steps/<path>``.
``language_instruction`` is the episode's task, or per step the active segment's description (else
``label: task``) for an episode with a ``segments.json`` (:mod:`telerig.export.language`).

Appending writes the new episodes to new shards; the old shards get their new ``-of-NN`` names as
hard links, and ``dataset_info.json`` (the file that lists the shards) is replaced last, so a
reader, or an export killed at any point, sees the previous dataset or the new one. Leftovers of an
interrupted export (temp dirs, links under names no ``dataset_info.json`` lists) are removed by
the next export.
"""

from __future__ import annotations

import contextlib
import fcntl
import io
import json
import logging
import math
import os
import re
import shutil
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar, Literal

import numpy as np
import numpy.typing as npt
from PIL import Image
from pydantic import BaseModel, ConfigDict, ValidationError

from telerig.errors import ExportError
from telerig.export.base import ValidationReport, write_atomic
from telerig.export.config import RldsExportConfig
from telerig.export.frames import EpisodeFrames
from telerig.export.schema import SCHEMA_FILE, DatasetSchema
from telerig.export.tfrecord import (
    Encoded,
    Feature,
    TFRecordWriter,
    bytes_feature,
    decode_example,
    encode_example,
    float_feature,
    int64_feature,
    read_records,
)

__all__ = [
    "EPISODES_FILE",
    "FEATURES_FILE",
    "INFO_FILE",
    "RLDS_VERSION",
    "ImageFormat",
    "RldsExporter",
    "dataset_dir",
    "dataset_name",
    "encode_episode",
    "features_json",
    "read_episodes",
    "shard_name",
]

_log = logging.getLogger("telerig.export.rlds")

#: Version directory of every telerig RLDS dataset (the layout of this module).
RLDS_VERSION = "1.0.0"
INFO_FILE = "dataset_info.json"
FEATURES_FILE = "features.json"
#: Telerig's own index: episode ids and lengths per shard, so an append knows what is there
#: without reading the shards back.
EPISODES_FILE = "telerig_episodes.json"
_SPLIT = "train"
_TEMPLATE = "{DATASET}-{SPLIT}.{FILEFORMAT}-{SHARD_X_OF_Y}"
_LOCK_FILE = ".telerig-rlds.lock"
_TMP_PREFIX = ".tmp-"
# The temp file write_atomic writes beside a metadata file before renaming it into place.
_ATOMIC_TMP = re.compile(r"^\..+\.tmp$")
_CAMERA_KEY = re.compile(r"^[A-Za-z0-9_]+$")

ImageFormat = Literal["jpeg", "png"]

_TFDS = "tensorflow_datasets.core.features."
_TENSOR = _TFDS + "tensor_feature.Tensor"
_SCALAR = _TFDS + "scalar.Scalar"
_TEXT = _TFDS + "text_feature.Text"
_IMAGE = _TFDS + "image_feature.Image"
_DICT = _TFDS + "features_dict.FeaturesDict"
_DATASET = _TFDS + "dataset_feature.Dataset"


def shard_name(name: str, index: int, count: int) -> str:
    """File name of shard ``index`` of ``count`` (TFDS's default ``{SHARD_X_OF_Y}`` template)."""
    return f"{name}-{_SPLIT}.tfrecord-{index:05d}-of-{count:05d}"


def dataset_name(rig: str) -> str:
    """The TFDS dataset name of a rig's export: the rig name as an identifier (``[a-z][a-z0-9_]*``)."""
    name = re.sub(r"[^a-z0-9]+", "_", rig.strip().lower()).strip("_")
    return name if re.match(r"^[a-z]", name) else f"rig_{name}"


# -- features -------------------------------------------------------------------------------------


def _tensor(shape: tuple[int, ...], dtype: str, doc: str) -> dict[str, object]:
    return {
        "pythonClassName": _SCALAR if not shape else _TENSOR,
        "tensor": {
            "shape": {"dimensions": [str(d) for d in shape]} if shape else {},
            "dtype": dtype,
            "encoding": "none",
        },
        "description": doc,
    }


def _text(doc: str) -> dict[str, object]:
    return {"pythonClassName": _TEXT, "text": {}, "description": doc}


def _features_dict(features: Mapping[str, object]) -> dict[str, object]:
    return {"pythonClassName": _DICT, "featuresDict": {"features": dict(features)}}


def features_json(schema: DatasetSchema, image_format: ImageFormat) -> dict[str, object]:
    """The ``features.json`` of a dataset of ``schema`` (``tfds.features`` serialized config).

    Raises:
        ExportError: A camera key is not usable as a feature name.
    """
    observation: dict[str, object] = {
        "state": _tensor(
            (len(schema.state),),
            "float32",
            "Measured robot state at the frame"
            + (", normalized to [-1, 1] from the limits" if schema.normalized else " [rad, m, opening 0..1]")
            + f"; entries in {SCHEMA_FILE} 'state' order: "
            + ", ".join(schema.state_names),
        ),
    }
    for camera in schema.cameras:
        if not _CAMERA_KEY.match(camera.key):
            raise ExportError(
                f"camera {camera.key!r} cannot name an RLDS feature; rename it to [A-Za-z0-9_]+"
            )
        observation[f"image_{camera.key}"] = {
            "pythonClassName": _IMAGE,
            "image": {
                "shape": {"dimensions": [str(camera.height), str(camera.width), str(camera.channels)]},
                "dtype": "uint8",
                "encodingFormat": image_format,
            },
            "description": f"Camera '{camera.key}' RGB image, nearest recorded frame ({camera.codec} source)",
        }
    steps = {
        "observation": _features_dict(observation),
        "action": _tensor(
            (len(schema.action),),
            "float32",
            "Command sent to the robot at the frame"
            + (", normalized to [-1, 1]" if schema.normalized else "")
            + f"; entries in {SCHEMA_FILE} 'action' order: "
            + ", ".join(schema.action_names),
        ),
        "reward": _tensor((), "float32", "1 on the last step of a successful episode, else 0"),
        "discount": _tensor((), "float32", "Always 1"),
        "is_first": _tensor((), "bool", "First step of the episode"),
        "is_last": _tensor((), "bool", "Last step of the episode"),
        "is_terminal": _tensor((), "bool", "Last step of an episode that ended complete"),
        "language_instruction": _text("The episode's task"),
        "timestamp": _tensor((), "float32", "Seconds from the episode's first frame (k / fps)"),
        "frame_ns": _tensor((), "int64", "Frame time on the rig's common clock [ns]"),
        "alignment_error_ms": _tensor(
            (), "float32", "Largest distance from the frame to a sample it uses, over all streams [ms]"
        ),
        "valid": _tensor((), "bool", "Every stream and camera had a sample within tolerance"),
    }
    metadata = {
        "episode_id": _text("Telerig episode id"),
        "rig": _text("Rig name"),
        "fingerprint": _text("Rig fingerprint digest"),
        "outcome": _text("'success', 'failure' or '' when not marked"),
        "quality": _tensor((), "float32", "Quality score in [0, 1]; NaN when not scored"),
        "gates_passed": _tensor((-1,), "string", "Quality gates the episode passed"),
        "gates_failed": _tensor((-1,), "string", "Quality gates the episode failed"),
    }
    dataset = {
        "pythonClassName": _DATASET,
        "sequence": {"feature": _features_dict(steps), "length": "-1"},
    }
    return _features_dict({"steps": dataset, "episode_metadata": _features_dict(metadata)})


def _image_format(features: Mapping[str, object]) -> ImageFormat | None:
    """The image encoding a features.json declares (``None`` without cameras)."""
    text = json.dumps(features)
    if '"encodingFormat": "jpeg"' in text:
        return "jpeg"
    if '"encodingFormat": "png"' in text:
        return "png"
    return None


# -- episodes -------------------------------------------------------------------------------------


def _encode_image(frame: npt.NDArray[np.uint8], image_format: ImageFormat, quality: int) -> bytes:
    buf = io.BytesIO()
    image = Image.fromarray(frame)
    if image_format == "jpeg":
        image.save(buf, format="JPEG", quality=quality)
    else:
        image.save(buf, format="PNG", compress_level=1)
    return buf.getvalue()


def _camera_images(
    episode: EpisodeFrames, image_format: ImageFormat, quality: int
) -> Iterator[tuple[str, list[bytes]]]:
    for spec in episode.schema.cameras:
        track = episode.cameras.get(spec.key)
        if track is None:
            raise ExportError(f"episode {episode.episode_id} has no camera {spec.key!r}; export without it")
        shape = (spec.height, spec.width, spec.channels)
        images: list[bytes] = []
        previous: npt.NDArray[np.uint8] | None = None
        for frame in track.frames():
            if frame is previous:  # a recorded frame used again (camera slower than the grid)
                images.append(images[-1])
                continue
            if frame.shape != shape:
                raise ExportError(
                    f"episode {episode.episode_id}: camera {spec.key} frame is {frame.shape}, "
                    f"the dataset declares {shape}"
                )
            images.append(_encode_image(frame, image_format, quality))
            previous = frame
        if len(images) != episode.length:
            raise ExportError(
                f"episode {episode.episode_id}: camera {spec.key} gave {len(images)} frames "
                f"for {episode.length} steps; run `telerig repair`"
            )
        yield spec.key, images


def encode_episode(
    episode: EpisodeFrames,
    *,
    image_format: ImageFormat = "jpeg",
    jpeg_quality: int = 95,
) -> Encoded:
    """One episode as a serialized ``tf.train.Example`` of the :func:`features_json` tree (in parts).

    Args:
        episode: The episode on the dataset grid.
        image_format: How step images are encoded.
        jpeg_quality: JPEG quality, 1..100.

    Raises:
        ExportError: The episode has no frame, or a camera disagrees with the schema.
    """
    n = episode.length
    if n == 0:
        raise ExportError(f"episode {episode.episode_id} has no frame on the dataset grid; leave it out")
    last = np.arange(n) == n - 1
    complete = episode.manifest.status == "complete"
    success = episode.outcome == "success"
    errors = list(episode.alignment_error_ms.values())
    worst = np.fmax.reduce(np.stack(errors), axis=0) if errors else np.full(n, np.nan, np.float32)
    task = episode.task.encode()
    # per step, the active segment's description (else "label: task"), the task where none is
    # active: RLDS datasets carry language per step (telerig.export.language)
    lang = episode.language
    instructions = [task] * n if lang is None else [t.encode() for t in lang.instruction]
    gates = episode.gates
    passed = [g.encode() for g, ok in gates.items() if ok is True]
    failed = [g.encode() for g, ok in gates.items() if ok is False]
    quality = episode.quality
    fingerprint = episode.extra.fingerprint
    features: dict[str, Encoded] = {
        "steps/is_first": int64_feature(np.arange(n) == 0),
        "steps/is_last": int64_feature(last),
        "steps/is_terminal": int64_feature(last & complete),
        "steps/reward": float_feature((last & success).astype(np.float32)),
        "steps/discount": float_feature(np.ones(n, np.float32)),
        "steps/language_instruction": bytes_feature(instructions),
        "steps/action": float_feature(episode.action),
        "steps/observation/state": float_feature(episode.state),
        "steps/timestamp": float_feature(episode.timestamp),
        "steps/frame_ns": int64_feature(episode.frame_ns),
        "steps/alignment_error_ms": float_feature(worst),
        "steps/valid": int64_feature(episode.valid),
        "episode_metadata/episode_id": bytes_feature([episode.episode_id.encode()]),
        "episode_metadata/rig": bytes_feature([episode.schema.rig.encode()]),
        "episode_metadata/fingerprint": bytes_feature(
            [(fingerprint.digest if fingerprint is not None else "").encode()]
        ),
        "episode_metadata/outcome": bytes_feature([(episode.outcome or "").encode()]),
        "episode_metadata/quality": float_feature([math.nan if quality is None else quality]),
        "episode_metadata/gates_passed": bytes_feature(passed),
        "episode_metadata/gates_failed": bytes_feature(failed),
    }
    for key, images in _camera_images(episode, image_format, jpeg_quality):
        features[f"steps/observation/image_{key}"] = bytes_feature(images)
    return encode_example(features)


# -- the dataset on disk --------------------------------------------------------------------------


class _ShardEntry(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    episodes: list[str]
    frames: list[int]
    bytes: int


class _EpisodeIndex(BaseModel):
    """``telerig_episodes.json``: what each shard holds, in shard order."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    format: int = 1
    name: str
    shards: list[_ShardEntry]


@dataclass(frozen=True, slots=True)
class _Dataset:
    """The dataset as its ``dataset_info.json`` (the commit point) lists it."""

    dir: Path
    name: str
    shard_lengths: tuple[int, ...]
    num_bytes: int
    shards: tuple[_ShardEntry, ...]

    @property
    def files(self) -> tuple[str, ...]:
        count = len(self.shard_lengths)
        return tuple(shard_name(self.name, i, count) for i in range(count))

    @property
    def episode_ids(self) -> list[str]:
        return [e for shard in self.shards for e in shard.episodes]


def dataset_dir(out: Path) -> Path | None:
    """The builder directory (``<out>/<name>/<version>``) of the dataset at ``out``; ``None`` if none.

    Raises:
        ExportError: ``out`` holds several datasets.
    """
    found = sorted(p.parent for p in Path(out).glob(f"*/*/{INFO_FILE}"))
    if len(found) > 1:
        listed = ", ".join(str(p) for p in found)
        raise ExportError(f"{out} holds several RLDS datasets ({listed}); export into another --out")
    return found[0] if found else None


def _read_info(directory: Path) -> tuple[str, tuple[int, ...], int]:
    """Name, shard lengths [episodes] and size [bytes] of the train split in ``dataset_info.json``."""
    try:
        info = json.loads((directory / INFO_FILE).read_text())
        split = next(s for s in info["splits"] if s["name"] == _SPLIT)
        lengths = tuple(int(n) for n in split.get("shardLengths", []))
        return str(info["name"]), lengths, int(split.get("numBytes", 0))
    except (OSError, ValueError, KeyError, StopIteration, TypeError) as exc:
        raise ExportError(
            f"{directory / INFO_FILE} is not readable ({type(exc).__name__}: {exc}); "
            "export into another --out"
        ) from None


def _read_dataset(out: Path) -> _Dataset | None:
    directory = dataset_dir(out)
    if directory is None:
        return None
    name, lengths, num_bytes = _read_info(directory)
    try:
        index = _EpisodeIndex.model_validate_json((directory / EPISODES_FILE).read_bytes())
    except (OSError, ValidationError) as exc:
        raise ExportError(
            f"{directory / EPISODES_FILE} is not readable ({type(exc).__name__}); "
            "this is not a telerig RLDS dataset: export into another --out"
        ) from None
    # The index is written just before dataset_info.json: after a kill between the two it lists
    # shards dataset_info.json does not; those are not part of the dataset.
    shards = tuple(index.shards[: len(lengths)])
    if (
        index.name != name
        or len(shards) != len(lengths)
        or any(len(s.episodes) != n for s, n in zip(shards, lengths, strict=True))
    ):
        raise ExportError(
            f"{directory}/{EPISODES_FILE} disagrees with {INFO_FILE}; export into another --out"
        )
    return _Dataset(directory, name, lengths, num_bytes, shards)


def read_episodes(directory: Path) -> Iterator[dict[str, Feature]]:
    """Every episode of a builder directory, decoded (feature key → values), in shard order.

    Reads what ``dataset_info.json`` lists, like TFDS: any RLDS dataset of TFRecord shards.

    Raises:
        ExportError: ``dataset_info.json`` or a shard is missing, truncated or corrupt.
    """
    directory = Path(directory)
    name, lengths, _ = _read_info(directory)
    for i in range(len(lengths)):
        path = directory / shard_name(name, i, len(lengths))
        if not path.is_file():
            raise ExportError(f"{path} is missing; re-export the dataset")
        for record in read_records(path):
            yield decode_example(record)


def _info_json(name: str, shards: list[_ShardEntry], schema: DatasetSchema) -> str:
    info = {
        "name": name,
        "version": RLDS_VERSION,
        "description": (
            f"Teleoperated demonstrations recorded with telerig on rig '{schema.rig}' at {schema.fps} Hz. "
            f"State and action entries are named, in order, in {SCHEMA_FILE} beside this file."
        ),
        "fileFormat": "tfrecord",
        "splits": [
            {
                "name": _SPLIT,
                "filepathTemplate": _TEMPLATE,
                "shardLengths": [str(len(s.episodes)) for s in shards],
                "numBytes": str(sum(s.bytes for s in shards)),
            }
        ],
    }
    return json.dumps(info, indent=2, sort_keys=True)


@contextlib.contextmanager
def _locked(out: Path) -> Iterator[None]:
    """Hold an exclusive lock on ``out`` (one export writes a dataset at a time)."""
    out.mkdir(parents=True, exist_ok=True)
    with (out / _LOCK_FILE).open("a") as lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise ExportError(f"another export is writing {out}; wait for it to finish") from None
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


def _remove_leftovers(directory: Path, dataset: _Dataset | None) -> None:
    """Remove what an interrupted export left: temp dirs, shards no ``dataset_info.json`` lists."""
    keep = set(dataset.files) if dataset is not None else set()
    pattern = re.compile(r"^.+-" + _SPLIT + r"\.tfrecord-\d{5,}-of-\d{5,}$")
    for path in directory.iterdir():
        if path.name.startswith(_TMP_PREFIX) and path.is_dir():
            shutil.rmtree(path, ignore_errors=True)
        elif path.name.startswith(_TMP_PREFIX) or _ATOMIC_TMP.match(path.name):
            path.unlink()
        elif pattern.match(path.name) and path.name not in keep:
            path.unlink()
            _log.info("removed %s, left by an interrupted export", path)


def _link(src: Path, dst: Path) -> None:
    """Give ``src`` a second name ``dst`` (a hard link; a copy where the file system has none)."""
    dst.unlink(missing_ok=True)
    try:
        os.link(src, dst)
    except OSError:
        tmp = dst.with_name(_TMP_PREFIX + dst.name)
        shutil.copyfile(src, tmp)
        os.replace(tmp, dst)


class RldsExporter:
    """Writes, appends to and validates RLDS datasets (see the module docstring)."""

    format: ClassVar[str] = "rlds"

    def __init__(self, config: RldsExportConfig) -> None:
        self.config = config

    def schema_path(self, out: Path) -> Path:
        """``robot_schema.json`` in the builder directory (``<out>/robot_schema.json`` before one exists)."""
        directory = dataset_dir(out)
        return (directory if directory is not None else Path(out)) / SCHEMA_FILE

    def existing_episodes(self, out: Path) -> set[str]:
        """Telerig episode ids in the dataset at ``out`` (empty when there is none)."""
        dataset = _read_dataset(Path(out))
        return set(dataset.episode_ids) if dataset is not None else set()

    def write(
        self,
        out: Path,
        schema: DatasetSchema,
        episodes: Iterable[EpisodeFrames],
        progress: Callable[[EpisodeFrames], None],
    ) -> int:
        """Write the episodes as new shards of the dataset at ``out`` (created when absent).

        Returns:
            Frames (steps) written.

        Raises:
            ExportError: The dataset at ``out`` has another name, image format or features.
        """
        out = Path(out)
        with _locked(out):
            dataset = _read_dataset(out)
            name = dataset.name if dataset is not None else self.config.name or dataset_name(schema.rig)
            if self.config.name is not None and name != self.config.name:
                raise ExportError(
                    f"{out} holds RLDS dataset '{name}', not '{self.config.name}'; use another --out"
                )
            directory = dataset.dir if dataset is not None else out / name / RLDS_VERSION
            directory.mkdir(parents=True, exist_ok=True)
            _remove_leftovers(directory, dataset)
            features = features_json(schema, self.config.image_format)
            if dataset is not None:
                self._check_features(directory, features)
            tmp = directory / f"{_TMP_PREFIX}{os.getpid()}"
            tmp.mkdir()
            try:
                skip = set(dataset.episode_ids) if dataset is not None else set()
                new, frames = self._write_shards(tmp, episodes, skip, progress)
                if new:
                    self._commit(directory, name, dataset, new, schema, features)
            finally:
                shutil.rmtree(tmp, ignore_errors=True)
        return frames

    def _check_features(self, directory: Path, features: dict[str, object]) -> None:
        try:
            existing = json.loads((directory / FEATURES_FILE).read_text())
        except (OSError, ValueError) as exc:
            raise ExportError(
                f"cannot read {directory / FEATURES_FILE} ({exc}); export into another --out"
            ) from None
        if existing != features:
            stored = _image_format(existing)
            if stored is not None and stored != self.config.image_format:
                raise ExportError(
                    f"{directory} stores {stored} images; export with image_format: {stored} "
                    "or into another --out"
                )
            raise ExportError(
                f"{directory} holds other features than this export writes; export into another --out"
            )

    def _write_shards(
        self,
        tmp: Path,
        episodes: Iterable[EpisodeFrames],
        skip: set[str],
        progress: Callable[[EpisodeFrames], None],
    ) -> tuple[list[tuple[Path, _ShardEntry]], int]:
        limit = self.config.shard_mb << 20
        done: list[tuple[Path, _ShardEntry]] = []
        writer: TFRecordWriter | None = None
        ids: list[str] = []
        lengths: list[int] = []
        frames = 0

        def close() -> None:
            if writer is not None:
                writer.close()
                done.append(
                    (
                        writer.path,
                        _ShardEntry(episodes=list(ids), frames=list(lengths), bytes=writer.bytes_written),
                    )
                )
                ids.clear()
                lengths.clear()

        for episode in episodes:
            if episode.episode_id in skip:
                _log.info("episode %s is already in the dataset; skipped", episode.episode_id)
                continue
            record = encode_episode(
                episode,
                image_format=self.config.image_format,
                jpeg_quality=self.config.jpeg_quality,
            )
            if writer is None or writer.bytes_written >= limit:
                close()
                writer = TFRecordWriter(tmp / f"shard-{len(done):05d}")
            writer.write(record)
            ids.append(episode.episode_id)
            lengths.append(episode.length)
            skip.add(episode.episode_id)
            frames += episode.length
            progress(episode)
        close()
        return done, frames

    def _commit(
        self,
        directory: Path,
        name: str,
        dataset: _Dataset | None,
        new: list[tuple[Path, _ShardEntry]],
        schema: DatasetSchema,
        features: dict[str, object],
    ) -> None:
        old = list(dataset.shards) if dataset is not None else []
        old_files = list(dataset.files) if dataset is not None else []
        count = len(old) + len(new)
        # 1. Every shard under its new name; the old names stay until dataset_info.json moves on.
        for i, file in enumerate(old_files):
            _link(directory / file, directory / shard_name(name, i, count))
        for j, (path, _entry) in enumerate(new):
            os.replace(path, directory / shard_name(name, len(old) + j, count))
        shards = old + [entry for _path, entry in new]
        # 2. Metadata; dataset_info.json last: it is what makes the new shards part of the dataset.
        write_atomic(directory / FEATURES_FILE, json.dumps(features, indent=2, sort_keys=True))
        write_atomic(directory / SCHEMA_FILE, schema.dumps())
        write_atomic(
            directory / EPISODES_FILE, _EpisodeIndex(name=name, shards=shards).model_dump_json(indent=2)
        )
        write_atomic(directory / INFO_FILE, _info_json(name, shards, schema))
        # 3. The old names are no longer listed anywhere.
        for file in old_files:
            if file not in {shard_name(name, i, count) for i in range(count)}:
                (directory / file).unlink(missing_ok=True)

    def validate(self, out: Path) -> ValidationReport:
        """Re-read every shard with telerig's decoder and check it against the schema and index.

        Checks: shard lengths and sizes against ``dataset_info.json``, each record's CRCs, every
        step field's length, the action and state dimensions, ``is_first`` / ``is_last`` /
        ``is_terminal``, strictly increasing timestamps, and every image's size, channels and
        encoding (headers only).
        """
        try:
            dataset = _read_dataset(Path(out))
        except ExportError as exc:
            return ValidationReport(0, 0, (str(exc),))
        if dataset is None:
            return ValidationReport(0, 0, (f"no RLDS dataset ({INFO_FILE}) under {out}",))
        try:
            schema = DatasetSchema.loads((dataset.dir / SCHEMA_FILE).read_bytes())
            features = json.loads((dataset.dir / FEATURES_FILE).read_text())
        except (OSError, ValueError, ExportError) as exc:
            return ValidationReport(0, 0, (f"{dataset.dir}: unreadable metadata ({exc})",))
        image_format = _image_format(features) or self.config.image_format
        problems: list[str] = []
        if features != features_json(schema, image_format):
            problems.append(f"{FEATURES_FILE} does not match {SCHEMA_FILE}")
        size = episodes = frames = 0
        for file, entry in zip(dataset.files, dataset.shards, strict=True):
            path = dataset.dir / file
            if not path.is_file():
                problems.append(f"shard {file} is missing")
                continue
            size += path.stat().st_size
            checked, found = _check_shard(path, entry, schema, image_format)
            episodes += checked
            frames += sum(entry.frames[:checked])
            problems += found
        if size != dataset.num_bytes:
            problems.append(f"shards hold {size} bytes, {INFO_FILE} says {dataset.num_bytes}")
        return ValidationReport(episodes, frames, tuple(problems))


def _check_shard(
    path: Path, entry: _ShardEntry, schema: DatasetSchema, image_format: ImageFormat
) -> tuple[int, list[str]]:
    """Episodes checked in one shard and the problems found (one episode in memory at a time)."""
    problems: list[str] = []
    if path.stat().st_size != entry.bytes:
        problems.append(f"shard {path.name} is {path.stat().st_size} bytes, the index says {entry.bytes}")
    count = 0
    try:
        for record in read_records(path):
            if count < len(entry.episodes):
                episode_id = entry.episodes[count]
                example = decode_example(record)
                found = _check_episode(example, schema, image_format, episode_id, entry.frames[count])
                problems.extend(f"episode {episode_id}: {p}" for p in found)
            count += 1
    except ExportError as exc:
        return min(count, len(entry.episodes)), [*problems, str(exc)]
    if count != len(entry.episodes):
        problems.append(f"shard {path.name} holds {count} episodes, {INFO_FILE} says {len(entry.episodes)}")
    return min(count, len(entry.episodes)), problems


def _check_episode(
    example: dict[str, Feature],
    schema: DatasetSchema,
    image_format: ImageFormat,
    episode_id: str,
    length: int,
) -> list[str]:
    """Problems of one decoded episode (empty when it is valid)."""
    try:
        stored_id = example["episode_metadata/episode_id"].as_bytes("episode_id")
        if stored_id != [episode_id.encode()]:
            return [f"the shard holds episode {stored_id!r} here"]
        first = example["steps/is_first"].as_array("is_first", "int64")
        n = first.size
        problems = [] if n == length else [f"{n} steps, the index says {length}"]
        if n == 0:
            return [*problems, "no steps"]
        expected_edges = np.zeros(n, np.int64)
        expected_edges[0] = 1
        if not np.array_equal(first, expected_edges):
            problems.append("is_first is not set on the first step only")
        last = example["steps/is_last"].as_array("is_last", "int64")
        if not np.array_equal(last, expected_edges[::-1]):
            problems.append("is_last is not set on the last step only")
        terminal = example["steps/is_terminal"].as_array("is_terminal", "int64")
        if terminal.size != n or terminal[:-1].any():
            problems.append("is_terminal is set before the last step")
        for key, width in (
            ("steps/action", len(schema.action)),
            ("steps/observation/state", len(schema.state)),
        ):
            values = example[key].as_array(key, "float")
            if values.size != n * width:
                problems.append(f"{key} has {values.size} values for {n} steps of {width} (the DoF count)")
        timestamp = example["steps/timestamp"].as_array("timestamp", "float")
        if timestamp.size != n or (n > 1 and not bool(np.all(np.diff(timestamp) > 0))):
            problems.append("timestamps are not strictly increasing, one per step")
        frame_ns = example["steps/frame_ns"].as_array("frame_ns", "int64")
        if frame_ns.size != n or (n > 1 and not bool(np.all(np.diff(frame_ns) > 0))):
            problems.append("frame_ns are not strictly increasing, one per step")
        for key in ("reward", "discount", "alignment_error_ms"):
            if example[f"steps/{key}"].as_array(key, "float").size != n:
                problems.append(f"steps/{key} does not have one value per step")
        for key in ("language_instruction",):
            if len(example[f"steps/{key}"].as_bytes(key)) != n:
                problems.append(f"steps/{key} does not have one value per step")
        for camera in schema.cameras:
            key = f"steps/observation/image_{camera.key}"
            images = example[key].as_bytes(key)
            if len(images) != n:
                problems.append(f"{key} has {len(images)} images for {n} steps")
            bad = _bad_image(images, image_format, camera.width, camera.height)
            if bad:
                problems.append(f"{key}: {bad}")
        return problems
    except KeyError as exc:
        return [f"feature {exc.args[0]} is missing"]
    except ExportError as exc:
        return [str(exc)]


def _bad_image(images: list[bytes], image_format: ImageFormat, width: int, height: int) -> str | None:
    """The first image (headers only) that is not an RGB ``width`` x ``height`` ``image_format``."""
    want = "JPEG" if image_format == "jpeg" else "PNG"
    for k, data in enumerate(images):
        try:
            with Image.open(io.BytesIO(data)) as image:
                if image.format != want or image.size != (width, height) or image.mode != "RGB":
                    return (
                        f"step {k} is a {image.format} {image.mode} {image.size[0]}x{image.size[1]} image, "
                        f"expected {want} RGB {width}x{height}"
                    )
        except (OSError, ValueError) as exc:
            return f"step {k} is not an image ({exc})"
    return None
