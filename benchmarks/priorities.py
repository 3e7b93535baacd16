"""CPU priorities by role (runtime.priorities): the control loop's latency and jitter beside the camera.

Runs the demo rig (scripted VR controller → embedded Mosquitto → control node → MuJoCo driver,
with its simulated 640x480@30 camera rendering, encoding and previewing beside it) under each
priority setting in turn, the settings interleaved and repeated, all in this one process (the
robot too: ``with_isolation("threads")``, the configuration these settings were chosen in; the
shipped demo rig runs its robot in a process of its own under SCHED_RR, which latency.py measures):

* ``before``: what telerig did before runtime.priorities: only the render process at nice 10;
* ``priorities``: the defaults (control threads nice -10 where the host allows, the station's
  other threads and the render processes SCHED_BATCH nice 10);
* ``control nice -10 only``: the control threads raised, everything else as before;
* ``render SCHED_IDLE 19`` / ``render nice 19``: the defaults with the render process lower still;
* ``control SCHED_RR 10``: the defaults with the control threads under SCHED_RR 10.

``--only NAME`` (repeatable) picks settings; the default runs ``before``, ``priorities`` and
``control nice -10 only``.

Per run: input-to-actuation latency p50/p99 (the control nodes' tracker), the interval between
applied commands (mean, std, from the recorded MCAP), the camera's delivered frame rate, and the
priority each role got. The table gives the median over the repeats and the min-max beside it.

Usage: python benchmarks/priorities.py [--duration 12] [--repeat 3] [--no-camera]
       [--out benchmarks/results/priorities.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

os.environ.setdefault("MUJOCO_GL", "osmesa")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])

from rich.console import Console
from rich.table import Table

from telerig import priority
from telerig.config import load_rig
from telerig.config.priorities import PriorityConfig
from telerig.ir.mcap_log import iter_raw
from telerig.runtime import streams
from telerig.runtime.process_settings import control_process
from telerig.runtime.rig import RigRuntime
from telerig.store.episodes import EpisodeStore
from telerig.store.manifest_extra import EpisodeExtra

sys.path.insert(0, str(Path(__file__).parent))
from host_steal import StealMeter, steal_warning

#: Name -> settings, in the order each repeat runs them.
SETTINGS: dict[str, PriorityConfig] = {
    "before": PriorityConfig(
        control_nice=0, work_nice=0, work_policy="other", render_nice=10, render_policy="other"
    ),
    "priorities": PriorityConfig(),
    "control nice -10 only": PriorityConfig(
        work_nice=0, work_policy="other", render_nice=10, render_policy="other"
    ),
    "render SCHED_IDLE 19": PriorityConfig(render_nice=19, render_policy="idle"),
    "render nice 19": PriorityConfig(render_nice=19, render_policy="other"),
    "control SCHED_RR 10": PriorityConfig(control_realtime=10),
}


def measure(settings: PriorityConfig, *, camera: bool, duration_s: float) -> dict[str, Any]:
    """Record one episode of the demo rig under ``settings``; latency, intervals, camera rate."""
    # The robot in this process (the demo rig runs it in one of its own): the settings are this
    # process's threads' priorities, and the control node's latencies are read here.
    config = load_rig("demo").with_isolation("threads").with_runtime(priorities=settings.model_dump())
    if not camera:
        config = config.model_copy(update={"cameras": []})
    with (
        tempfile.TemporaryDirectory() as tmp,
        control_process(),
        RigRuntime(config, data_root=Path(tmp)) as runtime,
    ):
        with StealMeter() as steal:
            result = runtime.run_episode(duration_s)
        applied = priority.applied()
        cameras = EpisodeExtra.of(EpisodeStore(Path(tmp)).get(result.episode_id)).cameras
        latency_ms = np.concatenate([n.latency.values_ns() for n in runtime.controls.values()]) / 1e6
        suffix = "/" + streams.JOINT_SENT
        sent = np.array(
            [pub for topic, _, _, pub in iter_raw(result.path / "episode.mcap") if topic.endswith(suffix)],
            dtype=np.int64,
        )
    intervals_ms = np.diff(np.sort(sent)) / 1e6
    return {
        "commands": int(latency_ms.size),
        "latency_p50_ms": float(np.percentile(latency_ms, 50)),
        "latency_p99_ms": float(np.percentile(latency_ms, 99)),
        "interval_mean_ms": float(intervals_ms.mean()),
        "interval_std_ms": float(intervals_ms.std()),
        "camera_fps": sum(result.camera_frames.values()) / duration_s,
        "encoder_dropped": sum(c.dropped for c in cameras.values()),
        "applied": applied,
        "steal_fraction": steal.fraction,
    }


def _spread(values: list[float]) -> str:
    return f"{statistics.median(values):.2f} ({min(values):.2f}-{max(values):.2f})"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=12.0, help="seconds per episode")
    parser.add_argument("--repeat", type=int, default=3, help="runs of each setting, interleaved")
    parser.add_argument("--no-camera", action="store_true", help="the control path alone")
    parser.add_argument("--only", action="append", choices=list(SETTINGS), help="settings to run")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/priorities.json"))
    args = parser.parse_args()
    console = Console(width=140)
    names = args.only or ["before", "priorities", "control nice -10 only"]
    runs: dict[str, list[dict[str, Any]]] = {name: [] for name in names}
    load = []
    for i in range(args.repeat):
        for name in names:
            console.print(f"run {i + 1}/{args.repeat}: {name} ({args.duration:g} s) ...")
            load.append(os.getloadavg()[0])
            runs[name].append(measure(SETTINGS[name], camera=not args.no_camera, duration_s=args.duration))
    what = "control only" if args.no_camera else "control + camera 640x480@30"
    table = Table(
        title=f"demo rig, {what}: median (min-max) of {args.repeat} runs, {os.cpu_count()} cores, "
        f"load average {min(load):.1f}-{max(load):.1f}"
    )
    columns = (
        "settings",
        "p50 ms",
        "p99 ms",
        "interval std ms",
        "camera fps",
        "encoder drops",
        "commands",
        "steal %",
    )
    for col in columns:
        table.add_column(col, justify="left" if col == "settings" else "right")
    for name, rs in runs.items():
        stolen = [100 * r["steal_fraction"] for r in rs if r["steal_fraction"] is not None]  # none off Linux
        table.add_row(
            name,
            _spread([r["latency_p50_ms"] for r in rs]),
            _spread([r["latency_p99_ms"] for r in rs]),
            _spread([r["interval_std_ms"] for r in rs]),
            _spread([r["camera_fps"] for r in rs]),
            _spread([float(r["encoder_dropped"]) for r in rs]),
            _spread([float(r["commands"]) for r in rs]),
            _spread(stolen) if stolen else "-",
        )
    console.print(table)
    if warning := steal_warning([r["steal_fraction"] for rs in runs.values() for r in rs]):
        console.print(f"[yellow]{warning}[/]")
    for name, rs in runs.items():
        console.print(f"{name}: {rs[-1]['applied']}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(
        json.dumps(
            {
                "benchmark": "priorities",
                "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
                "load_average": load,
                "camera": not args.no_camera,
                "duration_s": args.duration,
                "settings": {name: SETTINGS[name].model_dump() for name in names},
                "runs": runs,
            },
            indent=2,
        )
    )
    console.print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
