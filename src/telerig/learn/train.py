"""``telerig train``: fit a ``bc`` or ``act_lite`` policy to a LeRobot v3 export on the CPU.

One sample is one dataset frame ``t`` of a training episode: the state and camera images at ``t``
in, the actions ``t .. t + chunk - 1`` out (past the episode's end the last action repeats: the
robot holds still, which is what a finished demonstration shows). State and actions are
normalized with the training episodes' mean / std (stored in the checkpoint). Images get a random
shift of up to ``shift_px`` pixels (DrQ / Diffusion Policy's crop augmentation, the one
augmentation that consistently helps visuomotor BC on small datasets).

Outputs, all beside ``out``: the checkpoint (written atomically), ``<stem>.loss.png`` (train and
validation loss per step) and ``<stem>.train.json`` (the losses, timings and split). Wall times
are kept out of the checkpoint so two identical runs give the same checkpoint id.
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import torch

from telerig.errors import DependencyError, PolicyError
from telerig.learn.dataset import Episode, PolicyDataset, read_dataset, split_episodes
from telerig.policy.checkpoint import Checkpoint, Normalization, save_checkpoint
from telerig.policy.images import random_shift, to_tensor
from telerig.policy.models import POLICY_TYPES, ChunkPolicy, ModelConfig, PolicyType, build_model

__all__ = [
    "ACT_LITE_STEPS",
    "BC_STEPS",
    "TrainConfig",
    "TrainProgress",
    "TrainResult",
    "artifact_paths",
    "train",
]

_log = logging.getLogger("telerig.learn.train")
_F32 = npt.NDArray[np.float32]

#: Default steps of ``bc`` and ``act_lite``. Sized by benchmarks/train_speed.py on 2 pinned cores
#: of three idle server VMs (Xeon, torch 2.11, 72x96 images, 1 camera; benchmarks/results/
#: train_speed*.json): bc 10.7-18.7 steps/s at batch 64, act_lite 5.1-7.6 steps/s at batch 32, so
#: 8000 bc steps take 7-12.5 min and 4000 act_lite steps 9-13 min; decoding 50 demonstrations of
#: 15 s at 30 Hz (22 500 frames, 4.2 ms each decoded and resized on 2 cores) adds 1.6 min. That
#: leaves about a 2x margin for a slower CPU inside the issue's 30 min on 2 cores.
BC_STEPS = 8000
ACT_LITE_STEPS = 4000
#: Validation / loss-check samples evaluated at most (fixed, evenly spaced frames).
_EVAL_SAMPLES = 512


@dataclass(frozen=True, slots=True)
class TrainConfig:
    """How to train. Defaults are sized for <= 30 min on 2 CPU cores (see README, Policy loop).

    Attributes:
        policy_type: ``bc`` or ``act_lite``.
        steps: Optimizer steps.
        batch_size: Samples per step.
        lr: Peak learning rate (AdamW); ``None``: 1e-3 for ``bc``, 3e-4 for ``act_lite``.
        weight_decay: AdamW weight decay.
        warmup_steps: Linear warm-up, then cosine decay to 10 % of ``lr``.
        chunk_size: Actions predicted per observation.
        image_width: Policy image width [px] (height keeps the camera's aspect ratio).
        shift_px: Random-shift augmentation [px] (0: none).
        val_fraction: Share of episodes held out for validation.
        eval_every: Validation every this many steps.
        seed: Seeds the split, the initial weights and the batches.
        threads: torch intra-op threads.
        include_failures: Also train on episodes whose outcome is ``failure``.
        hidden: Model width (see :class:`ModelConfig`).
        layers: Model depth (see :class:`ModelConfig`).
        channels: Conv trunk widths (see :class:`ModelConfig`).
        keypoints: Spatial-softmax keypoints per camera (``bc``).
        relative_actions: Predict each joint action that names a state entry as an offset from
            that entry of the observation (see :class:`~telerig.policy.checkpoint.Normalization`);
            absolute targets otherwise. Gripper and base actions stay absolute either way: a
            gripper closed on an object measures wider than its command, so an offset would learn
            the object's width, and an offset of zero keeps a gripper however it started.
        gripper_weight: Weight of the gripper entries of each action in the L1 loss, relative to
            the other entries (1: plain L1). The loss is the weighted mean, so a weight of 1 gives
            the same numbers as an unweighted run.
    """

    policy_type: PolicyType = "bc"
    steps: int = BC_STEPS
    batch_size: int = 64
    lr: float | None = None
    weight_decay: float = 1e-4
    warmup_steps: int = 100
    chunk_size: int = 16
    image_width: int = 96
    shift_px: int = 4
    val_fraction: float = 0.1
    eval_every: int = 250
    seed: int = 0
    threads: int = 2
    include_failures: bool = False
    hidden: int = 256
    layers: int = 2
    channels: tuple[int, ...] = (16, 32, 32)
    keypoints: int = 32
    relative_actions: bool = True
    gripper_weight: float = 1.0

    def __post_init__(self) -> None:
        if self.policy_type not in POLICY_TYPES:
            raise PolicyError(
                f"unknown policy {self.policy_type!r}; use one of {', '.join(POLICY_TYPES)} (bc, act-lite)"
            )
        for name in ("steps", "batch_size", "chunk_size", "eval_every", "threads"):
            if getattr(self, name) < 1:
                raise PolicyError(f"train {name.replace('_', '-')} must be >= 1, got {getattr(self, name)}")
        if self.lr is not None and not (math.isfinite(self.lr) and self.lr > 0):
            raise PolicyError(f"learning rate must be > 0, got {self.lr}")
        if self.shift_px < 0 or self.warmup_steps < 0:
            raise PolicyError("shift-px and warmup-steps must be >= 0")
        if not (math.isfinite(self.gripper_weight) and self.gripper_weight > 0):
            raise PolicyError(f"gripper weight must be > 0, got {self.gripper_weight}")

    @classmethod
    def for_policy(cls, policy_type: PolicyType, **overrides: Any) -> TrainConfig:
        """Defaults for ``policy_type`` (``act_lite``: a 128-wide transformer, batch 32, fewer steps:
        one of its steps costs about 4x one of ``bc``'s on the CPU), then ``overrides`` (``None``
        values are ignored, so unset CLI options keep the defaults)."""
        base: dict[str, Any] = {"policy_type": policy_type}
        if policy_type == "act_lite":
            base.update(hidden=128, batch_size=32, steps=ACT_LITE_STEPS)
        base.update({k: v for k, v in overrides.items() if v is not None})
        return cls(**base)

    @property
    def learning_rate(self) -> float:
        if self.lr is not None:
            return self.lr
        return 1e-3 if self.policy_type == "bc" else 3e-4


@dataclass(frozen=True, slots=True)
class TrainProgress:
    """Reported after each step: ``step`` of ``steps``, the batch loss, the latest validation loss."""

    step: int
    steps: int
    loss: float
    val_loss: float | None


@dataclass
class TrainResult:
    """What a run produced and measured.

    Attributes:
        checkpoint_path: The checkpoint file.
        plot_path: The loss plot (``None`` when matplotlib is missing).
        report_path: ``<stem>.train.json``.
        checkpoint: The trained checkpoint (``checkpoint.id`` to record).
        loss: (step, batch loss) per step.
        val_loss: (step, validation loss) every ``eval_every`` steps and at the end; empty without
            validation episodes.
        fit_before: Loss on fixed training frames before the first step (no augmentation).
        fit_after: The same after the last step.
        read_seconds: Reading / decoding the dataset [s].
        train_seconds: The optimisation loop [s].
        train_episodes: ``episode_index`` of the training episodes.
        val_episodes: ``episode_index`` of the validation episodes.
        frames: Training frames.
    """

    checkpoint_path: Path
    plot_path: Path | None
    report_path: Path
    checkpoint: Checkpoint
    loss: list[tuple[int, float]] = field(default_factory=list)
    val_loss: list[tuple[int, float]] = field(default_factory=list)
    fit_before: float = math.nan
    fit_after: float = math.nan
    read_seconds: float = 0.0
    train_seconds: float = 0.0
    train_episodes: list[int] = field(default_factory=list)
    val_episodes: list[int] = field(default_factory=list)
    frames: int = 0

    @property
    def steps_per_second(self) -> float:
        return len(self.loss) / self.train_seconds if self.train_seconds > 0 else math.nan


def artifact_paths(out: str | os.PathLike[str]) -> tuple[Path, Path, Path]:
    """(checkpoint, loss plot, report) paths for ``out``: ``x.pt`` → ``x.loss.png``, ``x.train.json``."""
    path = Path(out)
    stem = path.name[: -len(path.suffix)] if path.suffix else path.name
    return path, path.with_name(f"{stem}.loss.png"), path.with_name(f"{stem}.train.json")


class _Samples:
    """Training frames as tensors: normalized state (N, S), action chunks, uint8 images (N, H, W, 3)."""

    def __init__(
        self, episodes: Sequence[Episode], norm: Normalization, keys: Sequence[str], chunk: int
    ) -> None:
        state, chunks = _chunks(episodes, chunk)
        self.state = torch.from_numpy(norm.normalize_state(state))
        # (N, chunk, A): the next ``chunk`` actions of each frame, relative entries from its state.
        self.target = torch.from_numpy(norm.normalize_action(chunks, state[:, None, :]))
        self.images = {k: torch.from_numpy(np.concatenate([e.images[k] for e in episodes])) for k in keys}

    def __len__(self) -> int:
        return int(self.state.shape[0])

    def batch(
        self, index: torch.Tensor, shift_px: int = 0, generator: torch.Generator | None = None
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor], torch.Tensor]:
        images = {k: to_tensor(v[index]) for k, v in self.images.items()}
        if shift_px:
            images = {k: random_shift(v, shift_px, generator) for k, v in images.items()}
        return self.state[index], images, self.target[index]


def _chunks(episodes: Sequence[Episode], chunk: int) -> tuple[_F32, _F32]:
    """Every frame's state (N, S) and its next ``chunk`` actions (N, chunk, A), the episode's last
    action repeated past its end."""
    chunks = []
    for e in episodes:
        steps = np.minimum(np.arange(e.length)[:, None] + np.arange(chunk)[None, :], e.length - 1)
        chunks.append(e.action[steps])
    return np.concatenate([e.state for e in episodes]), np.concatenate(chunks)


def train(
    dataset: str | os.PathLike[str] | PolicyDataset,
    out: str | os.PathLike[str],
    config: TrainConfig | None = None,
    *,
    cache_dir: str | os.PathLike[str] | None = None,
    progress: Callable[[TrainProgress], None] | None = None,
    read_progress: Callable[[str, int, int], None] | None = None,
) -> TrainResult:
    """Train a policy on a LeRobot v3 export and write the checkpoint, loss plot and report.

    Args:
        dataset: The export's directory (or a dataset already read at ``config.image_width``).
        out: Checkpoint path (``.pt``); the plot and report go beside it.
        config: Training settings (defaults: :class:`TrainConfig`).
        cache_dir: Decoded-frames cache for :func:`read_dataset`.
        progress: Called after every step.
        read_progress: Called while frames are decoded (``what, done, total``).

    Raises:
        PolicyError: One line: a bad dataset, no episode to train on, an ``out`` that is a
            directory, a loss that turned NaN.
    """
    cfg = config or TrainConfig()
    ckpt_path, plot_path, report_path = artifact_paths(out)
    if ckpt_path.is_dir():
        raise PolicyError(
            f"--out {ckpt_path} is a directory; name the checkpoint file, e.g. {ckpt_path}/policy.pt"
        )
    torch.set_num_threads(cfg.threads)
    started = time.perf_counter()
    data = (
        dataset
        if isinstance(dataset, PolicyDataset)
        else read_dataset(dataset, image_width=cfg.image_width, cache_dir=cache_dir, progress=read_progress)
    )
    read_seconds = time.perf_counter() - started
    usable = [e for e in data.episodes if cfg.include_failures or e.outcome != "failure"]
    if not usable:
        raise PolicyError(
            f"every episode of {data.root} failed (outcome 'failure'); --include-failures trains on them"
        )
    if len(usable) < len(data.episodes):
        _log.info("left out %d failed episodes", len(data.episodes) - len(usable))
    train_eps, val_eps = split_episodes(usable, cfg.val_fraction, cfg.seed)
    relative_to = (
        [
            data.state_names.index(a.name) if a.part == "joints" and a.name in data.state_names else -1
            for a in data.schema.action
        ]
        if cfg.relative_actions
        else []
    )
    if all(i < 0 for i in relative_to):
        relative_to = []  # no action names a state entry
    state, chunks = _chunks(train_eps, cfg.chunk_size)
    norm = Normalization.fit(state, chunks, relative_to, reference=state[:, None, :])
    model_config = ModelConfig(
        policy_type=cfg.policy_type,
        state_dim=len(data.state_names),
        action_dim=len(data.action_names),
        camera_keys=data.camera_keys,
        image_size=data.image_size,
        chunk_size=cfg.chunk_size,
        channels=cfg.channels,
        keypoints=cfg.keypoints,
        hidden=cfg.hidden,
        layers=cfg.layers,
    )
    torch.manual_seed(cfg.seed)
    model = build_model(model_config)
    train_set = _Samples(train_eps, norm, data.camera_keys, cfg.chunk_size)
    val_set = _Samples(val_eps, norm, data.camera_keys, cfg.chunk_size) if val_eps else None
    result = TrainResult(
        checkpoint_path=ckpt_path,
        plot_path=None,
        report_path=report_path,
        checkpoint=_checkpoint(model, model_config, norm, data, cfg, {}),
        read_seconds=read_seconds,
        train_episodes=[e.index for e in train_eps],
        val_episodes=[e.index for e in val_eps],
        frames=len(train_set),
    )
    weights = _action_weights(data, cfg)
    result.fit_before = _evaluate(model, train_set, weights)
    loop_started = time.perf_counter()
    _optimise(model, train_set, val_set, cfg, result, progress, weights)
    result.train_seconds = time.perf_counter() - loop_started
    result.fit_after = _evaluate(model, train_set, weights)
    summary = {
        "fit_before": round(result.fit_before, 6),
        "fit_after": round(result.fit_after, 6),
        "val_loss": round(result.val_loss[-1][1], 6) if result.val_loss else None,
        "train_episodes": result.train_episodes,
        "val_episodes": result.val_episodes,
    }
    result.checkpoint = _checkpoint(model, model_config, norm, data, cfg, summary)
    save_checkpoint(result.checkpoint, ckpt_path)
    result.plot_path = _plot(result, plot_path, cfg)
    _write_report(result, cfg, data)
    return result


def _action_weights(data: PolicyDataset, cfg: TrainConfig) -> torch.Tensor | None:
    """Loss weight per action entry: ``cfg.gripper_weight`` for gripper entries, 1 for the rest;
    ``None`` (plain L1) when every weight is 1."""
    weights = torch.tensor(
        [cfg.gripper_weight if a.part == "gripper" else 1.0 for a in data.schema.action], dtype=torch.float32
    )
    return None if bool((weights == 1.0).all()) else weights


def _optimise(
    model: ChunkPolicy,
    train_set: _Samples,
    val_set: _Samples | None,
    cfg: TrainConfig,
    result: TrainResult,
    progress: Callable[[TrainProgress], None] | None,
    weights: torch.Tensor | None = None,
) -> None:
    lr = cfg.learning_rate
    optimizer = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=cfg.weight_decay)

    def schedule(step: int) -> float:
        if step < cfg.warmup_steps:
            return (step + 1) / cfg.warmup_steps
        done = (step - cfg.warmup_steps) / max(cfg.steps - cfg.warmup_steps, 1)
        return 0.1 + 0.9 * 0.5 * (1.0 + math.cos(math.pi * min(done, 1.0)))

    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, schedule)
    generator = torch.Generator().manual_seed(cfg.seed)
    val_loss: float | None = None
    for step in range(1, cfg.steps + 1):
        model.train()
        index = torch.randint(0, len(train_set), (cfg.batch_size,), generator=generator)
        state, images, target = train_set.batch(index, cfg.shift_px, generator)
        loss = model.loss(model(state, images), target, weights)
        if not torch.isfinite(loss):
            raise PolicyError(
                f"training loss became {loss.item()} at step {step}; lower --lr or check the dataset"
            )
        optimizer.zero_grad(set_to_none=True)
        loss.backward()  # type: ignore[no-untyped-call]
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        optimizer.step()
        scheduler.step()
        result.loss.append((step, float(loss.item())))
        if val_set is not None and (step % cfg.eval_every == 0 or step == cfg.steps):
            val_loss = _evaluate(model, val_set, weights)
            result.val_loss.append((step, val_loss))
        if progress is not None:
            progress(TrainProgress(step, cfg.steps, float(loss.item()), val_loss))


def _evaluate(model: ChunkPolicy, samples: _Samples, weights: torch.Tensor | None = None) -> float:
    """Mean loss over up to :data:`_EVAL_SAMPLES` evenly spaced frames, eval mode, no augmentation."""
    n = len(samples)
    index = torch.from_numpy(np.unique(np.linspace(0, n - 1, min(n, _EVAL_SAMPLES)).round().astype(np.int64)))
    model.eval()
    total, count = 0.0, 0
    with torch.inference_mode():
        for start in range(0, len(index), 128):
            part = index[start : start + 128]
            state, images, target = samples.batch(part)
            total += float(model.loss(model(state, images), target, weights).item()) * len(part)
            count += len(part)
    return total / count


def _checkpoint(
    model: ChunkPolicy,
    model_config: ModelConfig,
    norm: Normalization,
    data: PolicyDataset,
    cfg: TrainConfig,
    summary: dict[str, Any],
) -> Checkpoint:
    settings = asdict(cfg)
    settings["channels"] = list(cfg.channels)
    return Checkpoint(
        model=model_config,
        state_dict=model.state_dict(),
        normalization=norm,
        state_names=data.state_names,
        action_names=data.action_names,
        fps=float(data.fps),
        rig=data.schema.rig,
        rig_fingerprint=data.schema.fingerprint,
        training={
            "dataset": str(data.root),
            "dataset_digest": data.digest,
            "config": settings,
            "torch": torch.__version__.split("+")[0],
            **summary,
        },
    )


def _plot(result: TrainResult, path: Path, cfg: TrainConfig) -> Path | None:
    """Loss curves (log scale) as a PNG; ``None`` with a warning when matplotlib is missing."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        _log.warning(
            "%s", DependencyError("matplotlib is not installed, no loss plot; pip install 'telerig[plot]'")
        )
        return None
    steps = np.array([s for s, _ in result.loss])
    losses = np.array([v for _, v in result.loss])
    fig, ax = plt.subplots(figsize=(8, 4.5), dpi=100)
    try:
        ax.plot(steps, losses, color="tab:blue", alpha=0.25, linewidth=0.8, label="train (batch)")
        window = max(1, len(losses) // 50)
        if window > 1:
            smooth = np.convolve(losses, np.ones(window) / window, mode="valid")
            ax.plot(
                steps[window - 1 :],
                smooth,
                color="tab:blue",
                linewidth=1.6,
                label=f"train ({window}-step mean)",
            )
        if result.val_loss:
            ax.plot(*zip(*result.val_loss, strict=True), "o-", color="tab:orange", label="validation")
        ax.set_yscale("log")
        ax.set_xlabel("step")
        ax.set_ylabel("L1 loss (normalized actions)")
        ax.set_title(
            f"{cfg.policy_type}: {result.frames} frames of {len(result.train_episodes)} episodes, "
            f"{result.steps_per_second:.1f} steps/s, id {result.checkpoint.id}",
            fontsize=10,
        )
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(loc="upper right")
        fig.tight_layout()
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        fig.savefig(tmp, format="png")
        os.replace(tmp, path)
    finally:
        plt.close(fig)
    return path


def _write_report(result: TrainResult, cfg: TrainConfig, data: PolicyDataset) -> None:
    report = {
        "checkpoint": str(result.checkpoint_path),
        "id": result.checkpoint.id,
        "sha256": result.checkpoint.sha256,
        "dataset": str(data.root),
        "policy": cfg.policy_type,
        "steps": cfg.steps,
        "batch_size": cfg.batch_size,
        "threads": cfg.threads,
        "gripper_weight": cfg.gripper_weight,
        "frames": result.frames,
        "train_episodes": result.train_episodes,
        "val_episodes": result.val_episodes,
        "read_seconds": round(result.read_seconds, 3),
        "train_seconds": round(result.train_seconds, 3),
        "steps_per_second": round(result.steps_per_second, 3),
        "fit_before": result.fit_before,
        "fit_after": result.fit_after,
        "loss": [round(v, 6) for _, v in result.loss],
        "val_loss": [[s, round(v, 6)] for s, v in result.val_loss],
    }
    tmp = result.report_path.with_name(f".{result.report_path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(report, indent=1) + "\n")
    os.replace(tmp, result.report_path)
