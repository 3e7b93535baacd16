"""``telerig view EPISODE|DATASET [--out FILE.rrd]``: write a Rerun recording to look at.

Video, joint plots (requested / sent / measured), the end effector's path and gate markers of an
episode (id or directory), or of an exported dataset's episodes; see :mod:`telerig.export.view`.
Nothing is shown and nothing goes over the network: open the file with ``rerun FILE.rrd``.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from rich.console import Console

__all__ = ["add_arguments", "cmd_view"]


def add_arguments(subparsers: Any) -> None:
    """Add ``telerig view`` to the CLI."""
    p = subparsers.add_parser(
        "view",
        help="write a Rerun .rrd of an episode or exported dataset (video, joint plots, end-effector path)",
    )
    p.add_argument("source", help="episode id, episode directory, or export directory (robot_schema.json)")
    p.add_argument("--out", type=Path, default=None, help="the .rrd to write (default: ./<source name>.rrd)")
    p.add_argument(
        "--data-root", type=Path, default=Path("telerig-data"), help="where episode ids are looked up"
    )
    p.set_defaults(handler=cmd_view)


def cmd_view(args: argparse.Namespace) -> int:
    from telerig.export.view import view

    summary = view(args.source, args.out, data_root=args.data_root)
    console = Console(highlight=False)
    kinds = ("/joints/", "/gripper/", "/state/", "/action/")
    series = sum(1 for k in summary.entities if any(kind in k for kind in kinds))
    console.print(
        f"wrote {summary.out}: {summary.source}, {len(summary.entities)} entities "
        f"({series} joint series), video: {summary.video}; open it with `rerun {summary.out}`"
    )
    for note in summary.notes:
        console.print(f"note: {note}")
    return 0
