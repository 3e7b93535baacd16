"""The ``telerig retarget`` commands: offline retargeting of whole recordings onto a robot."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from telerig.errors import TelerigError

__all__ = ["add_arguments", "cmd_retarget_humanoid"]

#: Exit code when ``--fail-on-flagged`` is given and frames were flagged.
EXIT_FLAGGED = 2
#: Names of ``telerig.retarget.humanoid.SKELETON_PROFILES`` (not imported here: it loads MuJoCo).
_PROFILES = ("mediapipe", "cmu", "motive")


def add_arguments(subparsers: Any) -> None:
    """Add ``retarget`` and its subcommands to the ``telerig`` parser's ``subparsers``.

    Args:
        subparsers: What ``ArgumentParser.add_subparsers()`` returned.
    """
    retarget = subparsers.add_parser("retarget", help="retarget whole recordings offline onto a robot")
    sub = retarget.add_subparsers(title="retarget commands")
    humanoid = sub.add_parser(
        "humanoid",
        help="body skeleton recording (BVH, episode MCAP) → G1 upper-body joint trajectory",
        description="Low-pass the skeleton keypoints with a zero-phase Butterworth filter, solve the "
        "upper-body IK per frame and flag frames whose wrist misses its target by more than the "
        "threshold. Writes humanoid_retarget.npz (and humanoid_retarget.png with matplotlib).",
    )
    humanoid.add_argument("source", type=Path, help="a .bvh file, an episode .mcap, or an episode folder")
    humanoid.add_argument(
        "-o",
        "--output",
        type=Path,
        default=None,
        help="folder to write into (default: ./<source name>.retarget)",
    )
    cutoff = humanoid.add_mutually_exclusive_group()
    cutoff.add_argument(
        "--cutoff", type=float, default=5.0, metavar="HZ", help="low-pass cutoff in Hz (default 5)"
    )
    cutoff.add_argument(
        "--no-filter", dest="cutoff", action="store_const", const=None, help="retarget the raw keypoints"
    )
    humanoid.add_argument("--order", type=int, default=4, help="Butterworth order, 1..10 (default 4)")
    humanoid.add_argument(
        "--source-id", default=None, help="the skeleton stream's source id when an MCAP holds several"
    )
    humanoid.add_argument(
        "--profile", choices=_PROFILES, default=None, help="skeleton joint naming (default: detect)"
    )
    humanoid.add_argument(
        "--threshold",
        type=float,
        default=0.05,
        metavar="M",
        help="wrist error above which a frame is flagged, metres (default 0.05)",
    )
    humanoid.add_argument(
        "--fail-on-flagged",
        action="store_true",
        help=f"exit with status {EXIT_FLAGGED} when any frame is flagged",
    )
    humanoid.set_defaults(handler=cmd_retarget_humanoid)


def cmd_retarget_humanoid(args: argparse.Namespace) -> int:
    """Run ``telerig retarget humanoid``; returns the exit code (0, or 2 on flags with --fail-on-flagged).

    Raises:
        TelerigError: the recording cannot be used or an option is out of range (one line).
    """
    from telerig.retarget.humanoid import HumanoidIK
    from telerig.retarget.offline import retarget_recording

    console = Console(width=None if sys.stdout.isatty() else 130)
    source: Path = args.source
    if not args.threshold > 0:
        raise TelerigError(f"--threshold must be a positive distance in metres, got {args.threshold:g}")
    if args.cutoff is not None and not args.cutoff > 0:
        raise TelerigError(f"--cutoff must be a positive frequency in Hz, got {args.cutoff:g}")
    output = args.output if args.output is not None else Path(f"{source.name}.retarget")
    with Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeRemainingColumn(),
        console=console,
        transient=True,
    ) as bar:
        task = bar.add_task(f"retargeting {source.name}", total=None)

        def progress(done: int, total: int) -> None:
            bar.update(task, completed=done, total=total)

        try:
            result = retarget_recording(
                source,
                output,
                cutoff_hz=args.cutoff,
                order=args.order,
                source_id=args.source_id,
                profile=args.profile,
                ik=HumanoidIK(residual_threshold_m=args.threshold),
                progress=progress,
            )
        except ValueError as exc:  # a skeleton lacking joints, a cutoff above Nyquist, a bad order
            raise TelerigError(f"{source}: {exc}") from None
    s = result.summary
    filtered = "no filter" if s.cutoff_hz is None else f"{s.cutoff_hz:g} Hz low-pass (order {s.order})"
    flag_style = "red" if s.flagged else "green"
    console.print(
        f"retargeted [bold]{s.frames}[/] frames ({s.duration_s:.1f} s at {s.rate_hz:.0f} Hz, profile "
        f"{s.profile}, {filtered}): [{flag_style}]{s.flagged} flagged[/] (wrist error > "
        f"{s.threshold_m * 1e3:.0f} mm), max wrist error {s.max_wrist_error_m * 1e3:.1f} mm → "
        f"{', '.join(str(f) for f in result.files)}",
        highlight=False,
        soft_wrap=True,
    )
    if len(result.files) < 2:  # the plot is skipped only when matplotlib is missing
        console.print("no plot written: matplotlib is not installed (pip install matplotlib)")
    return EXIT_FLAGGED if args.fail_on_flagged and s.flagged else 0
