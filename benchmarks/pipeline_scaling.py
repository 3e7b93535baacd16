"""telerig process (issue 15): the runner's scaling, in process vs process pool vs Dask (1 and 2 workers).

The same items and stages run four ways in one run, each into a fresh processed root: in this
process (the baseline), a local pool of 2 workers, and a Dask ``LocalCluster`` (worker processes,
127.0.0.1, no dashboard) with 1 and 2 workers; a fifth run repeats the first to show what a re-run
costs when every stage is skipped. Items: ``--videos`` generated plain videos (640x480 30 fps
H.264, moving textured blobs so the motion-energy segmenter finds actions). Stages: segment, clips,
annotate (offline), layout: the frame filter is left out (its MediaPipe tracker is measured by
``benchmarks/pipeline.py``; here it would only add the tracker's start per worker).

Reported per way: wall seconds, video hours processed per wall hour, speedup against the in-process
run of the same run, and whether its outputs (every clips.json and index.json clip id) match the
baseline's. Dask's cluster start is outside the timing (a cluster is long-lived), the workers'
first imports inside it (each worker's first item pays them).

Usage: python benchmarks/pipeline_scaling.py [--videos 8] [--seconds 20]
       [--json benchmarks/results/pipeline_scaling.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path
from typing import Any

import av
import numpy as np
from rich.console import Console
from rich.table import Table

from telerig.config.process import ProcessSettings
from telerig.process.items import discover
from telerig.process.run import RunSummary, plan, run_pipeline
from telerig.registry import PROCESS_STAGES

_STAGES = ("segment", "clips", "annotate", "layout")


def make_video(path: Path, seconds: float, seed: int, fps: int = 30) -> None:
    """640x480 H.264: a textured background, a blob that moves in bursts (actions) and rests."""
    rng = np.random.default_rng(seed)
    background = rng.integers(40, 90, size=(480, 640, 3), dtype=np.uint8)
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=fps, options={"preset": "ultrafast", "g": str(fps)})
        stream.width, stream.height, stream.pix_fmt = 640, 480, "yuv420p"
        x, y = 200.0, 200.0
        for i in range(round(seconds * fps)):
            moving = (i // (3 * fps)) % 2 == 0  # 3 s of motion, 3 s of rest
            if moving:
                x = 100 + 200 * (1 + np.sin(i / 9.0))
                y = 120 + 120 * (1 + np.cos(i / 7.0))
            image = background.copy()
            image[int(y) : int(y) + 80, int(x) : int(x) + 80] = (220, 180, 150)
            for packet in stream.encode(av.VideoFrame.from_ndarray(image, format="rgb24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)


def _outputs(work: Path) -> list[str]:
    index = json.loads((work / "index.json").read_text())
    return sorted(c["id"] for c in index["clips"])


def _first_failure(summary: RunSummary) -> str:
    """The first failed item's stage and one-line reason ("" when none failed)."""
    for outcome in summary.failures:
        failed = outcome.failed
        if failed is not None:
            return f"{outcome.item_id} {failed.name}: {failed.message}"
    return ""


def _run(found: Any, work: Path, **how: Any) -> tuple[float, RunSummary]:
    settings = ProcessSettings()
    stages = plan([PROCESS_STAGES.get(n)() for n in _STAGES], {n: settings.for_stage(n) for n in _STAGES})
    t0 = time.perf_counter()
    summary = run_pipeline(found.items, stages, work, skipped=found.skipped, **how)
    return time.perf_counter() - t0, summary


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--videos", type=int, default=8)
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--json", type=Path, default=Path("benchmarks/results/pipeline_scaling.json"))
    args = parser.parse_args()
    from distributed import LocalCluster

    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="pipeline-scaling-") as tmp:
        root = Path(tmp)
        (root / "videos").mkdir()
        for k in range(args.videos):
            make_video(root / "videos" / f"v{k:02d}.mp4", args.seconds, seed=k)
        found = discover(str(root / "videos"))
        hours = args.videos * args.seconds / 3600.0
        wall, summary = _run(found, root / "inline", workers=1)
        baseline, expected = wall, _outputs(root / "inline")
        rows.append({"way": "in process", "workers": 1, "wall_s": wall, "failures": len(summary.failures)})
        rows[-1]["first_failure"] = _first_failure(summary)
        wall, summary = _run(found, root / "pool", workers=2)
        rows.append({"way": "process pool", "workers": 2, "wall_s": wall, "failures": len(summary.failures)})
        rows[-1]["first_failure"] = _first_failure(summary)
        rows[-1]["same_outputs"] = _outputs(root / "pool") == expected
        for n in (1, 2):
            with LocalCluster(  # type: ignore[no-untyped-call]
                n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=None
            ) as cluster:
                work = root / f"dask{n}"
                wall, summary = _run(found, work, cluster=str(cluster.scheduler_address))
            rows.append({"way": "dask", "workers": n, "wall_s": wall, "failures": len(summary.failures)})
            rows[-1]["first_failure"] = _first_failure(summary)
            rows[-1]["same_outputs"] = _outputs(work) == expected
        wall, summary = _run(found, root / "inline", workers=1)
        rows.append({"way": "re-run (all skipped)", "workers": 1, "wall_s": wall, "failures": 0})
        rows[-1]["same_outputs"] = _outputs(root / "inline") == expected
        rows[0]["same_outputs"] = True
    for row in rows:
        row.setdefault("first_failure", "")
        row["video_h_per_wall_h"] = hours / (row["wall_s"] / 3600.0)
        row["speedup"] = baseline / row["wall_s"]
    stages = ", ".join(_STAGES)
    table = Table(title=f"telerig process: {args.videos} videos x {args.seconds:.0f} s, stages {stages}")
    for column in ("way", "workers", "wall s", "video h / wall h", "speedup", "same outputs", "failures"):
        table.add_column(column, justify="left" if column == "way" else "right")
    for row in rows:
        table.add_row(
            row["way"], str(row["workers"]), f"{row['wall_s']:.1f}", f"{row['video_h_per_wall_h']:.1f}",
            f"{row['speedup']:.2f}x", str(row["same_outputs"]), str(row["failures"]),
        )  # fmt: skip
    console = Console(width=130)
    console.print(table)
    for row in rows:
        if row["first_failure"]:
            way = f"{row['way']} ({row['workers']})"
            console.print(f"{way}: first failure: {row['first_failure']}", highlight=False)
    result = {
        "host": platform.node(),
        "cpus": os.cpu_count(),
        "load_avg": os.getloadavg(),
        "videos": args.videos,
        "seconds_each": args.seconds,
        "stages": list(_STAGES),
        "rows": rows,
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
