"""robomimic export: one HDF5 file, ``<out>/robomimic.hdf5``, in the layout robomimic's
``SequenceDataset`` and its scripts read (robomimic docs, "Dataset Structure").

Layout (N frames in a demo, S state and A action entries)::

    /data                      attrs: total (frames in all demos), env_args (JSON: env_name, type,
                               env_kwargs), telerig_schema (the robot_schema.json text)
    /data/demo_<i>             attrs: num_samples, episode_id, task, operator, outcome, quality
    /data/demo_<i>/obs/state           float32 (N, S)  the whole state vector (names in attrs)
    /data/demo_<i>/obs/<robot>_<part>  float32 (N, k)  each named part of it (``arm0_joints``...)
    /data/demo_<i>/obs/<camera>_image  uint8 (N, H, W, 3) RGB, channel-last as robomimic expects
    /data/demo_<i>/next_obs/<key>      obs shifted by one frame, the last repeated: HDF5 virtual
                                       datasets over ``obs`` (no second copy of the images)
    /data/demo_<i>/actions     float32 (N, A)
    /data/demo_<i>/rewards     float32 (N,)  1 at the last frame of a demo marked success, else 0
    /data/demo_<i>/dones       uint8 (N,)    1 at the last frame
    /data/demo_<i>/timestamp   float64 (N,)  [s] from the first frame (robomimic ignores it)
    /data/demo_<i>/language/subtask, instruction   utf-8 (N,) per frame, attrs: segments (JSON);
                               only for an episode with segments (see :mod:`telerig.export.hdf5`)
    /mask/<filter_key>         demo names (bytes): train, valid, success, passed_qa, their
                               ``<key>_train`` / ``<key>_valid`` halves, and ``gate_<name>``
                               (the demos that quality gate did not fail: passed, or not
                               applicable, like the fall gate on a fixed arm)

``env_args.type`` is robomimic's robosuite type (1) and ``env_name`` the rig: telerig's simulated
robots are robosuite models, but ``env_kwargs`` (rig, fingerprint, rate, robots) build no robosuite
environment, so train with rollouts off. robomimic expects actions in [-1, 1]: export with
``--normalize``, or set ``train.action_config["actions"]["normalization"] = "min_max"``.

The train/valid split is stable: a demo keeps its half on every append (a validation demo never
leaks into training); a new one goes to ``valid`` when a hash of its episode id falls below
:data:`VALID_RATIO`, and while ``valid`` is empty the newest new demo of a file of two or more goes
there.

Crash safety: an append works on a copy (``<out>/.tmp-<pid>/``; a reflink where the filesystem has
them) that replaces ``robomimic.hdf5`` by one rename once complete and synced, so a killed export
leaves the previous file as it was. An append therefore costs a copy of the existing file.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import shutil
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import h5py
import numpy as np
from pydantic import JsonValue

from telerig.errors import ExportError
from telerig.export.base import ValidationReport, write_atomic
from telerig.export.frames import EpisodeFrames
from telerig.export.hdf5 import (
    check_images,
    check_timestamps,
    check_vector,
    episode_gates,
    fsync_dir,
    scratch_dir,
    write_images,
    write_language,
)
from telerig.export.schema import SCHEMA_FILE, DatasetSchema

if TYPE_CHECKING:
    from telerig.export.config import RobomimicExportConfig

__all__ = ["DATASET_FILE", "ENV_TYPE", "VALID_RATIO", "RobomimicExporter", "obs_keys"]

#: The dataset file inside the output directory.
DATASET_FILE = "robomimic.hdf5"
#: ``robomimic.envs.env_base.EnvType.ROBOSUITE_TYPE``.
ENV_TYPE = 1
#: Share of demos in the ``valid`` filter key (robomimic's split_train_val.py default, 0.1).
VALID_RATIO = 0.1
#: Filter keys from each episode's labels (besides train / valid).
_LABEL_KEYS = ("success", "passed_qa")
#: ``FICLONE`` ioctl: share the file's extents instead of copying its bytes (btrfs, XFS).
_FICLONE = 0x40049409

Demo = dict[str, Any]


def obs_keys(schema: DatasetSchema) -> dict[str, tuple[int, int] | None]:
    """Observation key → [start, stop) columns of the state vector, ``None`` for an image key."""
    keys: dict[str, tuple[int, int] | None] = {"state": (0, len(schema.state))}
    for part, span in schema.parts("state").items():
        keys[part.replace(".", "_")] = span
    for cam in schema.cameras:
        keys[f"{cam.key}_image"] = None
    return keys


class RobomimicExporter:
    """Writes and validates the robomimic dataset file (exporter ``robomimic``)."""

    format: ClassVar[str] = "robomimic"

    def __init__(self, config: RobomimicExportConfig) -> None:
        self.config = config

    def schema_path(self, out: Path) -> Path:
        """``<out>/robot_schema.json``."""
        return Path(out) / SCHEMA_FILE

    def existing_episodes(self, out: Path) -> set[str]:
        """Episode ids of the demos in ``<out>/robomimic.hdf5``."""
        path = Path(out) / DATASET_FILE
        if not path.is_file():
            return set()
        try:
            with h5py.File(path, "r") as f:
                return {str(g.attrs["episode_id"]) for g in f["data"].values()}
        except (OSError, KeyError) as exc:
            raise ExportError(f"{path} is unreadable ({exc}); export into a new --out directory") from None

    def write(
        self,
        out: Path,
        schema: DatasetSchema,
        episodes: Iterable[EpisodeFrames],
        progress: Callable[[EpisodeFrames], None],
    ) -> int:
        """Add the episodes as new demos (a new file or a copy of the existing one, renamed over it
        when complete); return the frames written.

        Raises:
            ExportError: A video cannot be decoded, or the disk refused a write.
        """
        out = Path(out)
        final = out / DATASET_FILE
        write_atomic(self.schema_path(out), schema.dumps())
        frames = 0
        with scratch_dir(out) as tmp:
            work = tmp / DATASET_FILE
            try:
                if final.is_file():
                    _clone(final, work)
                with h5py.File(work, "a") as f:
                    data = f.require_group("data")
                    before = len(data)
                    for episode in episodes:
                        _write_demo(data, f"demo_{_next_index(data)}", episode)
                        frames += episode.length
                        progress(episode)
                    if len(data) == before:
                        return 0
                    _dataset_attrs(data, schema)
                    _write_masks(f, before)
                with open(work, "rb") as synced:
                    os.fsync(synced.fileno())
                os.replace(work, final)
                fsync_dir(out)
            except OSError as exc:
                raise ExportError(f"{final}: cannot write ({exc}); free disk space and re-run") from None
        return frames

    def validate(self, out: Path) -> ValidationReport:
        """Re-read the file the way robomimic does: ``/data`` attributes, every demo's
        ``num_samples`` against its datasets, action dimension, images, masks naming demos."""
        out = Path(out)
        try:
            schema = DatasetSchema.loads(self.schema_path(out).read_bytes())
        except FileNotFoundError:
            return ValidationReport(0, 0, (f"{SCHEMA_FILE} is missing; re-run the export",))
        except ExportError as exc:
            return ValidationReport(0, 0, (str(exc),))
        path = out / DATASET_FILE
        try:
            with h5py.File(path, "r", swmr=True, libver="latest") as f:
                return _check_file(f, schema)
        except (OSError, KeyError, ValueError) as exc:
            return ValidationReport(0, 0, (f"{DATASET_FILE}: cannot read it ({exc}); re-run the export",))


# --- writing -------------------------------------------------------------------------------------


def _next_index(data: Any) -> int:
    used = [int(name.removeprefix("demo_")) for name in data if name.removeprefix("demo_").isdigit()]
    return max(used, default=-1) + 1


def _write_demo(data: Any, name: str, episode: EpisodeFrames) -> None:
    schema, n = episode.schema, episode.length
    demo = data.create_group(name)
    demo.attrs["num_samples"] = n
    demo.attrs["episode_id"] = episode.episode_id
    demo.attrs["task"] = episode.task
    demo.attrs["operator"] = episode.manifest.operator
    demo.attrs["outcome"] = episode.outcome or ""
    demo.attrs["quality"] = float("nan") if episode.quality is None else episode.quality
    demo.attrs["gates"] = json.dumps(episode_gates(episode))
    obs = demo.create_group("obs")
    for key, span in obs_keys(schema).items():
        if span is None:
            camera = key.removesuffix("_image")
            write_images(obs, key, episode.cameras[camera], n)
            continue
        values = obs.create_dataset(key, data=episode.state[:, span[0] : span[1]])
        values.attrs["names"] = list(schema.state_names[span[0] : span[1]])
    _next_obs(demo, obs, n)
    actions = demo.create_dataset("actions", data=episode.action)
    actions.attrs["names"] = list(schema.action_names)
    rewards = np.zeros(n, dtype=np.float32)
    if episode.outcome == "success":
        rewards[-1] = 1.0
    demo.create_dataset("rewards", data=rewards)
    dones = np.zeros(n, dtype=np.uint8)
    dones[-1] = 1
    demo.create_dataset("dones", data=dones)
    demo.create_dataset("timestamp", data=episode.timestamp).attrs["unit"] = "s"
    write_language(demo, episode)


def _next_obs(demo: Any, obs: Any, n: int) -> None:
    """``next_obs/<key>[t] = obs/<key>[min(t + 1, n - 1)]`` as virtual datasets in the same file."""
    group = demo.create_group("next_obs")
    for key, source in obs.items():
        layout = h5py.VirtualLayout(shape=source.shape, dtype=source.dtype)
        vsource = h5py.VirtualSource(".", source.name, shape=source.shape)
        if n > 1:
            layout[: n - 1] = vsource[1:n]
        layout[n - 1] = vsource[n - 1]
        shifted = group.create_virtual_dataset(key, layout)
        for attr, value in source.attrs.items():
            shifted.attrs[attr] = value


def _dataset_attrs(data: Any, schema: DatasetSchema) -> None:
    data.attrs["total"] = int(sum(int(g.attrs["num_samples"]) for g in data.values()))
    data.attrs["env_args"] = json.dumps(
        {
            "env_name": schema.rig,
            "type": ENV_TYPE,
            "env_kwargs": {
                "telerig_rig": schema.rig,
                "telerig_fingerprint": schema.fingerprint,
                "control_freq": schema.fps,
                "robots": dict(schema.robots),
                "obs_keys": list(obs_keys(schema)),
                "action_names": list(schema.action_names),
                "normalized": schema.normalized,
            },
        }
    )
    data.attrs["telerig_schema"] = schema.dumps()


def _write_masks(f: Any, before: int) -> None:
    """Every filter key, rewritten from the demos' labels; train/valid membership of the demos that
    were already there is kept."""
    data = f["data"]
    demos = sorted(data, key=lambda d: int(d.removeprefix("demo_")))
    old_valid = set(_mask(f, "valid"))
    old = demos[:before]
    new = demos[before:]
    valid = [d for d in old if d in old_valid] + [d for d in new if _hash_fraction(data[d]) < VALID_RATIO]
    if not valid and new and len(demos) >= 2:
        valid = [new[-1]]
    keys: dict[str, list[str]] = {"valid": valid, "train": [d for d in demos if d not in valid]}
    labels: dict[str, list[str]] = {k: [] for k in _LABEL_KEYS}
    for d in demos:
        gates = json.loads(str(data[d].attrs["gates"]))
        if data[d].attrs["outcome"] == "success":
            labels["success"].append(d)
        if gates.get("passed") is True:
            labels["passed_qa"].append(d)
        for gate, passed in gates.get("gates", {}).items():
            labels.setdefault(f"gate_{gate}", [])
            if passed is not False:  # passed, or not applicable (no fall gate on a fixed arm)
                labels[f"gate_{gate}"].append(d)
    for label, members in labels.items():
        keys[label] = members
        keys[f"{label}_train"] = [d for d in members if d not in valid]
        keys[f"{label}_valid"] = [d for d in members if d in valid]
    mask = f.require_group("mask")
    for key, members in keys.items():
        if key in mask:
            del mask[key]
        mask.create_dataset(key, data=np.array(members, dtype="S"), shape=(len(members),), dtype="S64")


def _mask(f: Any, key: str) -> list[str]:
    if f"mask/{key}" not in f:
        return []
    return [bytes(b).decode() for b in f[f"mask/{key}"][()]]


def _hash_fraction(demo: Any) -> float:
    """A stable number in [0, 1) from the demo's episode id (its train/valid draw)."""
    digest = hashlib.sha256(str(demo.attrs["episode_id"]).encode()).digest()
    return int.from_bytes(digest[:8], "big") / 2**64


