"""Export throughput per dataset format, the share of it spent on video, dataset size, gate + score time.

Records N episodes of the shipped demo rig once (scripted VR operator, simulated UR5e, one 640x480
camera; ``telerig run demo`` in a subprocess) or reuses ``--data-root``, then, pinned to one CPU core
(``sched_setaffinity``; PyAV's codec threads inherit it), for every format registered in
``telerig.registry.EXPORTERS``:

- throughput: episode-seconds exported per wall-second by :func:`telerig.export.export` (select,
  resample, write, validate; what ``telerig export`` runs) into a fresh directory, and per
  CPU-second of the process (the figure a loaded machine does not distort);
- video share: a second export of the same episodes with a stack sampler (every 5 ms, the main
  thread): the fraction of samples inside video work (decoding the recorded MP4 in
  ``CameraTrack.frames``, the LeRobot video writer, HDF5 image datasets, RLDS image encoding, PyAV
  and Pillow code). Sampling rather than a run with video off: every format writes its images, so
  there is no "video off" to compare with; the sampled run's own overhead is reported;
- validation: the exporter's re-read of the dataset, timed alone (part of the export time);
- size on disk per episode-minute (every file under the dataset directory), beside the recording's.

Then the quality gates and score of each episode (``telerig.qa.gates.evaluate`` and
``telerig.qa.score.score``), in seconds per episode-minute.

Target: LeRobot v3 >= 20x real time with one 640x480 camera.

Usage: python benchmarks/export.py [--episodes 3] [--duration 20] [--data-root DIR] [--formats lerobot,hdf5]
       [--cpu 0] [--json benchmarks/results/export.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from types import FrameType
from typing import Any

from rich.console import Console
from rich.table import Table

from telerig.store.episodes import EpisodeStore

RESULTS = Path(__file__).parent / "results" / "export.json"
#: Minimum export speed [x real time] per format (issue 13).
TARGETS = {"lerobot": 20.0}
SAMPLE_INTERVAL_S = 0.005

console = Console(width=None if sys.stdout.isatty() else 150)

# --- what counts as video work -------------------------------------------------------------------

#: (file path suffix, function name or None for any function of that file).
_VIDEO_CODE: tuple[tuple[str, str | None], ...] = (
    ("telerig/export/frames.py", "frames"),  # CameraTrack.frames: decode the recorded MP4
    ("telerig/export/frames.py", "_probe_camera"),
    ("telerig/export/_lerobot_video.py", None),  # LeRobot: remux or encode the videos
    ("telerig/export/hdf5.py", "write_images"),  # HDF5 / robomimic: chunked, compressed images
    ("telerig/export/hdf5.py", "check_images"),
    ("telerig/export/rlds.py", "_camera_images"),  # RLDS: JPEG/PNG step images
    ("telerig/export/rlds.py", "_encode_image"),
)
_VIDEO_PACKAGES = (f"{os.sep}av{os.sep}", f"{os.sep}PIL{os.sep}")
_VIDEO_NAME = re.compile(r"video|image", re.IGNORECASE)


def _is_video_frame(frame: FrameType) -> bool:
    path, name = frame.f_code.co_filename, frame.f_code.co_name
    if any(p in path for p in _VIDEO_PACKAGES):
        return True
    for suffix, func in _VIDEO_CODE:
        if path.endswith(suffix) and (func is None or func == name):
            return True
    return "telerig/export/" in path and bool(_VIDEO_NAME.search(name))


class StackSampler(threading.Thread):
    """Samples the main thread's Python stack every ``interval`` seconds: how often it is in video work.

    A frame inside C code (PyAV's Cython codec calls, h5py's compression filter) shows as the Python
    function that called it, so the attribution is by the calling telerig or library function.
    """

    def __init__(self, interval: float = SAMPLE_INTERVAL_S) -> None:
        super().__init__(name="stack-sampler", daemon=True)
        self.interval = interval
        self.samples = 0
        self.video = 0
        self._target = threading.main_thread().ident
        self._stop_event = threading.Event()

    def run(self) -> None:
        while not self._stop_event.wait(self.interval):
            frame: FrameType | None = sys._current_frames().get(self._target or 0)
            self.samples += 1
            while frame is not None:
                if _is_video_frame(frame):
                    self.video += 1
                    break
                frame = frame.f_back

    def stop(self) -> float:
        """Stop sampling; the fraction of samples in video work."""
        self._stop_event.set()
        self.join()
        return self.video / self.samples if self.samples else float("nan")


# --- recording ------------------------------------------------------------------------------------


def record(root: Path, episodes: int, duration: float) -> None:
    """``telerig run demo`` into ``root``; its own progress bar shows."""
    console.print(f"recording {episodes} demo episode(s) of {duration:g} s into {root} ...")
    env = {**os.environ, "MUJOCO_GL": "osmesa", "PYOPENGL_PLATFORM": "osmesa"}
    cmd = [sys.executable, "-m", "telerig.cli.main", "run", "demo", "--episodes", str(episodes)]
    cmd += ["--duration", str(duration), "--data-root", str(root)]
    done = subprocess.run(cmd, env=env, cwd=root.parent, check=False, stdout=subprocess.PIPE, text=True)
    tail = "\n".join(done.stdout.splitlines()[-12:])
    if done.returncode != 0:
        raise SystemExit(f"recording failed ({done.returncode}):\n{tail}")
    console.print(tail, highlight=False)


def _tree_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


# --- one format -----------------------------------------------------------------------------------


@dataclass
class FormatResult:
    format: str
    episodes: int = 0
    episode_s: float = 0.0
    frames: int = 0
    wall_s: float = 0.0
    cpu_s: float = 0.0
    x_realtime_wall: float = 0.0
    x_realtime_cpu: float = 0.0
    video_share: float = float("nan")
    sampled_wall_s: float = 0.0
    validate_s: float = 0.0
    bytes: int = 0
    mb_per_episode_min: float = 0.0
    target_x: float | None = None
    meets_target: bool | None = None
    error: str | None = None
    notes: list[str] = field(default_factory=list)


def _export(
    fmt: str, root: Path, out: Path, progress: Callable[[int, int, str], None] | None
) -> tuple[float, float, Any]:
    from telerig.export import export

    shutil.rmtree(out, ignore_errors=True)
    cpu, wall = time.process_time(), time.perf_counter()
    summary = export(root, fmt, out, progress=progress)
    return time.perf_counter() - wall, time.process_time() - cpu, summary


def bench_format(fmt: str, root: Path, work: Path, episode_s: float) -> FormatResult:
    from telerig.export.run import build_exporter

    result = FormatResult(fmt, target_x=TARGETS.get(fmt))
    exporter = build_exporter(fmt)  # imports the writer modules before the clock starts
    out = work / fmt

    def progress(done: int, total: int, episode_id: str) -> None:
        console.print(f"  {fmt}: {done}/{total} {episode_id}", highlight=False)

    try:
        wall, cpu, summary = _export(fmt, root, out, progress)
    except Exception as exc:  # a format that fails is a row with its error, the others still run
        result.error = f"{type(exc).__name__}: {exc}"
        console.print(f"  [red]{fmt} failed:[/] {result.error}", highlight=False)
        return result
    result.episodes = len(summary.added)
    result.episode_s = episode_s
    result.frames = summary.frames
    result.wall_s, result.cpu_s = wall, cpu
    result.x_realtime_wall = episode_s / wall
    result.x_realtime_cpu = episode_s / cpu if cpu > 0 else float("nan")
    result.bytes = _tree_bytes(out)
    result.mb_per_episode_min = result.bytes / 1e6 / (episode_s / 60.0)
    t = time.perf_counter()
    exporter.validate(out).raise_if_invalid(out)
    result.validate_s = time.perf_counter() - t
    if result.target_x is not None:
        result.meets_target = result.x_realtime_wall >= result.target_x

    sampler = StackSampler()
    sampler.start()
    try:
        result.sampled_wall_s, _, _ = _export(fmt, root, work / f"{fmt}-sampled", None)
    finally:
        result.video_share = sampler.stop()
        shutil.rmtree(work / f"{fmt}-sampled", ignore_errors=True)
    return result


# --- quality gates and score ---------------------------------------------------------------------


def bench_qa(episode_dirs: list[Path], episode_s: float) -> dict[str, Any]:
    """Gate + score time per episode-minute, or the note why it did not run."""
    try:
        from telerig.config.qa import QaThresholds
        from telerig.qa.gates import evaluate
        from telerig.qa.score import score
    except ImportError as exc:
        return {"skipped": f"telerig.qa is not importable here ({exc}); gates and score not timed"}
    thresholds = QaThresholds()
    gates_s = score_s = 0.0
    failed: dict[str, int] = {}
    for d in episode_dirs:
        t = time.perf_counter()
        report = evaluate(d, thresholds)
        gates_s += time.perf_counter() - t
        t = time.perf_counter()
        score(d, report, task_median_s=None)
        score_s += time.perf_counter() - t
        for v in report.verdicts:
            if v.passed is False:
                failed[v.gate] = failed.get(v.gate, 0) + 1
    minutes = episode_s / 60.0
    return {
        "episodes": len(episode_dirs),
        "gates_s": gates_s,
        "score_s": score_s,
        "gates_s_per_episode_min": gates_s / minutes,
        "score_s_per_episode_min": score_s / minutes,
        "total_s_per_episode_min": (gates_s + score_s) / minutes,
        "failed_gates": failed,
    }


# --- main -----------------------------------------------------------------------------------------


def _pin(cpu: int | None) -> str:
    if cpu is None:
        return "not pinned"
    if not hasattr(os, "sched_setaffinity"):
        return "not pinned (no sched_setaffinity on this OS)"
    os.sched_setaffinity(0, {cpu})  # this thread; threads started later (PyAV's) inherit it
    return f"pinned to CPU {cpu}"


def _table(rows: list[FormatResult], qa: dict[str, Any], meta: dict[str, Any]) -> Table:
    table = Table(
        title=f"export of {meta['episodes']} demo episode(s), {meta['episode_s']:.1f} episode-s, "
        f"one 640x480 camera; {meta['affinity']}",
        title_justify="left",
    )
    for name in (
        "format",
        "frames",
        "wall s",
        "x real time",
        "x per CPU-s",
        "video share",
        "validate s",
        "MB / episode-min",
        "target",
    ):
        table.add_column(name, justify="left" if name == "format" else "right")
    for r in rows:
        if r.error is not None:
            table.add_row(r.format, "-", "-", "-", "-", "-", "-", "-", f"error: {r.error[:60]}")
            continue
        target = "-" if r.target_x is None else f"{'ok' if r.meets_target else 'MISSED'} (>= {r.target_x:g}x)"
        table.add_row(
            r.format,
            str(r.frames),
            f"{r.wall_s:.2f}",
            f"{r.x_realtime_wall:.1f}x",
            f"{r.x_realtime_cpu:.1f}x",
            f"{100 * r.video_share:.0f} %",
            f"{r.validate_s:.2f}",
            f"{r.mb_per_episode_min:.1f}",
            target,
        )
    table.add_row(
        "(recording)", "-", "-", "-", "-", "-", "-", f"{meta['recording_mb_per_episode_min']:.1f}", "-"
    )
    if "skipped" in qa:
        table.caption = f"gates + score: skipped: {qa['skipped']}"
    else:
        table.caption = (
            f"gates + score: {qa['total_s_per_episode_min']:.2f} s per episode-minute "
            f"(gates {qa['gates_s_per_episode_min']:.2f}, score {qa['score_s_per_episode_min']:.2f}; "
            f"{qa['episodes']} episodes)"
        )
    return table


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--episodes", type=int, default=3, help="demo episodes to record (default 3)")
    parser.add_argument("--duration", type=float, default=20.0, help="seconds per episode (default 20)")
    parser.add_argument("--data-root", type=Path, default=None, help="reuse the episodes of this data root")
    parser.add_argument("--formats", default=None, help="comma-separated formats (default: every registered)")
    parser.add_argument("--cpu", type=int, default=None, help="CPU to pin to (default: the last one)")
    parser.add_argument("--no-pin", action="store_true", help="do not pin to one CPU")
    parser.add_argument("--json", type=Path, default=RESULTS, help=f"results JSON (default {RESULTS})")
    args = parser.parse_args()

    from telerig.registry import EXPORTERS

    formats = args.formats.split(",") if args.formats else sorted(EXPORTERS.names())
    with tempfile.TemporaryDirectory(prefix="telerig-bench-export-") as tmp:
        root = args.data_root or Path(tmp) / "data"
        if args.data_root is None:
            record(root, args.episodes, args.duration)
        summaries = EpisodeStore(root).list()
        if not summaries:
            raise SystemExit(f"no committed episode in {root}")
        episode_s = sum(s.duration_s or 0.0 for s in summaries)
        recording_bytes = sum(_tree_bytes(s.path) for s in summaries)
        cpu = None if args.no_pin else (args.cpu if args.cpu is not None else (os.cpu_count() or 1) - 1)
        affinity = _pin(cpu)
        meta: dict[str, Any] = {
            "python": platform.python_version(),
            "machine": platform.machine(),
            "cpus": os.cpu_count(),
            "load_avg_1m": os.getloadavg()[0],
            "affinity": affinity,
            "episodes": len(summaries),
            "episode_s": episode_s,
            "recording_mb_per_episode_min": recording_bytes / 1e6 / (episode_s / 60.0),
            "sample_interval_s": SAMPLE_INTERVAL_S,
        }
        console.print(
            f"{len(summaries)} episodes, {episode_s:.1f} episode-s in {root}; {affinity}; formats: "
            + ", ".join(formats),
            highlight=False,
        )
        work = Path(tmp) / "exports"
        work.mkdir()
        rows = []
        for fmt in formats:
            console.print(f"[bold]{fmt}[/]")
            rows.append(bench_format(fmt, root, work, episode_s))
        console.print("[bold]quality gates + score[/]")
        qa = bench_qa([s.path for s in summaries], episode_s)
        meta["load_avg_1m_end"] = os.getloadavg()[0]
    console.print(_table(rows, qa, meta))
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps({"meta": meta, "formats": [asdict(r) for r in rows], "qa": qa}, indent=2))
    console.print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
