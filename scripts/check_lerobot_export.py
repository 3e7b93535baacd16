"""Load a telerig LeRobot export with the real LeRobot and decode every frame of every episode.

Run it with the Python of a separate venv that has ``lerobot`` 0.4.x (it forces CUDA torch,
~8 GB, so it never enters telerig's venv)::

    python3 -m venv /tmp/venvs/lerobot && /tmp/venvs/lerobot/bin/pip install 'lerobot>=0.4,<0.5'
    /tmp/venvs/lerobot/bin/python scripts/check_lerobot_export.py DATASET_DIR

It builds ``LeRobotDataset(repo_id, root=DIR, video_backend="pyav")``, reads every item (video
frames decoded within LeRobot's 1e-4 s tolerance), checks each against the shapes ``info.json``
declares and the episode lengths the metadata lists, loads the stats, and prints one summary line
(exit status 1 and the first problem otherwise).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("root", type=Path, help="dataset directory (holds meta/info.json)")
    parser.add_argument(
        "--repo-id", default="telerig/export-check", help="any repo id; nothing is downloaded"
    )
    parser.add_argument(
        "--delta", action="store_true", help="also query 2 past frames per item (delta_timestamps)"
    )
    args = parser.parse_args()

    import lerobot
    import torch
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    started = time.perf_counter()
    ds = LeRobotDataset(args.repo_id, root=args.root, video_backend="pyav")
    meta = ds.meta
    fps = meta.fps
    if args.delta:
        deltas = {key: [-2 / fps, -1 / fps, 0.0] for key in meta.video_keys}
        ds = LeRobotDataset(args.repo_id, root=args.root, video_backend="pyav", delta_timestamps=deltas)
    shapes = {key: tuple(ft["shape"]) for key, ft in meta.features.items()}
    lengths: dict[int, int] = {}
    for idx in range(len(ds)):
        item = ds[idx]
        ep = int(item["episode_index"])
        lengths[ep] = lengths.get(ep, 0) + 1
        if int(item["frame_index"]) != lengths[ep] - 1:
            return _fail(f"item {idx}: frame_index {int(item['frame_index'])}, expected {lengths[ep] - 1}")
        for key in meta.video_keys:
            h, w, c = shapes[key]
            frame = item[key]
            want = (3, c, h, w) if args.delta else (c, h, w)
            if tuple(frame.shape) != want or frame.dtype != torch.float32:
                return _fail(
                    f"item {idx}: {key} is {tuple(frame.shape)} {frame.dtype}, info.json declares {want}"
                )
            if float(frame.min()) < 0.0 or float(frame.max()) > 1.0:
                return _fail(f"item {idx}: {key} values leave [0, 1]")
        for key in ("observation.state", "action"):
            if tuple(item[key].shape) != shapes[key]:
                return _fail(
                    f"item {idx}: {key} is {tuple(item[key].shape)}, info.json declares {shapes[key]}"
                )
        if not isinstance(item["task"], str) or not item["task"]:
            return _fail(f"item {idx}: no task string")
    for ep in range(meta.total_episodes):
        want = meta.episodes[ep]["length"]
        if lengths.get(ep) != want:
            return _fail(f"episode {ep}: {lengths.get(ep)} items, metadata length {want}")
    if meta.stats is None or any(
        k not in meta.stats for k in ("observation.state", "action", *meta.video_keys)
    ):
        return _fail("meta/stats.json lacks a feature")
    print(
        f"OK lerobot {lerobot.__version__}: {meta.total_episodes} episodes, {len(ds)} frames decoded "
        f"({', '.join(f'{k} {shapes[k]}' for k in meta.video_keys)}), fps {fps}, "
        f"tasks {list(meta.tasks.index)}, {time.perf_counter() - started:.1f} s"
    )
    return 0


def _fail(message: str) -> int:
    print(f"FAIL {message}")
    return 1


if __name__ == "__main__":
    sys.exit(main())
