"""Where the operator loop's latency goes, stage by stage, in the demo rig through a real Mosquitto.

Runs the demo rig (scripted VR → embedded Mosquitto → control node: mink IK, safety chain →
MuJoCo driver) twice in one process: without the camera (the control path alone, the baseline) and
with the 640x480@30 camera rendering, encoding and previewing beside it. Per applied command the
control node keeps one row of stamps (:data:`telerig.config.latency.ROBOT_STAGES`: capture →
telerig receive → control node receive → tick → retargeted → applied → first state after it); the
benchmark reads every row of the episode from the live ring (sampled each second) and reports each
stage's p50/p99/max against the rig's budget, and, with the camera, the preview's video stages
(capture → JPEG encoded, both stamped by the camera node in the JPEG → received by a bus client, as
``telerig serve`` receives it). The browser stages (``rendered``, ``video_display``) need a page and
are measured by ``tests/server/test_latency_stages_browser.py`` / the dashboard.

It also times the instrumentation itself: one ``add_stamps`` of a 7-stamp row (what the control
thread pays per applied command) against one ``add`` of a single latency (the ring that was there
before, the baseline), in the same run.

Usage: python benchmarks/latency_stages.py [--duration 10] [--out benchmarks/results/latency_stages.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

os.environ.setdefault("MUJOCO_GL", "osmesa")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])

from rich.console import Console
from rich.table import Table

from telerig.bus.base import Message
from telerig.bus.mqtt import MqttBus
from telerig.bus.topics import Topic
from telerig.config import load_rig
from telerig.config.latency import DEFAULT_BUDGETS_MS, ROBOT_STAGES, VIDEO_STAGES
from telerig.runtime.metrics import LatencyWindow
from telerig.runtime.rig import RigRuntime
from telerig.runtime.robot_host import StageRows
from telerig.server.gateway import jpeg_stamps


def _stats(values_ms: npt.NDArray[np.float64]) -> dict[str, float | int | None]:
    if values_ms.size == 0:
        return {"count": 0, "p50_ms": None, "p99_ms": None, "max_ms": None}
    p50, p99 = np.percentile(values_ms, [50, 99])
    return {
        "count": int(values_ms.size),
        "p50_ms": float(p50),
        "p99_ms": float(p99),
        "max_ms": float(values_ms.max()),
    }


def _stage_rows(runtime: RigRuntime, robot: str) -> Callable[[int], npt.NDArray[np.int64]]:
    """What reads ``robot``'s live stage rows up to a time [ns]: its control node's ring, in a host
    process (the demo rig's ``runtime.isolation: processes``) or in this one."""
    host = runtime.hosts.get(robot)
    if host is not None:
        return lambda now_ns: host.call(StageRows(now_ns))
    return runtime.controls[robot].live.stages.rows


def measure(*, camera: bool, duration_s: float) -> dict[str, Any]:
    """One recorded episode of the demo rig: every applied command's stage row, and the previews'."""
    config = load_rig("demo")
    if not camera:
        config = config.model_copy(update={"cameras": []})
    rows: list[npt.NDArray[np.int64]] = []
    previews: list[tuple[int, int, int]] = []
    with tempfile.TemporaryDirectory() as tmp, RigRuntime(config, data_root=Path(tmp)) as runtime:
        assert runtime.broker_url is not None
        watcher = MqttBus(runtime.broker_url, client_id="stages-bench").connect()

        def on_preview(message: Message) -> None:
            stamps = jpeg_stamps(message.payload)
            if stamps is not None:
                previews.append((*stamps, message.received_ns))

        for c in config.cameras:
            watcher.subscribe(str(Topic(config.name, c.id, "preview")), on_preview)
        read_rows = _stage_rows(runtime, "arm0")
        done = threading.Event()

        def sample() -> None:  # the live ring holds 2 s: read it every second
            while not done.wait(1.0):
                rows.append(read_rows(time.time_ns()))

        sampler = threading.Thread(target=sample, daemon=True)
        sampler.start()
        try:
            result = runtime.run_episode(duration_s)
        finally:
            done.set()
            sampler.join()
            rows.append(read_rows(time.time_ns()))
            watcher.close()
    table = np.unique(np.concatenate(rows), axis=0)
    steps = np.diff(table, axis=1) / 1e6
    stages = {name: _stats(steps[:, i]) for i, name in enumerate(ROBOT_STAGES)}
    stages["end_to_end"] = _stats((table[:, -1] - table[:, 0]) / 1e6)
    if previews:
        p = np.array(previews, dtype=np.int64)
        video = np.diff(p, axis=1) / 1e6
        for i, name in enumerate(VIDEO_STAGES[:2]):
            stages[name] = _stats(video[:, i])
    return {
        "config": "control + camera 640x480@30 (previews 2 Hz)" if camera else "control only",
        "commands": int(table.shape[0]),
        "out_of_order": int(np.count_nonzero((np.diff(table, axis=1) < 0).any(axis=1))),
        "stages_sum_p50_ms": float(sum(v["p50_ms"] or 0.0 for k, v in stages.items() if k in ROBOT_STAGES)),
        "stages": stages,
        "camera_frames": sum(result.camera_frames.values()),
        "previews": len(previews),
    }


def instrumentation_cost(n: int = 200_000) -> dict[str, float]:
    """Per-call cost [us] of the control thread's writes: a 7-stamp row against a single latency."""
    single = LatencyWindow(2.0, 4096)
    staged = LatencyWindow(2.0, 4096, stages=ROBOT_STAGES)
    t = time.time_ns()
    start = time.perf_counter_ns()
    for i in range(n):
        single.add(i, t)
    add_us = (time.perf_counter_ns() - start) / n / 1e3
    start = time.perf_counter_ns()
    for i in range(n):
        staged.add_stamps(t, i, i + 1, i + 2, i + 3, i + 4, i + 5, i + 6)
    stamps_us = (time.perf_counter_ns() - start) / n / 1e3
    return {"add_us": add_us, "add_stamps_us": stamps_us, "ratio": stamps_us / add_us}


def _plot(rows: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [*ROBOT_STAGES, *VIDEO_STAGES[:2]]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=False)
    for ax, key in zip(axes, ("p50_ms", "p99_ms"), strict=True):
        x = np.arange(len(names))
        for j, r in enumerate(rows):
            values = [r["stages"].get(s, {}).get(key) or 0.0 for s in names]
            ax.bar(x + (j - 0.5) * 0.38, values, 0.38, label=r["config"])
        ax.scatter(x, [DEFAULT_BUDGETS_MS[s] for s in names], marker="_", s=300, color="k", label="budget")
        ax.set_xticks(x, [s.replace("video_", "video\n") for s in names], fontsize=8)
        ax.set_yscale("log")
        ax.set_ylabel(f"{key.removesuffix('_ms')} [ms]")
        ax.set_title(f"latency per stage, {key.removesuffix('_ms')}")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=10.0, help="seconds per configuration")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/latency_stages.json"))
    args = parser.parse_args()
    console = Console(width=130)
    rows = []
    for camera in (False, True):
        console.print(
            f"measuring the demo rig {'with' if camera else 'without'} its camera for {args.duration:g} s ..."
        )
        rows.append(measure(camera=camera, duration_s=args.duration))
    cost = instrumentation_cost()
    base, cam = rows
    table = Table(
        title=f"latency per stage, demo rig through Mosquitto "
        f"({os.cpu_count()} cores, load {os.getloadavg()[0]:.1f})"
    )
    for col in (
        "stage",
        "budget ms",
        "p50 ms",
        "p99 ms",
        "max ms",
        "+camera p50",
        "+camera p99",
        "p99 ratio",
    ):
        table.add_column(col, justify="left" if col == "stage" else "right")

    def f(v: float | None, digits: int = 2) -> str:
        return "-" if v is None else f"{v:.{digits}f}"

    for name in (*ROBOT_STAGES, "end_to_end", *VIDEO_STAGES[:2]):
        b, c = base["stages"].get(name, {}), cam["stages"].get(name, {})
        ratio = c["p99_ms"] / b["p99_ms"] if b.get("p99_ms") and c.get("p99_ms") else None
        table.add_row(
            name,
            f(DEFAULT_BUDGETS_MS[name], 0),
            f(b.get("p50_ms")),
            f(b.get("p99_ms")),
            f(b.get("max_ms")),
            f(c.get("p50_ms")),
            f(c.get("p99_ms")),
            "-" if ratio is None else f"{ratio:.2f}x",
        )
    console.print(table)
    for r in rows:
        console.print(
            f"{r['config']}: {r['commands']} commands, {r['out_of_order']} out of order, sum of stage "
            f"p50s {r['stages_sum_p50_ms']:.2f} ms vs end-to-end p50 "
            f"{r['stages']['end_to_end']['p50_ms']:.2f} ms"
            + (f", {r['previews']} previews" if r["previews"] else "")
        )
    console.print(
        f"instrumentation on the control thread: add_stamps (7 stamps) {cost['add_stamps_us']:.2f} us vs "
        f"add (1 latency, the baseline) {cost['add_us']:.2f} us per call: {cost['ratio']:.2f}x"
    )
    over = [
        f"{r['config']}: {k}"
        for r in rows
        for k, v in r["stages"].items()
        if v.get("p99_ms") is not None and v["p99_ms"] > DEFAULT_BUDGETS_MS[k]
    ]
    console.print("over budget (p99): " + (", ".join(over) if over else "none"))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    plot = args.out.with_suffix(".png")
    _plot(rows, plot)
    args.out.write_text(
        json.dumps(
            {
                "benchmark": "latency_stages",
                "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
                "duration_s": args.duration,
                "load_average": os.getloadavg(),
                "budgets_ms": DEFAULT_BUDGETS_MS,
                "results": rows,
                "instrumentation": cost,
                "over_budget": over,
            },
            indent=2,
        )
    )
    console.print(f"wrote {args.out} and {plot}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
