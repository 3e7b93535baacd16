"""Policy checkpoints: one file holding a trained network and everything needed to run it.

Format (``torch.save`` of a dict of plain types and tensors, read back with
``torch.load(weights_only=True)``, which unpickles nothing but those)::

    {"format": "telerig-policy", "version": 1,
     "meta": "<JSON text>",                 # see Checkpoint: type, model config, names, stats, ...
     "state_dict": {name: tensor, ...},     # float32 CPU tensors of the network
     "sha256": "<64 hex>"}                  # content hash of meta + state_dict (see content_hash)

The content hash covers the metadata and every tensor's name, dtype, shape and bytes, not the
container (zip layout, pickle protocol), so it identifies *what the policy is*: rollout episodes
record ``id`` (its first 12 hex digits) and ``sha256``, and loading recomputes it, so a file
damaged on disk is refused with one line rather than run.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import os
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import torch

from telerig.errors import PolicyError
from telerig.policy.models import ModelConfig, PolicyType, build_model

__all__ = [
    "FORMAT",
    "FORMAT_VERSION",
    "MAX_CHECKPOINT_BYTES",
    "Checkpoint",
    "Normalization",
    "content_hash",
    "load_checkpoint",
    "save_checkpoint",
    "tiny_for_tests",
]

FORMAT = "telerig-policy"
FORMAT_VERSION = 1
#: Smallest std used to normalize an entry [its unit]: a joint that never moved in the
#: demonstrations (or a gripper always open) must not blow up to inf / NaN.
MIN_STD = 1e-3

#: Largest checkpoint file read [bytes]. telerig's networks are 0.1-5 M parameters (< 20 MB); a
#: file far larger is something else, and torch.load would read all of it into memory first.
MAX_CHECKPOINT_BYTES = 2**30

Float32Array = npt.NDArray[np.float32]


@dataclass(frozen=True)
class Normalization:
    """Per-entry mean and std of state and action [their physical units], shape (S,) / (A,).

    ``normalize_*`` maps physical values to zero mean and unit std; ``denormalize_action`` inverts
    it for the network's output. Std is floored at :data:`MIN_STD`.

    An action entry may be *relative*: the network predicts it as an offset from a state entry of
    the observation it acts on (``relative_to[i]`` is that state index, -1 for an absolute entry;
    empty: every entry absolute, as checkpoints before relative actions). Joint targets a few
    frames ahead differ from the measured joints by a few hundredths of a radian while the joints
    range over radians: predicted absolutely, that motion is a rounding error of the output and a
    small demonstration set teaches a policy to repeat the state it sees (it stands still).
    Offsets normalized by their own spread make the motion what the network learns. The action
    mean and std of a relative entry are those of the offsets.
    """

    state_mean: Float32Array
    state_std: Float32Array
    action_mean: Float32Array
    action_std: Float32Array
    relative_to: tuple[int, ...] = ()

    @classmethod
    def fit(
        cls,
        state: npt.ArrayLike,
        action: npt.ArrayLike,
        relative_to: Sequence[int] = (),
        reference: npt.ArrayLike | None = None,
    ) -> Normalization:
        """Statistics of training frames: ``state`` (N, S) and ``action`` (..., A).

        With ``relative_to``, ``reference`` holds the state each action is taken from, broadcast
        against ``action`` (e.g. (N, 1, S) for chunks (N, C, A)); the relative entries' statistics
        are those of the offsets.
        """
        s = np.asarray(state, dtype=np.float64)
        a = np.asarray(action, dtype=np.float64)
        norm = cls(
            state_mean=s.mean(axis=0).astype(np.float32),
            state_std=np.maximum(s.std(axis=0), MIN_STD).astype(np.float32),
            action_mean=np.zeros(a.shape[-1], np.float32),
            action_std=np.ones(a.shape[-1], np.float32),
            relative_to=tuple(int(i) for i in relative_to),
        )
        norm._check_relative(s.shape[-1], a.shape[-1])
        if norm.relative_to:
            if reference is None:
                raise PolicyError("relative actions need the reference state of each action")
            a = a - norm._base(reference)
        flat = a.reshape(-1, a.shape[-1])
        return cls(
            state_mean=norm.state_mean,
            state_std=norm.state_std,
            action_mean=flat.mean(axis=0).astype(np.float32),
            action_std=np.maximum(flat.std(axis=0), MIN_STD).astype(np.float32),
            relative_to=norm.relative_to,
        )

    def _check_relative(self, state_dim: int, action_dim: int) -> None:
        if not self.relative_to:
            return
        if len(self.relative_to) != action_dim or any(not -1 <= i < state_dim for i in self.relative_to):
            raise PolicyError(
                f"relative_to must give one state index in [-1, {state_dim}) per action entry "
                f"({action_dim}), got {list(self.relative_to)}"
            )

    def _base(self, state: npt.ArrayLike | None) -> npt.NDArray[np.float64] | float:
        """What the relative entries are offsets from: (..., A), 0 for absolute entries."""
        if not self.relative_to:
            return 0.0
        if state is None:
            raise PolicyError("this policy's actions are relative to the state: pass the state")
        s = np.asarray(state, dtype=np.float64)
        index = np.asarray(self.relative_to)
        base = s[..., np.maximum(index, 0)]
        return np.where(index >= 0, base, 0.0)

    def normalize_state(self, state: npt.ArrayLike) -> Float32Array:
        """(..., S) physical → normalized."""
        return ((np.asarray(state, dtype=np.float32) - self.state_mean) / self.state_std).astype(np.float32)

    def normalize_action(self, action: npt.ArrayLike, state: npt.ArrayLike | None = None) -> Float32Array:
        """(..., A) physical → normalized; ``state`` (broadcast against ``action``) for relative entries."""
        a = np.asarray(action, dtype=np.float64) - self._base(state)
        return ((a - self.action_mean) / self.action_std).astype(np.float32)

    def denormalize_action(self, action: npt.ArrayLike, state: npt.ArrayLike | None = None) -> Float32Array:
        """(..., A) normalized → physical units; ``state`` as for :meth:`normalize_action`."""
        a = np.asarray(action, dtype=np.float64) * self.action_std + self.action_mean
        return (a + self._base(state)).astype(np.float32)

    def to_json(self) -> dict[str, list[float] | list[int]]:
        out: dict[str, list[float] | list[int]] = {
            "state_mean": self.state_mean.tolist(),
            "state_std": self.state_std.tolist(),
            "action_mean": self.action_mean.tolist(),
            "action_std": self.action_std.tolist(),
        }
        if self.relative_to:
            out["relative_to"] = list(self.relative_to)
        return out

    @classmethod
    def from_json(cls, data: Any, state_dim: int, action_dim: int) -> Normalization:
        keys = ("state_mean", "state_std", "action_mean", "action_std")
        try:
            arrays = {k: np.asarray(data[k], dtype=np.float32) for k in keys}
            relative = data.get("relative_to", [])
            if not isinstance(relative, list) or any(type(i) is not int for i in relative):
                raise TypeError("relative_to is not a list of integers")
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise PolicyError(f"checkpoint normalization is invalid ({exc!r}); retrain it") from None
        for key, arr in arrays.items():
            want = state_dim if key.startswith("state") else action_dim
            if arr.shape != (want,) or not np.isfinite(arr).all():
                raise PolicyError(f"checkpoint normalization {key} is not {want} finite values; retrain it")
            if key.endswith("std") and (arr <= 0).any():
                raise PolicyError(f"checkpoint normalization {key} has a value <= 0; retrain it")
        norm = cls(**arrays, relative_to=tuple(relative))
        norm._check_relative(state_dim, action_dim)
        return norm


@dataclass(frozen=True)
class Checkpoint:
    """A trained (or freshly initialised) policy and what it needs to run.

    Attributes:
        model: Network type and size (``model.policy_type`` is ``bc`` or ``act_lite``).
        state_dict: The network's tensors (CPU float32).
        normalization: State/action statistics of the training set [physical units].
        state_names: Entry names of the state vector the policy reads, in order (the dataset's
            ``observation.state`` names: joint names, ``gripper``, ...).
        action_names: Entry names of one action, in order (the dataset's ``action`` names).
        fps: Rate [Hz] of the dataset frames: consecutive actions of a chunk are 1/fps s apart.
        rig: Rig name of the training dataset.
        rig_fingerprint: Rig fingerprint of the training dataset ("" when unknown).
        training: Free JSON about the run (dataset path, steps, losses, seconds); part of the hash.
    """

    model: ModelConfig
    state_dict: Mapping[str, torch.Tensor]
    normalization: Normalization
    state_names: tuple[str, ...]
    action_names: tuple[str, ...]
    fps: float
    rig: str = ""
    rig_fingerprint: str = ""
    training: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if len(self.state_names) != self.model.state_dim:
            raise PolicyError(
                f"checkpoint has {len(self.state_names)} state names for a state of {self.model.state_dim}"
            )
        if len(self.action_names) != self.model.action_dim:
            raise PolicyError(
                f"checkpoint has {len(self.action_names)} action names for an action of "
                f"{self.model.action_dim}"
            )
        if not (math.isfinite(self.fps) and self.fps > 0):
            raise PolicyError(f"checkpoint fps must be > 0 Hz, got {self.fps}")

    @property
    def policy_type(self) -> PolicyType:
        return self.model.policy_type

    @property
    def camera_keys(self) -> tuple[str, ...]:
        return self.model.camera_keys

    @property
    def image_size(self) -> tuple[int, int]:
        """(H, W) [px] of the images the policy takes."""
        return self.model.image_size

    @property
    def chunk_size(self) -> int:
        return self.model.chunk_size

    def meta_json(self) -> str:
        """The metadata as canonical JSON text (sorted keys): what the hash and the file hold."""
        meta = {
            "model": self.model.to_json(),
            "normalization": self.normalization.to_json(),
            "state_names": list(self.state_names),
            "action_names": list(self.action_names),
            "fps": self.fps,
            "rig": self.rig,
            "rig_fingerprint": self.rig_fingerprint,
            "training": dict(self.training),
        }
        try:
            return json.dumps(meta, sort_keys=True, separators=(",", ":"), allow_nan=False)
        except (TypeError, ValueError) as exc:
            raise PolicyError(f"checkpoint metadata is not plain JSON: {exc}") from None

    @property
    def sha256(self) -> str:
        """Content hash (64 hex) of metadata and weights; see :func:`content_hash`."""
        return content_hash(self.meta_json(), self.state_dict)

    @property
    def id(self) -> str:
        """Short id: the first 12 hex digits of :attr:`sha256` (what rollout episodes show)."""
        return self.sha256[:12]


def content_hash(meta_json: str, state_dict: Mapping[str, torch.Tensor]) -> str:
    """sha256 over the metadata JSON and, in name order, each tensor's name, dtype, shape and bytes."""
    h = hashlib.sha256()
    h.update(FORMAT.encode() + b"\0" + str(FORMAT_VERSION).encode() + b"\0")
    h.update(meta_json.encode())
    for name in sorted(state_dict):
        tensor = state_dict[name].detach().cpu().contiguous()
        h.update(f"\0{name}\0{tensor.dtype}\0{tuple(tensor.shape)}\0".encode())
        h.update(tensor.view(torch.uint8).numpy().tobytes() if tensor.numel() else b"")
    return h.hexdigest()


def save_checkpoint(checkpoint: Checkpoint, path: str | os.PathLike[str]) -> Path:
    """Write ``checkpoint`` to ``path`` atomically (temp file, fsync, rename); returns the path.

    A crash mid-write leaves the previous file (if any) intact, never a torn checkpoint.
    """
    path = Path(path)
    state = {k: v.detach().cpu().contiguous().clone() for k, v in checkpoint.state_dict.items()}
    meta = checkpoint.meta_json()
    payload = {
        "format": FORMAT,
        "version": FORMAT_VERSION,
        "meta": meta,
        "state_dict": state,
        "sha256": content_hash(meta, state),
    }
    buffer = io.BytesIO()
    torch.save(payload, buffer)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        try:
            os.fchmod(fd, 0o644)  # mkstemp makes 0600; a lab shares its checkpoints
            with os.fdopen(fd, "wb") as f:
                f.write(buffer.getbuffer())
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
    except OSError as exc:
        raise PolicyError(f"cannot write checkpoint {path}: {exc.strerror or exc}") from None
    return path


def load_checkpoint(path: str | os.PathLike[str]) -> Checkpoint:
    """Read and verify a checkpoint written by :func:`save_checkpoint`.

    Raises:
        PolicyError: One line: missing, not a telerig checkpoint, another format version, damaged
            (content hash mismatch), or weights that do not fit the model config.
    """
    path = Path(path)
    if not path.is_file():
        raise PolicyError(f"checkpoint {path} does not exist or is not a file; pass what telerig train wrote")
    size = path.stat().st_size
    if size > MAX_CHECKPOINT_BYTES:
        raise PolicyError(
            f"checkpoint {path} is {size / 2**30:.1f} GiB, more than a telerig policy can be "
            f"({MAX_CHECKPOINT_BYTES // 2**30} GiB); it is not a telerig checkpoint"
        )
    try:
        raw = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch.load raises anything from zipfile/pickle/RuntimeError on damage
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise PolicyError(
            f"checkpoint {path} is unreadable ({first[:160]}); it is damaged or not a telerig policy"
        ) from None
    if not isinstance(raw, dict) or raw.get("format") != FORMAT:
        raise PolicyError(f"{path} is not a telerig policy checkpoint (no format {FORMAT!r})")
    if raw.get("version") != FORMAT_VERSION:
        raise PolicyError(
            f"checkpoint {path} has format version {raw.get('version')!r}, this telerig reads "
            f"{FORMAT_VERSION}; retrain with this telerig"
        )
    meta_text, state, digest = raw.get("meta"), raw.get("state_dict"), raw.get("sha256")
    if (
        not isinstance(meta_text, str)
        or not isinstance(digest, str)
        or not isinstance(state, dict)
        or not all(isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in state.items())
    ):
        raise PolicyError(f"checkpoint {path} lacks its metadata, weights or hash; it is damaged")
    if content_hash(meta_text, state) != digest:
        raise PolicyError(f"checkpoint {path} does not match its content hash; the file is damaged")
    return _from_meta(path, meta_text, state)


def _from_meta(path: Path, meta_text: str, state: dict[str, torch.Tensor]) -> Checkpoint:
    try:
        meta = json.loads(meta_text)
        model = ModelConfig.from_json(meta["model"])
        checkpoint = Checkpoint(
            model=model,
            state_dict=state,
            normalization=Normalization.from_json(meta["normalization"], model.state_dim, model.action_dim),
            state_names=tuple(str(n) for n in meta["state_names"]),
            action_names=tuple(str(n) for n in meta["action_names"]),
            fps=float(meta["fps"]),
            rig=str(meta.get("rig", "")),
            rig_fingerprint=str(meta.get("rig_fingerprint", "")),
            training=dict(meta.get("training", {})),
        )
    except PolicyError as exc:
        raise PolicyError(f"checkpoint {path}: {exc}") from None
    except (KeyError, TypeError, ValueError) as exc:
        raise PolicyError(f"checkpoint {path} has invalid metadata ({exc!r}); retrain it") from None
    try:
        build_model(model).load_state_dict(state)
    except RuntimeError as exc:
        first = str(exc).strip().splitlines()[0]
        raise PolicyError(f"checkpoint {path}: weights do not fit its model config ({first[:160]})") from None
    return checkpoint


def tiny_for_tests(
    path: str | os.PathLike[str],
    policy_type: PolicyType = "bc",
    *,
    state_names: Sequence[str] = ("j0", "j1", "j2", "j3", "j4", "j5", "gripper"),
    action_names: Sequence[str] | None = None,
    camera_keys: Sequence[str] = ("scene",),
    image_size: tuple[int, int] = (24, 32),
    chunk_size: int = 4,
    fps: float = 30.0,
    seed: int = 0,
    rig: str = "",
    rig_fingerprint: str = "",
) -> Checkpoint:
    """Write a real, randomly initialised (untrained) checkpoint of the real network; return it.

    For tests of the runner and of policy rollout: small (about 30k parameters), loads in
    milliseconds, same file format and code path as a trained one. Normalization is the identity
    (mean 0, std 1), so actions come out in the network's raw output range.
    """
    actions = tuple(action_names if action_names is not None else state_names)
    config = ModelConfig(
        policy_type=policy_type,
        state_dim=len(state_names),
        action_dim=len(actions),
        camera_keys=tuple(camera_keys),
        image_size=image_size,
        chunk_size=chunk_size,
        channels=(8, 16),
        keypoints=8,
        hidden=32,
        layers=1,
        heads=2,
    )
    generator_state = torch.random.get_rng_state()
    try:
        torch.manual_seed(seed)
        model = build_model(config)
    finally:
        torch.random.set_rng_state(generator_state)
    s, a = len(state_names), len(actions)
    checkpoint = Checkpoint(
        model=config,
        state_dict=model.state_dict(),
        normalization=Normalization(
            state_mean=np.zeros(s, np.float32),
            state_std=np.ones(s, np.float32),
            action_mean=np.zeros(a, np.float32),
            action_std=np.ones(a, np.float32),
        ),
        state_names=tuple(state_names),
        action_names=actions,
        fps=fps,
        rig=rig,
        rig_fingerprint=rig_fingerprint,
        training={"untrained": True, "seed": seed},
    )
    save_checkpoint(checkpoint, path)
    return checkpoint