def _clone(src: Path, dst: Path) -> None:
    """Copy ``src`` to ``dst``: a reflink (no bytes copied) where the filesystem has them."""
    with open(src, "rb") as fin, open(dst, "wb") as fout:
        try:
            fcntl.ioctl(fout.fileno(), _FICLONE, fin.fileno())
            return
        except OSError:
            pass
        shutil.copyfileobj(fin, fout, 16 * 1024 * 1024)


# --- validation ----------------------------------------------------------------------------------


def _check_file(f: Any, schema: DatasetSchema) -> ValidationReport:
    if "data" not in f:
        return ValidationReport(0, 0, ("/data is missing; re-run the export",))
    data = f["data"]
    problems: list[str] = []
    for attr in ("total", "env_args"):
        if attr not in data.attrs:
            problems.append(f"/data lacks the {attr!r} attribute robomimic reads")
    if "env_args" in data.attrs:
        problems += _check_env_args(str(data.attrs["env_args"]))
    frames = 0
    for name in data:
        found, n = _check_demo(data[name], schema)
        problems += [f"/data/{name}: {p}" for p in found]
        frames += n
    if "total" in data.attrs and int(data.attrs["total"]) != frames:
        problems.append(f"/data total is {int(data.attrs['total'])}, the demos hold {frames} samples")
    problems += _check_masks(f, set(data))
    return ValidationReport(len(data), frames, tuple(problems))


