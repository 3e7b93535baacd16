"""Read a LeRobot v3.0 dataset written by ``telerig export --format lerobot`` for training.

What is read (see :mod:`telerig.export.lerobot` for the writer):

* ``meta/info.json`` (``codebase_version`` v3.0, ``fps``, ``features``, ``total_episodes`` - the
  commit point: rows past it are left over from an interrupted export and ignored);
* ``meta/robot_schema.json`` for the state / action entry names (and limits, to undo ``--normalize``:
  a checkpoint always works in physical units);
* ``meta/episodes/chunk-*/file-*.parquet`` for where each episode's rows and video frames are,
  and its ``telerig/outcome``;
* ``data/chunk-*/file-*.parquet`` (``observation.state``, ``action``, ``frame_index``) with pyarrow;
* ``videos/<key>/chunk-*/file-*.mp4`` with PyAV: each file is decoded once, front to back, and each
  frame is resized to the policy's image size with :func:`telerig.policy.images.resize_rgb` (the
  same resize the runner applies at rollout) and kept as uint8 in memory. Frame ``k`` of an
  episode is the frame whose pts is ``from_timestamp + k / fps``.

Anything that is not such a dataset is refused with one :class:`PolicyError` line that names the
file and the fix. An optional cache directory keeps the decoded, resized frames as one ``.npz``
per (dataset content, image size), so a second training run on the same export skips the decode.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import zipfile
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import av
import numpy as np
import numpy.typing as npt
import pyarrow as pa
import pyarrow.parquet as pq

from telerig.errors import ExportError, PolicyError
from telerig.export._lerobot_video import VIDEO_PATH
from telerig.export.lerobot import (
    ACTION,
    CODEBASE_VERSION,
    DATA_PATH,
    IMAGES,
    INFO_PATH,
    SCHEMA_PATH,
    STATE,
)
from telerig.export.schema import DatasetSchema
from telerig.policy.images import resize_rgb

__all__ = ["MAX_INFO_BYTES", "Episode", "PolicyDataset", "image_size_for", "read_dataset", "split_episodes"]

_log = logging.getLogger("telerig.learn.dataset")

Float32Array = npt.NDArray[np.float32]
UInt8Array = npt.NDArray[np.uint8]
#: Called as ``progress(what, done, total)`` while frames are decoded.
Progress = Callable[[str, int, int], None]

#: Tolerance [frames] between a video frame's pts and the grid time it stands for: the writer puts
#: frame k exactly at ``from_timestamp + k / fps``; pts are integers in a 1/fps time base.
_PTS_TOLERANCE_FRAMES = 0.25
#: Frames resized per torch call while decoding (bounds the float32 batch to ~100 MB at 640x480).
_RESIZE_BATCH = 64
_CACHE_VERSION = 1
#: Largest ``meta/info.json`` read [bytes]: telerig's are a few kB (features of a few cameras).
MAX_INFO_BYTES = 16 * 2**20


@dataclass(frozen=True)
class Episode:
    """One episode of the dataset, ready to sample from.

    Attributes:
        index: ``episode_index`` in the dataset.
        episode_id: The telerig episode id (``""`` if the dataset lacks the column).
        outcome: ``success``, ``failure`` or ``None`` when unknown.
        state: Measured state per frame [physical units], float32 (F, S).
        action: Commanded action per frame [physical units], float32 (F, A).
        images: Camera key → frames at the requested image size, uint8 (F, H, W, 3).
    """

    index: int
    episode_id: str
    outcome: str | None
    state: Float32Array
    action: Float32Array
    images: Mapping[str, UInt8Array]

    @property
    def length(self) -> int:
        return int(self.state.shape[0])


@dataclass(frozen=True)
class PolicyDataset:
    """A LeRobot v3 export read into memory.

    Attributes:
        root: The dataset directory.
        schema: Its ``robot_schema.json``.
        fps: Frame rate [Hz].
        camera_keys: Cameras read (the ``<key>`` of ``observation.images.<key>``), in dataset order.
        image_size: (H, W) [px] of every frame in :attr:`Episode.images`.
        episodes: Committed episodes, by ``episode_index``.
        digest: sha256 of ``info.json`` and the episodes tables (identifies the dataset's content).
    """

    root: Path
    schema: DatasetSchema
    fps: int
    camera_keys: tuple[str, ...]
    image_size: tuple[int, int]
    episodes: tuple[Episode, ...]
    digest: str

    @property
    def state_names(self) -> tuple[str, ...]:
        return self.schema.state_names

    @property
    def action_names(self) -> tuple[str, ...]:
        return self.schema.action_names

    @property
    def frames(self) -> int:
        return sum(e.length for e in self.episodes)


def image_size_for(height: int, width: int, target_width: int) -> tuple[int, int]:
    """(H, W) [px] of ``target_width`` wide keeping a camera's aspect ratio (H rounded, >= 8)."""
    if height < 1 or width < 1 or target_width < 8:
        raise PolicyError(f"cannot size policy images from a {width}x{height} camera to width {target_width}")
    return (max(8, round(target_width * height / width)), target_width)


def split_episodes(
    episodes: Sequence[Episode], val_fraction: float, seed: int
) -> tuple[list[Episode], list[Episode]]:
    """Split by episode (never frames of one episode on both sides): (train, val).

    At least one episode trains; validation gets ``round(n * val_fraction)`` episodes, at least
    one when ``val_fraction > 0`` and there are two or more episodes.
    """
    if not 0.0 <= val_fraction < 1.0:
        raise PolicyError(f"validation fraction must be in [0, 1), got {val_fraction}")
    order = np.random.default_rng(seed).permutation(len(episodes))
    n_val = min(max(round(len(episodes) * val_fraction), 1 if val_fraction > 0 else 0), len(episodes) - 1)
    n_val = max(n_val, 0)
    val = sorted(order[:n_val].tolist())
    train = sorted(order[n_val:].tolist())
    return [episodes[i] for i in train], [episodes[i] for i in val]


def read_dataset(
    root: str | os.PathLike[str],
    *,
    image_width: int = 96,
    image_size: tuple[int, int] | None = None,
    cameras: Sequence[str] | None = None,
    cache_dir: str | os.PathLike[str] | None = None,
    progress: Progress | None = None,
) -> PolicyDataset:
    """Read a LeRobot v3 export into memory, frames resized for a policy.

    Args:
        root: Dataset directory (``telerig export --format lerobot --out ROOT``).
        image_width: Policy image width [px]; the height keeps the first camera's aspect ratio.
        image_size: (H, W) [px] instead of ``image_width`` (e.g. a checkpoint's size).
        cameras: Camera keys to read (default: every camera of the dataset).
        cache_dir: Directory for the decoded-frames cache (``None``: decode every time).
        progress: ``progress(what, done, total)`` while decoding.

    Raises:
        PolicyError: One line: not a directory, not a LeRobot v3 dataset, a missing or damaged
            file, frames or video that do not match the metadata.
    """
    path = Path(root)
    if not path.is_dir():
        raise PolicyError(
            f"dataset {path} is not a directory; pass the --out of `telerig export --format lerobot`"
        )
    info = _read_info(path)
    schema = _read_schema(path)
    fps = _fps(path, info)
    keys = _camera_keys(path, info, schema, cameras)
    size = image_size or (
        image_size_for(schema.camera(keys[0]).height, schema.camera(keys[0]).width, image_width)
        if keys
        else (image_width, image_width)
    )
    rows, digest = _read_episode_rows(path, info, keys)
    vectors = _read_vectors(path, info, schema, rows)  # cheap checks before the long decode
    cached = _load_cache(cache_dir, digest, size, keys, len(rows))
    if cached is not None:
        images = cached
    else:
        images = {key: _decode_camera(path, key, rows, fps, size, progress) for key in keys}
        _save_cache(cache_dir, digest, size, images)
    episodes = tuple(
        Episode(
            index=int(row["episode_index"]),
            episode_id=str(row.get("telerig/episode_id") or ""),
            outcome=row.get("telerig/outcome"),
            state=state,
            action=action,
            images={key: images[key][i] for key in keys},
        )
        for i, (row, (state, action)) in enumerate(zip(rows, vectors, strict=True))
    )
    return PolicyDataset(
        root=path, schema=schema, fps=fps, camera_keys=keys, image_size=size, episodes=episodes, digest=digest
    )


# -- metadata -------------------------------------------------------------------------------------


def _read_info(root: Path) -> dict[str, Any]:
    info_path = root / INFO_PATH
    if not info_path.is_file():
        raise PolicyError(
            f"{root} is not a LeRobot dataset (no {INFO_PATH}); export one with "
            f"`telerig export --format lerobot --out {root}`"
        )
    size = info_path.stat().st_size
    if size > MAX_INFO_BYTES:
        raise PolicyError(
            f"{info_path} is {size / 2**20:.0f} MiB, more than LeRobot metadata ever is "
            f"({MAX_INFO_BYTES // 2**20} MiB); it is not a dataset's info.json, re-export the dataset"
        )
    try:
        info = json.loads(info_path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise PolicyError(f"{info_path} is unreadable ({_first_line(exc)}); re-export the dataset") from None
    if not isinstance(info, dict):
        raise PolicyError(f"{info_path} is not a JSON object; re-export the dataset")
    if info.get("codebase_version") != CODEBASE_VERSION:
        raise PolicyError(
            f"{root} is a LeRobot {info.get('codebase_version')!r} dataset; telerig train reads "
            f"{CODEBASE_VERSION} (re-export with telerig export --format lerobot)"
        )
    features = info.get("features")
    if not isinstance(features, dict) or STATE not in features or ACTION not in features:
        raise PolicyError(f"{info_path} lacks the {STATE} / {ACTION} features; re-export the dataset")
    total = info.get("total_episodes")
    if not isinstance(total, int) or total < 1:
        raise PolicyError(
            f"{info_path}: total_episodes is {total!r}; the dataset holds no episode to train on"
        )
    return info


def _read_schema(root: Path) -> DatasetSchema:
    schema_path = root / SCHEMA_PATH
    try:
        return DatasetSchema.loads(schema_path.read_bytes())
    except FileNotFoundError:
        raise PolicyError(
            f"{root} has no {SCHEMA_PATH}; it was not written by telerig export (re-export it)"
        ) from None
    except (OSError, ExportError) as exc:
        raise PolicyError(f"{schema_path}: {_first_line(exc)}") from None


def _fps(root: Path, info: Mapping[str, Any]) -> int:
    fps = info.get("fps")
    if not isinstance(fps, int) or fps <= 0:
        raise PolicyError(f"{root / INFO_PATH}: fps is {fps!r}, not a positive integer; re-export")
    return fps


def _camera_keys(
    root: Path, info: Mapping[str, Any], schema: DatasetSchema, wanted: Sequence[str] | None
) -> tuple[str, ...]:
    available = [
        key[len(IMAGES) :]
        for key, ft in info["features"].items()
        if key.startswith(IMAGES) and isinstance(ft, dict) and ft.get("dtype") == "video"
    ]
    if wanted is None:
        keys = available
    else:
        missing = [k for k in wanted if k not in available]
        if missing:
            raise PolicyError(
                f"camera {missing[0]!r} is not in {root}. Available: {', '.join(available) or 'none'}"
            )
        keys = list(wanted)
    for key in keys:
        try:
            schema.camera(key)
        except ExportError as exc:
            raise PolicyError(f"{root / SCHEMA_PATH}: {exc}; re-export the dataset") from None
    return tuple(keys)


def _read_episode_rows(
    root: Path, info: Mapping[str, Any], keys: Sequence[str]
) -> tuple[list[dict[str, Any]], str]:
    total = int(info["total_episodes"])
    files = sorted(root.glob("meta/episodes/chunk-*/file-*.parquet"))
    if not files:
        raise PolicyError(f"{root} has no meta/episodes/*.parquet; the export is incomplete (re-export it)")
    wanted = ["episode_index", "length", "data/chunk_index", "data/file_index"]
    for key in keys:
        wanted += [f"videos/{IMAGES}{key}/{c}" for c in ("chunk_index", "file_index", "from_timestamp")]
    optional = ["telerig/episode_id", "telerig/outcome"]
    digest = hashlib.sha256((root / INFO_PATH).read_bytes())
    rows: list[dict[str, Any]] = []
    for file in files:
        try:
            digest.update(file.read_bytes())
            columns = pq.read_schema(file).names
            absent = [c for c in wanted if c not in columns]
            if absent:
                raise PolicyError(f"{file} lacks column {absent[0]!r}; re-export the dataset")
            table = pq.read_table(file, columns=wanted + [c for c in optional if c in columns])
        except (OSError, pa.ArrowException) as exc:
            raise PolicyError(f"{file} is unreadable ({_first_line(exc)}); re-export the dataset") from None
        rows += table.to_pylist()
    rows = sorted((r for r in rows if int(r["episode_index"]) < total), key=lambda r: int(r["episode_index"]))
    if [int(r["episode_index"]) for r in rows] != list(range(total)):
        raise PolicyError(
            f"{root}/meta/episodes does not hold episodes 0..{total - 1} that info.json commits; re-export"
        )
    for row in rows:
        if not isinstance(row["length"], int) or row["length"] < 1:
            raise PolicyError(f"episode {row['episode_index']} of {root} has length {row['length']!r}")
    return rows, digest.hexdigest()


# -- state and action -----------------------------------------------------------------------------


def _read_vectors(
    root: Path, info: Mapping[str, Any], schema: DatasetSchema, rows: list[dict[str, Any]]
) -> list[tuple[Float32Array, Float32Array]]:
    dims = {STATE: len(schema.state_names), ACTION: len(schema.action_names)}
    out: dict[int, tuple[Float32Array, Float32Array]] = {}
    by_file: dict[tuple[int, int], list[dict[str, Any]]] = {}
    for row in rows:
        by_file.setdefault((int(row["data/chunk_index"]), int(row["data/file_index"])), []).append(row)
    for (chunk, file), eps in sorted(by_file.items()):
        rel = DATA_PATH.format(chunk_index=chunk, file_index=file)
        try:
            table = pq.read_table(root / rel, columns=["episode_index", "frame_index", STATE, ACTION])
        except FileNotFoundError:
            raise PolicyError(f"{root / rel} is missing; the export is incomplete (re-export it)") from None
        except (OSError, pa.ArrowException) as exc:
            raise PolicyError(f"{root / rel} is unreadable ({_first_line(exc)}); re-export it") from None
        episode_index = table["episode_index"].to_numpy()
        frame_index = table["frame_index"].to_numpy()
        arrays = {key: _matrix(table[key], dims[key], root / rel) for key in (STATE, ACTION)}
        for row in eps:
            ep = int(row["episode_index"])
            mask = episode_index == ep
            if int(mask.sum()) != row["length"]:
                raise PolicyError(
                    f"episode {ep}: {rel} holds {int(mask.sum())} frames, its length is {row['length']}; "
                    "re-export the dataset"
                )
            order = np.argsort(frame_index[mask], kind="stable")
            state, action = arrays[STATE][mask][order], arrays[ACTION][mask][order]
            if not (np.isfinite(state).all() and np.isfinite(action).all()):
                raise PolicyError(f"episode {ep}: {rel} holds NaN or inf state/action values; re-export it")
            if schema.normalized:  # --normalize export: back to physical units, as the runner works
                state, action = schema.denormalize(state, "state"), schema.denormalize(action, "action")
            out[ep] = (state.astype(np.float32), action.astype(np.float32))
    return [out[int(r["episode_index"])] for r in rows]


def _matrix(column: pa.ChunkedArray, dim: int, path: Path) -> Float32Array:
    """A fixed-size-list column as float32 (N, dim)."""
    array = column.combine_chunks()
    size = getattr(array.type, "list_size", None)
    if size != dim:
        raise PolicyError(f"{path}: a frame holds {size} values where the schema names {dim}; re-export")
    return np.asarray(array.flatten().to_numpy(zero_copy_only=False), dtype=np.float32).reshape(-1, dim)


# -- video ----------------------------------------------------------------------------------------


def _decode_camera(
    root: Path,
    key: str,
    rows: list[dict[str, Any]],
    fps: int,
    size: tuple[int, int],
    progress: Progress | None,
) -> list[UInt8Array]:
    """Every episode's frames of one camera, resized: one uint8 (F, H, W, 3) per episode row."""
    prefix = f"videos/{IMAGES}{key}"
    by_file: dict[tuple[int, int], list[int]] = {}
    for i, row in enumerate(rows):
        by_file.setdefault((int(row[f"{prefix}/chunk_index"]), int(row[f"{prefix}/file_index"])), []).append(
            i
        )
    out: list[UInt8Array | None] = [None] * len(rows)
    total = sum(int(r["length"]) for r in rows)
    done = 0
    for (chunk, file), members in sorted(by_file.items()):
        rel = VIDEO_PATH.format(video_key=IMAGES + key, chunk_index=chunk, file_index=file)
        spans = [(i, float(rows[i][f"{prefix}/from_timestamp"]), int(rows[i]["length"])) for i in members]
        for i, frames in _decode_file(root / rel, spans, fps, size):
            out[i] = frames
            done += frames.shape[0]
            if progress is not None:
                progress(f"decoding {key}", done, total)
    return [_filled(frames, root, key, i) for i, frames in enumerate(out)]


def _filled(frames: UInt8Array | None, root: Path, key: str, episode: int) -> UInt8Array:
    if frames is None:  # every member is yielded by _decode_file; this guards a logic slip only
        raise PolicyError(f"{root}: camera {key} has no frames for episode {episode}; re-export it")
    return frames


def _decode_file(
    path: Path, spans: list[tuple[int, float, int]], fps: int, size: tuple[int, int]
) -> list[tuple[int, UInt8Array]]:
    """Decode one MP4 front to back; return (row, frames) for each span (row, from_s, length)."""
    if not path.is_file():
        raise PolicyError(f"{path} is missing; the export is incomplete (re-export it)")
    h, w = size
    result = {i: np.zeros((n, h, w, 3), np.uint8) for i, _, n in spans}
    filled = {i: np.zeros(n, bool) for i, _, n in spans}
    starts = np.array([s for _, s, _ in spans])
    order = np.argsort(starts)
    pending: list[tuple[int, int, UInt8Array]] = []

    def flush() -> None:
        if not pending:
            return
        small = resize_rgb(np.stack([f for _, _, f in pending]), size)
        for (i, k, _), frame in zip(pending, small, strict=True):
            result[i][k] = frame
            filled[i][k] = True
        pending.clear()

    try:
        with av.open(str(path)) as container:
            stream = container.streams.video[0]
            stream.thread_type = "AUTO"
            for frame in container.decode(stream):
                if frame.pts is None:
                    continue
                t = float(frame.pts * frame.time_base)
                at = int(np.searchsorted(starts[order], t + _PTS_TOLERANCE_FRAMES / fps, side="right")) - 1
                if at < 0:
                    continue
                i, from_s, n = spans[int(order[at])]
                k = (t - from_s) * fps
                kk = round(k)
                if abs(k - kk) > _PTS_TOLERANCE_FRAMES or not 0 <= kk < n:
                    continue
                pending.append((i, kk, frame.to_ndarray(format="rgb24")))
                if len(pending) >= _RESIZE_BATCH:
                    flush()
            flush()
    except (av.FFmpegError, OSError, IndexError, ValueError) as exc:
        raise PolicyError(f"{path} is unreadable ({_first_line(exc)}); re-export the dataset") from None
    for i, from_s, n in spans:
        if not filled[i].all():
            missing = int(np.flatnonzero(~filled[i])[0])
            raise PolicyError(
                f"{path} has no frame at {from_s + missing / fps:.3f} s (frame {missing} of an episode of "
                f"{n}); the video is truncated or damaged, re-export the dataset"
            )
    return [(i, result[i]) for i, _, _ in spans]


# -- cache ----------------------------------------------------------------------------------------


def _cache_path(cache_dir: str | os.PathLike[str], digest: str, size: tuple[int, int]) -> Path:
    return Path(cache_dir) / f"frames-v{_CACHE_VERSION}-{digest[:16]}-{size[0]}x{size[1]}.npz"


def _load_cache(
    cache_dir: str | os.PathLike[str] | None,
    digest: str,
    size: tuple[int, int],
    keys: Sequence[str],
    episodes: int,
) -> dict[str, list[UInt8Array]] | None:
    if cache_dir is None:
        return None
    path = _cache_path(cache_dir, digest, size)
    if not path.is_file():
        return None
    try:
        with open(path, "rb") as f, np.load(f) as data:
            images = {key: [data[f"{key}/{i}"] for i in range(episodes)] for key in keys}
    except (OSError, KeyError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        _log.warning("frame cache %s unreadable (%s); decoding again", path, _first_line(exc))
        return None
    if any(a.dtype != np.uint8 or a.shape[1:] != (*size, 3) for frames in images.values() for a in frames):
        _log.warning("frame cache %s does not hold %s frames; decoding again", path, size)
        return None
    return images


def _save_cache(
    cache_dir: str | os.PathLike[str] | None,
    digest: str,
    size: tuple[int, int],
    images: Mapping[str, list[UInt8Array]],
) -> None:
    if cache_dir is None:
        return
    path = _cache_path(cache_dir, digest, size)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(tmp, "wb") as f:
            arrays: dict[str, Any] = {
                f"{key}/{i}": a for key, frames in images.items() for i, a in enumerate(frames)
            }
            np.savez(f, **arrays)
        os.replace(tmp, path)
    except OSError as exc:  # a cache that cannot be written only costs the next run a decode
        tmp.unlink(missing_ok=True)
        _log.warning("cannot write frame cache %s: %s", path, exc)


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return (text.splitlines()[0] if text else type(exc).__name__)[:200]
