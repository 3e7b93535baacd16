"""Export throughput per dataset format, the share of it spent on video, dataset size, gate + score time.

Two sources of episodes:

- ``demo``: N episodes of the shipped demo rig (scripted VR operator, simulated UR5e, one 640x480
  camera), recorded once by ``telerig run demo`` in a subprocess, or the episodes of ``--data-root``.
  On a loaded host its MuJoCo camera renders below its configured 30 fps, so exports re-encode it;
- ``synthetic 30 fps``: as many full-rate episodes of the same rig (its fingerprint and robot joints,
  100 Hz joint streams, one 640x480 camera at exactly 30 fps written by the recorder's VideoEncoder
  with a frame record per frame): what a rig camera delivering its configured rate gives, whose
  video LeRobot can remux instead of re-encoding (``--synthetic 0`` leaves them out).

Then, pinned to one CPU core (``sched_setaffinity``; PyAV's codec threads inherit it), for every format
registered in ``telerig.registry.EXPORTERS``, after an untimed one-episode warm-up (imports, the
robot model, encoder set-up):

- throughput: episode-seconds exported per wall-second by :func:`telerig.export.export` (select,
  resample, write, validate; what ``telerig export`` runs) into a fresh directory, and per
  CPU-second of the process (what one core does, whatever the neighbours on a shared host take);
- video share: a second export of the same episodes with a stack sampler (every 5 ms, the main
  thread): the fraction of samples inside video work (decoding the recorded MP4 in
  ``CameraTrack.frames``, the LeRobot video writer, HDF5 image datasets, RLDS image encoding, PyAV
  and Pillow code). Sampling rather than a run with video off: every format writes its images, so
  there is no "video off" to compare with; the sampled run's own overhead is in the JSON;
- validation: the exporter's re-read of the dataset, timed alone (part of the export time);
- size on disk per episode-minute (every file under the dataset directory), beside the recording's.

Then the quality gates and score of each demo episode (``telerig.qa.gates.evaluate`` and
``telerig.qa.score.score``), wall and CPU seconds per episode-minute.

Target: LeRobot v3 >= 20x real time with one 640x480 camera, judged per CPU-second (one core).

Usage: python benchmarks/export.py [--episodes 3] [--duration 20] [--data-root DIR] [--synthetic N]
       [--formats lerobot,hdf5] [--cpu 0] [--json benchmarks/results/export.json]
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


W, H, FPS = 640, 480, 30
JOINT_HZ = 100


def _synthetic_frames(n: int, seed: int = 0) -> list[Any]:
    """``n`` RGB 640x480 frames: drifting gradients, two moving squares, mild sensor noise (sigma 2)."""
    import numpy as np

    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:H, 0:W].astype(np.float32)
    frames = []
    for i in range(n):
        phase = 2 * np.pi * i / n
        image = np.stack(
            [
                128 + 90 * np.sin(x / 80 + phase),
                128 + 90 * np.sin(y / 60 - phase),
                128 + 60 * np.sin((x + y) / 120),
            ],
            axis=-1,
        )
        for k, (size, speed) in enumerate(((90, 7), (60, -11))):
            cx, cy = int((W / 2 + speed * i) % (W - size)), int((H / 3 + 50 * k) % (H - size))
            image[cy : cy + size, cx : cx + size] = (230, 40 + 150 * k, 60)
        image += rng.normal(0, 2, image.shape).astype(np.float32)
        frames.append(np.clip(image, 0, 255).astype(np.uint8))
    return frames


def synthesize(root: Path, template: Path, episodes: int, duration: float) -> None:
    """Full-rate episodes of the template's rig: its manifest's fingerprint and robot joints, joint
    streams at 100 Hz (a smooth motion around the template's first measured pose), and one 640x480
    camera at exactly 30 fps written by the recorder's own VideoEncoder (H.264, capture-time pts) with
    a CameraFrame record per frame, committed through EpisodeStore with their virtual start and end.

    Raises:
        SystemExit: the template's manifest has no robot joints record (recorded by an older telerig).
    """
    import numpy as np

    from telerig.bus.topics import Topic
    from telerig.cameras.encoder import DEFAULT_QUEUE_SIZE, VideoEncoder
    from telerig.ir import wire
    from telerig.ir.mcap_log import McapLog, read_log
    from telerig.ir.types import CameraFrame, GripperCommand, JointCommand, JointState, Stamp, now_ns
    from telerig.store.manifest_extra import EpisodeExtra

    store = EpisodeStore(root)
    manifest = json.loads((template / "manifest.json").read_text())
    extra = EpisodeExtra.model_validate(manifest["extra"])
    rig = manifest["rig"]
    if not extra.robot_joints:
        raise SystemExit(f"{template}: no robot_joints in its manifest (older recording); record anew")
    robot, joints_record = next(iter(extra.robot_joints.items()))
    (camera,) = list(extra.cameras) or ["scene"]
    names = tuple(joints_record.joints)
    home = next(
        e.sample.positions
        for e in read_log(template / "episode.mcap", topics=[str(Topic(rig, robot, "joint_state"))])
        if isinstance(e.sample, JointState)
    )
    frames = _synthetic_frames(2 * FPS)
    console.print(f"synthesizing {episodes} full-rate episode(s) of {duration:g} s (640x480 @ {FPS} fps) ...")
    start = now_ns() + 10**9
    for e in range(episodes):
        t0 = start + e * round((duration + 2) * 1e9)
        draft = store.begin(rig=rig, task=manifest["task"], operator="synthetic", start_ns=t0)
        topic = {
            s: str(Topic(rig, robot, s))
            for s in ("joint_state", "joint_command_sent", "gripper_command_sent")
        }
        frames_topic = str(Topic(rig, camera, "frames"))
        encoder = VideoEncoder(draft.camera_path(camera), width=W, height=H, fps=FPS)
        encoder.start()
        with McapLog(draft.mcap_path) as log:
            n_joint = int(duration * JOINT_HZ)
            for k in range(n_joint):
                t = t0 + k * 10**9 // JOINT_HZ
                q = home + 0.3 * np.sin(2 * np.pi * (k / JOINT_HZ) / 4.0 + np.arange(len(names)))
                stamp = Stamp(robot, k, t, t)
                log.write(
                    topic["joint_command_sent"],
                    wire.encode(JointCommand(stamp, names, q)),
                    log_time_ns=t + 10**6,
                    publish_time_ns=t,
                )
                state = JointState(stamp, names, q - 0.002, np.zeros(len(names)))
                log.write(topic["joint_state"], wire.encode(state), log_time_ns=t + 10**6, publish_time_ns=t)
                opening = 1.0 if (k // JOINT_HZ) % 4 < 2 else 0.0
                log.write(
                    topic["gripper_command_sent"],
                    wire.encode(GripperCommand(stamp, opening)),
                    log_time_ns=t + 10**6,
                    publish_time_ns=t,
                )
            for i in range(int(duration * FPS)):
                t = t0 + i * 10**9 // FPS
                while encoder.frames <= i - DEFAULT_QUEUE_SIZE:  # never drop: wait for the encoder
                    time.sleep(0.002)
                assert encoder.submit(frames[i % len(frames)], t)
                record = CameraFrame(Stamp(camera, i, t, t), camera, i, W, H)
                log.write(frames_topic, wire.encode(record), log_time_ns=t + 10**6, publish_time_ns=t)
        result = encoder.finish()
        cameras = {
            camera: {
                "file": f"cameras/{camera}.mp4",
                "frames": result.frames,
                "dropped": 0,
                "width": W,
                "height": H,
                "fps": FPS,
                "codec": "h264",
            }
        }
        keep = ("fingerprint", "station", "session_id", "robots", "robot_joints")
        n_frames = int(duration * FPS)
        streams = [
            {"name": t, "expected_hz": float(JOINT_HZ), "measured_hz": float(JOINT_HZ), "messages": n_joint}
            for t in topic.values()
        ] + [
            {"name": frames_topic, "expected_hz": float(FPS), "measured_hz": float(FPS), "messages": n_frames}
        ]
        data = {k: v for k, v in manifest["extra"].items() if k in keep} | {
            "cameras": cameras,
            "streams": streams,
        }
        draft.commit(data, end_ns=t0 + round(duration * 1e9))
        console.print(f"  synthetic {e + 1}/{episodes} {draft.id}", highlight=False)


def _tree_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


# --- one format -----------------------------------------------------------------------------------


@dataclass
class FormatResult:
    format: str
    source: str = "demo"
    episodes: int = 0
    episode_s: float = 0.0
    frames: int = 0
    wall_s: float = 0.0
    cpu_s: float = 0.0
    x_realtime_wall: float = 0.0
    x_realtime_cpu: float = 0.0
    video_share: float = float("nan")
    sampled_wall_s: float = 0.0
    sampler_overhead: float = float("nan")
    warmup_s: float = 0.0
    validate_s: float = 0.0
    bytes: int = 0
    mb_per_episode_min: float = 0.0
    target_x: float | None = None
    meets_target: bool | None = None
    error: str | None = None
    notes: list[str] = field(default_factory=list)


def _export(
    fmt: str,
    root: Path,
    out: Path,
    progress: Callable[[int, int, str], None] | None,
    ids: tuple[str, ...] = (),
) -> tuple[float, float, Any]:
    from telerig.export import EpisodeFilter, export

    shutil.rmtree(out, ignore_errors=True)
    # Every committed episode: the station's quality gates may have moved demo episodes to failures/.
    selection = EpisodeFilter(ids=ids, include_failures=True)
    cpu, wall = time.process_time(), time.perf_counter()
    summary = export(root, fmt, out, selection=selection, progress=progress)
    return time.perf_counter() - wall, time.process_time() - cpu, summary


def bench_format(fmt: str, root: Path, work: Path, episode_s: float, first_id: str) -> FormatResult:
    from telerig.export.run import build_exporter

    result = FormatResult(fmt, target_x=TARGETS.get(fmt))
    exporter = build_exporter(fmt)
    work.mkdir(parents=True, exist_ok=True)
    out = work / fmt

    def progress(done: int, total: int, episode_id: str) -> None:
        console.print(f"  {fmt}: {done}/{total} {episode_id}", highlight=False)

    try:
        # Warm-up, not timed: one episode pays the one-off costs (writer imports, the robot model's
        # compile for the joint limits, encoder set-up) that a long export pays once.
        result.warmup_s, _, _ = _export(fmt, root, work / f"{fmt}-warmup", None, ids=(first_id,))
        shutil.rmtree(work / f"{fmt}-warmup", ignore_errors=True)
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
    if result.target_x is not None:  # judged on what one core does, not on what the neighbours left
        result.meets_target = result.x_realtime_cpu >= result.target_x

    sampler = StackSampler()
    sampler.start()
    try:
        result.sampled_wall_s, _, _ = _export(fmt, root, work / f"{fmt}-sampled", None)
        result.sampler_overhead = result.sampled_wall_s / result.wall_s - 1.0
    finally:
        result.video_share = sampler.stop()
        shutil.rmtree(work / f"{fmt}-sampled", ignore_errors=True)
    return result


def _camera_paths(episode_dirs: list[Path]) -> dict[str, Any]:
    """How fast the recorded cameras really ran, and how many episodes' videos can be remuxed
    (every recorded frame used once, in order, at the dataset rate) instead of re-encoded."""
    from telerig.export import load_episode
    from telerig.export.frames import read_manifest
    from telerig.store.manifest_extra import EpisodeExtra

    fps: list[float] = []
    remuxable = 0
    for d in episode_dirs:
        manifest = read_manifest(d)
        frames = sum(c.frames for c in EpisodeExtra.of(manifest).cameras.values())
        fps.append(frames / manifest.duration_s if manifest.duration_s else float("nan"))
        tracks = list(load_episode(d).cameras.values())
        remuxable += int(bool(tracks) and all(t.one_to_one for t in tracks))
    return {"recorded_camera_fps": [round(f, 1) for f in fps], "remuxable_episodes": remuxable}


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
    gates_s = score_s = gates_cpu = score_cpu = 0.0
    failed: dict[str, int] = {}
    for d in episode_dirs:
        t, c = time.perf_counter(), time.process_time()
        report = evaluate(d, thresholds)
        gates_s += time.perf_counter() - t
        gates_cpu += time.process_time() - c
        t, c = time.perf_counter(), time.process_time()
        score(d, report, task_median_s=None)
        score_s += time.perf_counter() - t
        score_cpu += time.process_time() - c
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
        "gates_cpu_s_per_episode_min": gates_cpu / minutes,
        "score_cpu_s_per_episode_min": score_cpu / minutes,
        "total_cpu_s_per_episode_min": (gates_cpu + score_cpu) / minutes,
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
        title=f"export throughput, one 640x480 camera; {meta['affinity']} "
        f"(load average {meta['load_avg_1m']:.1f} on {meta['cpus']} CPUs)",
        title_justify="left",
    )
    for name in (
        "source",
        "format",
        "frames",
        "wall s",
        "x real time",
        "x per CPU-s",
        "video share",
        "validate s",
        "MB / episode-min",
        "target (per CPU-s)",
    ):
        table.add_column(name, justify="left" if name in ("source", "format") else "right")
    for r in rows:
        if r.error is not None:
            table.add_row(r.source, r.format, "-", "-", "-", "-", "-", "-", "-", f"error: {r.error[:60]}")
            continue
        target = "-" if r.target_x is None else f"{'ok' if r.meets_target else 'MISSED'} (>= {r.target_x:g}x)"
        table.add_row(
            r.source,
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
    lines = []
    for name, src in meta["sources"].items():
        lines.append(
            f"{name}: {src['episodes']} episodes, {src['episode_s']:.1f} episode-s, recorded camera "
            f"{', '.join(f'{f:g}' for f in src['recorded_camera_fps'])} fps, "
            f"{src['remuxable_episodes']}/{src['episodes']} remuxable (rest re-encoded), "
            f"recording {src['recording_mb_per_episode_min']:.1f} MB / episode-min"
        )
    if "skipped" in qa:
        lines.append(f"gates + score: skipped: {qa['skipped']}")
    else:
        lines.append(
            f"gates + score (demo episodes): {qa['total_s_per_episode_min']:.2f} s wall, "
            f"{qa['total_cpu_s_per_episode_min']:.2f} CPU-s per episode-minute (gates "
            f"{qa['gates_cpu_s_per_episode_min']:.2f}, score {qa['score_cpu_s_per_episode_min']:.2f} CPU-s; "
            f"{qa['episodes']} episodes)"
        )
    table.caption = "\n".join(lines)
    table.caption_justify = "left"
    return table


def _source(root: Path) -> tuple[list[Any], float, dict[str, Any]]:
    summaries = EpisodeStore(root).list(include_failures=True)
    if not summaries:
        raise SystemExit(f"no committed episode in {root}")
    episode_s = sum(s.duration_s or 0.0 for s in summaries)
    info = {
        "root": str(root),
        "episodes": len(summaries),
        "episode_s": episode_s,
        "recording_mb_per_episode_min": sum(_tree_bytes(s.path) for s in summaries) / 1e6 / (episode_s / 60),
        **_camera_paths([s.path for s in summaries]),
    }
    return summaries, episode_s, info


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--episodes", type=int, default=3, help="demo episodes to record (default 3)")
    parser.add_argument("--duration", type=float, default=20.0, help="seconds per episode (default 20)")
    parser.add_argument("--data-root", type=Path, default=None, help="reuse the episodes of this data root")
    parser.add_argument(
        "--synthetic",
        type=int,
        default=None,
        help="full-rate synthetic episodes (30 fps camera), a second source (default: --episodes; 0: none)",
    )
    parser.add_argument("--formats", default=None, help="comma-separated formats (default: every registered)")
    parser.add_argument("--cpu", type=int, default=None, help="CPU to pin to (default: the last one)")
    parser.add_argument("--no-pin", action="store_true", help="do not pin to one CPU")
    parser.add_argument("--json", type=Path, default=RESULTS, help=f"results JSON (default {RESULTS})")
    args = parser.parse_args()

    from telerig.registry import EXPORTERS

    formats = args.formats.split(",") if args.formats else sorted(EXPORTERS.names())
    with tempfile.TemporaryDirectory(prefix="telerig-bench-export-") as tmp:
        roots = {"demo": args.data_root or Path(tmp) / "data"}
        if args.data_root is None:
            record(roots["demo"], args.episodes, args.duration)
        demo = EpisodeStore(roots["demo"]).list(include_failures=True)
        synthetic = args.episodes if args.synthetic is None else args.synthetic
        if synthetic > 0 and demo:
            roots["synthetic 30 fps"] = Path(tmp) / "synthetic"
            synthesize(roots["synthetic 30 fps"], demo[0].path, synthetic, args.duration)
        cpu = None if args.no_pin else (args.cpu if args.cpu is not None else (os.cpu_count() or 1) - 1)
        affinity = _pin(cpu)
        meta: dict[str, Any] = {
            "python": platform.python_version(),
            "machine": platform.machine(),
            "cpus": os.cpu_count(),
            "load_avg_1m": os.getloadavg()[0],
            "affinity": affinity,
            "sample_interval_s": SAMPLE_INTERVAL_S,
            "sources": {},
        }
        work = Path(tmp) / "exports"
        work.mkdir()
        rows: list[FormatResult] = []
        demo_dirs: list[Path] = []
        demo_s = 0.0
        for name, root in roots.items():
            summaries, episode_s, info = _source(root)
            meta["sources"][name] = info
            if name == "demo":
                demo_dirs, demo_s = [s.path for s in summaries], episode_s
            console.print(
                f"[bold]{name}[/]: {len(summaries)} episodes, {episode_s:.1f} episode-s in {root}; "
                f"{affinity}; formats: {', '.join(formats)}",
                highlight=False,
            )
            for fmt in formats:
                console.print(f"[bold]{name} / {fmt}[/]")
                result = bench_format(fmt, root, work / name.replace(" ", "_"), episode_s, summaries[0].id)
                result.source = name
                rows.append(result)
        console.print("[bold]quality gates + score[/]")
        qa = bench_qa(demo_dirs, demo_s)
        meta["load_avg_1m_end"] = os.getloadavg()[0]
    console.print(_table(rows, qa, meta))
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps({"meta": meta, "formats": [asdict(r) for r in rows], "qa": qa}, indent=2))
    console.print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