def _check_env_args(text: str) -> list[str]:
    try:
        env: JsonValue = json.loads(text)
    except json.JSONDecodeError:
        return ["/data env_args is not JSON"]
    if not isinstance(env, dict) or not {"env_name", "type", "env_kwargs"} <= set(env):
        return ["/data env_args lacks env_name, type or env_kwargs"]
    return []


def _check_demo(demo: Any, schema: DatasetSchema) -> tuple[list[str], int]:
    if "num_samples" not in demo.attrs:
        return ["lacks the num_samples attribute"], 0
    n = int(demo.attrs["num_samples"])
    if n < 1:
        return [f"num_samples is {n}; robomimic needs at least 1"], 0
    missing = [k for k in ("actions", "rewards", "dones", "obs", "next_obs") if k not in demo]
    if missing:
        return [f"lacks {', '.join(missing)}"], n
    problems = check_vector(demo["actions"], len(schema.action), n, "actions", "DoF")
    if schema.normalized:
        actions = demo["actions"][()]
        if actions.size and (float(actions.min()) < -1.0 or float(actions.max()) > 1.0):
            problems.append("normalized actions leave [-1, 1]")
    for key in ("rewards", "dones"):
        if demo[key].shape != (n,):
            problems.append(f"{key} has shape {demo[key].shape}, expected ({n},)")
    if "timestamp" in demo:
        problems += check_timestamps(demo["timestamp"][()], "timestamp")
    for key, span in obs_keys(schema).items():
        for group in ("obs", "next_obs"):
            if key not in demo[group]:
                problems.append(f"{group}/{key} is missing")
                continue
            values = demo[group][key]
            if span is None:
                camera = schema.camera(key.removesuffix("_image"))
                problems += check_images(values, camera.shape, n, f"{group}/{key}")
            else:
                problems += check_vector(values, span[1] - span[0], n, f"{group}/{key}", "entries")
    return problems, n


def _check_masks(f: Any, demos: set[str]) -> list[str]:
    if "mask" not in f:
        return ["/mask is missing (train/valid filter keys)"]
    problems: list[str] = []
    for key in f["mask"]:
        unknown = sorted(set(_mask(f, key)) - demos)
        if unknown:
            problems.append(f"/mask/{key} names {unknown[0]}, which is not in /data")
    train, valid = set(_mask(f, "train")), set(_mask(f, "valid"))
    if train & valid:
        problems.append(f"{sorted(train & valid)[0]} is in both mask/train and mask/valid")
    if train | valid != demos:
        problems.append(f"mask/train and mask/valid cover {len(train | valid)} of {len(demos)} demos")
    return problems
