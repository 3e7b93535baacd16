"""``telerig train``: a ``bc`` or ``act-lite`` policy from a LeRobot v3 export, on the CPU.

torch and the dataset reader are imported when the command runs, so ``telerig --help`` and every
other command stay free of torch.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

__all__ = ["add_arguments"]

#: CLI spelling → policy type.
_POLICIES = {"bc": "bc", "act-lite": "act_lite"}


def add_arguments(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add the ``train`` command."""
    p = sub.add_parser(
        "train",
        help="train a policy (bc | act-lite) on a LeRobot v3 export, CPU only",
        description="Train a behaviour-cloning policy on a dataset written by `telerig export --format "
        "lerobot`: proprioception plus every camera at low resolution, predicting chunks of actions. "
        "Writes the checkpoint (atomically), a loss plot CKPT-stem.loss.png and a report "
        "CKPT-stem.train.json beside it. Episodes whose outcome is 'failure' are left out unless "
        "--include-failures.",
    )
    p.add_argument("dataset", type=Path, help="LeRobot v3 dataset directory (telerig export --out)")
    p.add_argument("--policy", required=True, choices=sorted(_POLICIES), help="policy architecture")
    p.add_argument("--out", type=Path, required=True, help="checkpoint file to write, e.g. policy.pt")
    p.add_argument("--steps", type=int, default=None, help="optimizer steps (bc 8000, act-lite 4000)")
    p.add_argument("--batch", type=int, default=None, help="samples per step (default: bc 64, act-lite 32)")
    p.add_argument("--seed", type=int, default=None, help="seed of split, weights, batches (0)")
    p.add_argument("--lr", type=float, default=None, help="peak learning rate (bc 1e-3, act-lite 3e-4)")
    p.add_argument("--chunk", type=int, default=None, help="actions predicted per observation (default 16)")
    p.add_argument(
        "--image-width",
        type=int,
        default=None,
        help="image width [px] (96; height keeps aspect)",
    )
    p.add_argument(
        "--shift-px", type=int, default=None, help="random-shift image augmentation [px] (default 4; 0: none)"
    )
    p.add_argument(
        "--absolute-actions",
        action="store_true",
        help="predict absolute joint targets (default: offsets from the observed joints)",
    )
    p.add_argument(
        "--gripper-weight",
        type=float,
        default=None,
        help="L1 loss weight of the gripper entries of each action against the joints' (default 1)",
    )
    p.add_argument("--threads", type=int, default=None, help="torch threads (default 2)")
    p.add_argument("--val-fraction", type=float, default=None, help="episodes held out (default 0.1)")
    p.add_argument("--include-failures", action="store_true", help="also train on failed episodes")
    p.add_argument(
        "--cache",
        type=Path,
        default=None,
        help="directory for decoded frames, reused by later runs on the same dataset (default: none)",
    )
    p.set_defaults(handler=_cmd_train)


def _cmd_train(args: argparse.Namespace) -> int:
    from telerig.learn.train import TrainConfig, TrainProgress, train

    config = TrainConfig.for_policy(
        _POLICIES[args.policy],  # type: ignore[arg-type]  # the choices are the PolicyType values
        steps=args.steps,
        batch_size=args.batch,
        seed=args.seed,
        lr=args.lr,
        chunk_size=args.chunk,
        image_width=args.image_width,
        shift_px=args.shift_px,
        relative_actions=False if args.absolute_actions else None,
        gripper_weight=args.gripper_weight,
        threads=args.threads,
        val_fraction=args.val_fraction,
        include_failures=args.include_failures or None,
    )
    console = Console(stderr=True)
    with Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[loss]}"),
        TimeRemainingColumn(),
        console=console,
        transient=True,
        disable=not sys.stderr.isatty(),
    ) as bar:
        reading = bar.add_task("reading dataset", total=None, loss="")
        training = bar.add_task("training", total=config.steps, loss="", visible=False)

        def read_progress(what: str, done: int, total: int) -> None:
            bar.update(reading, description=what, completed=done, total=total)

        def step_progress(p: TrainProgress) -> None:
            if p.step == 1:
                bar.update(reading, visible=False)
                bar.update(training, visible=True)
            val = f" val {p.val_loss:.4f}" if p.val_loss is not None else ""
            bar.update(training, completed=p.step, loss=f"loss {p.loss:.4f}{val}")

        result = train(
            args.dataset,
            args.out,
            config,
            cache_dir=args.cache,
            progress=step_progress,
            read_progress=read_progress,
        )
    out = Console(width=None if sys.stdout.isatty() else 130)
    val = f", validation {result.val_loss[-1][1]:.4f}" if result.val_loss else ""
    plot = f", plot {result.plot_path}" if result.plot_path else " (no plot: matplotlib missing)"
    out.print(
        f"{config.policy_type}: {config.steps} steps on {result.frames} frames of "
        f"{len(result.train_episodes)} episodes in {result.train_seconds:.0f} s "
        f"({result.steps_per_second:.2f} steps/s, dataset read in {result.read_seconds:.1f} s); "
        f"fit loss {result.fit_before:.4f} -> {result.fit_after:.4f}{val}; "
        f"checkpoint {result.checkpoint_path} id {result.checkpoint.id}{plot}",
        highlight=False,
        soft_wrap=True,
    )
    return 0
