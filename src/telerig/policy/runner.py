"""Run a policy checkpoint: physical state + camera frames in, a chunk of physical actions out.

:func:`load_policy` reads a checkpoint (:mod:`telerig.policy.checkpoint`) into a
:class:`PolicyRunner`. ``runner.act(state, images)`` is deterministic (eval mode, no dropout, no
sampling; one torch thread by default so results do not depend on the host's core count) and
thread-compatible but not thread-safe: a rollout worker owns one runner.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import torch

from telerig.errors import PolicyError
from telerig.policy.checkpoint import Checkpoint, load_checkpoint
from telerig.policy.images import resize_rgb, to_tensor
from telerig.policy.models import PolicyType, build_model

__all__ = ["PolicyRunner", "PolicySpec", "load_policy"]

Float32Array = npt.NDArray[np.float32]


@dataclass(frozen=True, slots=True)
class PolicySpec:
    """What a policy reads and writes; a rollout binds robot state and cameras from it.

    Attributes:
        policy_type: ``bc`` or ``act_lite``.
        state_names: Entries of the state vector ``act`` takes, in order (joint names, ``gripper``).
        action_names: Entries of one action ``act`` returns, in order.
        camera_keys: Cameras ``act`` needs, one RGB image each.
        image_size: (H, W) [px] the network sees; other sizes are resized to it.
        fps: Dataset rate [Hz]: action ``k`` of a chunk is meant for ``k / fps`` s after the
            observation.
        chunk_size: Actions per ``act`` call.
        checkpoint_id: Short content id (12 hex) to record with rollout episodes.
        checkpoint_sha256: Full content hash (64 hex).
        rig: Rig name of the training data.
        rig_fingerprint: Rig fingerprint of the training data ("" when unknown).
    """

    policy_type: PolicyType
    state_names: tuple[str, ...]
    action_names: tuple[str, ...]
    camera_keys: tuple[str, ...]
    image_size: tuple[int, int]
    fps: float
    chunk_size: int
    checkpoint_id: str
    checkpoint_sha256: str
    rig: str
    rig_fingerprint: str

    @property
    def state_dim(self) -> int:
        return len(self.state_names)

    @property
    def action_dim(self) -> int:
        return len(self.action_names)


class PolicyRunner:
    """A loaded policy. Build with :func:`load_policy` (or from a :class:`Checkpoint` in memory).

    Args:
        checkpoint: The policy.
        threads: torch intra-op threads (process-wide setting). 1 by default: a rollout worker
            shares the host with the control loop, and one thread makes results identical on any
            machine. ``None`` leaves torch's setting alone.
    """

    def __init__(self, checkpoint: Checkpoint, threads: int | None = 1) -> None:
        if threads is not None:
            if threads < 1:
                raise PolicyError(f"policy threads must be >= 1, got {threads}")
            torch.set_num_threads(threads)
        self.checkpoint = checkpoint
        sha = checkpoint.sha256
        self.spec = PolicySpec(
            policy_type=checkpoint.policy_type,
            state_names=checkpoint.state_names,
            action_names=checkpoint.action_names,
            camera_keys=checkpoint.camera_keys,
            image_size=checkpoint.image_size,
            fps=checkpoint.fps,
            chunk_size=checkpoint.chunk_size,
            checkpoint_id=sha[:12],
            checkpoint_sha256=sha,
            rig=checkpoint.rig,
            rig_fingerprint=checkpoint.rig_fingerprint,
        )
        self._model = build_model(checkpoint.model)
        self._model.load_state_dict(checkpoint.state_dict)
        self._model.eval()
        self._norm = checkpoint.normalization

    def act(self, state: npt.ArrayLike, images: Mapping[str, npt.NDArray[np.uint8]]) -> Float32Array:
        """The next ``chunk_size`` actions for one observation.

        Args:
            state: Measured state in ``spec.state_names`` order [physical units: rad, m, 0..1
                gripper opening], shape (S,).
            images: ``spec.camera_keys`` → RGB frame, uint8 (H, W, 3), any size (resized to
                ``spec.image_size`` with the training resize). Extra keys are ignored.

        Returns:
            float32 (chunk_size, A) in ``spec.action_names`` order, physical units.

        Raises:
            PolicyError: A state of the wrong length or not finite, a missing camera, a frame that
                is not uint8 RGB.
        """
        s = np.asarray(state, dtype=np.float32)
        if s.shape != (self.spec.state_dim,):
            raise PolicyError(
                f"policy state must have shape ({self.spec.state_dim},) "
                f"({', '.join(self.spec.state_names)}), got {s.shape}"
            )
        if not np.isfinite(s).all():
            raise PolicyError("policy state holds NaN or inf; refusing to act on it")
        missing = [k for k in self.spec.camera_keys if k not in images]
        if missing:
            raise PolicyError(
                f"policy needs camera {missing[0]!r} (cameras: {', '.join(self.spec.camera_keys)}); "
                f"got {', '.join(sorted(images)) or 'none'}"
            )
        frames = {key: np.asarray(images[key]) for key in self.spec.camera_keys}
        for key, frame in frames.items():
            if frame.ndim != 3:
                raise PolicyError(
                    f"camera {key!r} frame must be one uint8 (H, W, 3) image, got shape {frame.shape}"
                )
        batch = {key: to_tensor(resize_rgb(f, self.spec.image_size)[None]) for key, f in frames.items()}
        with torch.inference_mode():
            out = self._model(torch.from_numpy(self._norm.normalize_state(s))[None], batch)
        return self._norm.denormalize_action(out[0].numpy(), s)


def load_policy(path: str | os.PathLike[str], threads: int | None = 1) -> PolicyRunner:
    """Load a checkpoint file into a runner (one-line :class:`PolicyError` when it cannot)."""
    return PolicyRunner(load_checkpoint(path), threads=threads)
