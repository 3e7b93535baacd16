"""telerig process (issue 15) throughput; stage 1, the frame filter: video s per CPU s and recall per rate.

Only the filter so far; the other stages and the 1 -> 2 Dask worker scaling belong here too.

Generated egocentric-like footage (640x480, 30 fps H.264, a keyframe every second): a textured
empty scene, spans with a drawn hand (MediaPipe 0.10.21's palm detector finds it), a short 1 s hand
span, a shaken span (the whole picture jumps each frame) and a dark tail; the hand spans are the
ground truth. Pinned to one CPU core (``sched_setaffinity``; the MediaPipe tracker process started
after the pin inherits it). For each sample rate and hand model the filter runs once untimed (the
tracker starts, ~6 s) and then timed; CPU = this process + the tracker process (psutil).

- throughput: video seconds per CPU second (one core), and per wall second;
- baseline in the same run: a plain PyAV decode of the same file (every frame, what the filter's
  decode pass costs at least), as video seconds per CPU second; ratio = filter / decode;
- recall: the fraction of ground-truth hand seconds kept; spill: the fraction of non-hand seconds
  kept (padding and keyframe alignment add some).

Usage: python benchmarks/pipeline.py [--duration 30] [--rates 1,2,5] [--models full,lite] [--cpu 0]
       [--json benchmarks/results/pipeline.json]
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
import numpy.typing as npt
import psutil
from rich.console import Console
from rich.table import Table

from telerig.config.process import FilterSettings
from telerig.devices.markerless.fake import synthetic_hand_frame
from telerig.process.filter import FILTER_FILE, FilterStage
from telerig.process.hands import MediaPipeDetectorConfig, MediaPipeHandDetector
from telerig.process.stage import Item, StageContext

W, H, FPS = 640, 480, 30
Image = npt.NDArray[np.uint8]


def footage(path: Path, duration_s: float) -> list[tuple[float, float]]:
    """Write the test footage; return the ground-truth hand spans [s]."""
    rng = np.random.default_rng(0)
    # A textured scene (blocks of 8 px, softened) so the blur measure sees a sharp frame.
    tex = rng.integers(-25, 26, (H // 8, W // 8, 1)).repeat(8, 0).repeat(8, 1).astype(np.float32)
    hands = [synthetic_hand_frame(t) for t in (0.0, 0.5)]
    shade = (0.7 + 0.6 * np.arange(W, dtype=np.float32) / W)[None, :, None]
    plain = np.broadcast_to(np.array([40.0, 60.0, 90.0], np.float32) * shade, (H, W, 3))
    masks = [np.abs(h.astype(np.float32) - plain).max(axis=2, keepdims=True) > 25 for h in hands]
    scene = (plain + tex).clip(0, 255)
    with_hand = [np.where(m, h.astype(np.float32), scene) for h, m in zip(hands, masks, strict=True)]
    d = duration_s
    truth = [(0.17 * d, 0.4 * d), (0.5 * d, 0.5 * d + 1.0), (0.7 * d, 0.85 * d)]
    shaken = (0.55 * d, 0.65 * d)
    dark_from = 0.9 * d

    def frame(k: int) -> Image:
        t = k / FPS
        img: npt.NDArray[Any] = scene
        if any(a <= t < b for a, b in truth):
            img = with_hand[(k // 8) % 2]
        if shaken[0] <= t < shaken[1]:
            img = np.roll(scene, (int(rng.integers(-40, 41)), int(rng.integers(-40, 41))), axis=(0, 1))
        if t >= dark_from:
            img = scene * 0.05
        noise = rng.integers(-3, 4, (H, W, 1))
        return np.asarray((img + noise).clip(0, 255), dtype=np.uint8)

    with av.open(str(path), "w") as c:
        st = c.add_stream("libx264", rate=FPS)
        st.width, st.height, st.pix_fmt = W, H, "yuv420p"
        st.options = {
            "preset": "veryfast",
            "crf": "23",
            "g": str(FPS),
            "keyint_min": str(FPS),
            "sc_threshold": "0",
        }
        for k in range(round(d * FPS)):
            for p in st.encode(av.VideoFrame.from_ndarray(frame(k), format="rgb24")):
                c.mux(p)
        for p in st.encode():
            c.mux(p)
    return truth


def overlap(a: list[tuple[float, float]], b: list[tuple[float, float]]) -> float:
    return sum(max(0.0, min(x1, y1) - max(x0, y0)) for x0, x1 in a for y0, y1 in b)


def decode_cpu(path: Path) -> float:
    c0 = time.process_time()
    with av.open(str(path)) as c:
        c.streams.video[0].thread_type = "AUTO"
        for _ in c.decode(video=0):
            pass
    return time.process_time() - c0


def run_filter(path: Path, rate: float, model: str, out: Path) -> dict[str, Any]:
    settings = FilterSettings(sample_hz=rate, detector={"type": "mediapipe", "hand_model": model})
    config = MediaPipeDetectorConfig.model_validate({"hand_model": model})
    item = Item("bench", "video", (path,), None, "0", {})
    with MediaPipeHandDetector(config) as det, FilterStage(det) as stage:
        if det._proc is None:
            raise SystemExit("the tracker did not start")
        child = psutil.Process(det._proc.pid)
        warm = out / "warm"
        warm.mkdir(parents=True)
        stage.run(item, StageContext(warm, out, {}, settings, lambda f: None))  # untimed warm-up
        timed = out / "timed"
        timed.mkdir()
        c_child0 = sum(child.cpu_times()[:2])
        c0, w0 = time.process_time(), time.perf_counter()
        result = stage.run(item, StageContext(timed, out, {}, settings, lambda f: None))
        cpu = time.process_time() - c0 + sum(child.cpu_times()[:2]) - c_child0
        wall = time.perf_counter() - w0
        detector_cpu = sum(child.cpu_times()[:2]) - c_child0
    doc = json.loads((timed / FILTER_FILE).read_text())["videos"][0]
    return {"result": result, "cpu_s": cpu, "wall_s": wall, "detector_cpu_s": detector_cpu, "video": doc}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--duration", type=float, default=30.0)
    p.add_argument("--rates", default="1,2,5")
    p.add_argument("--models", default="full,lite")
    p.add_argument("--cpu", type=int, default=0)
    p.add_argument("--json", type=Path, default=Path("benchmarks/results/pipeline.json"))
    args = p.parse_args()
    os.sched_setaffinity(0, {args.cpu})
    console = Console()
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        video = Path(tmp) / "ego.mp4"
        console.print(f"writing {args.duration:g} s of {W}x{H} {FPS} fps footage...")
        truth = footage(video, args.duration)
        truth_s = sum(b - a for a, b in truth)
        decode_cpu(video)
        base = min(decode_cpu(video) for _ in range(2))
        for model in args.models.split(","):
            for rate in (float(r) for r in args.rates.split(",")):
                console.print(f"filter: {rate:g} Hz, {model} hand model...")
                r = run_filter(video, rate, model, Path(tmp) / f"{model}-{rate:g}")
                kept = [tuple(s) for s in r["video"]["kept"]]
                kept_s = sum(b - a for a, b in kept)
                hit = overlap(kept, truth)
                rows.append(
                    {
                        "model": model,
                        "sample_hz": rate,
                        "x_realtime_per_cpu": args.duration / r["cpu_s"],
                        "x_realtime_wall": args.duration / r["wall_s"],
                        "cpu_s": r["cpu_s"],
                        "detector_cpu_s": r["detector_cpu_s"],
                        "ratio_to_decode": (args.duration / r["cpu_s"]) / (args.duration / base),
                        "recall": hit / truth_s,
                        "spill": (kept_s - hit) / (args.duration - truth_s),
                        "kept_fraction": r["video"]["kept_fraction"],
                        "kept": kept,
                        "status": r["result"].status,
                    }
                )
    table = Table(
        title=f"frame filter, {args.duration:g} s of {W}x{H} {FPS} fps H.264, one core (CPU {args.cpu})"
    )
    for col in (
        "model",
        "Hz",
        "x RT / CPU-s",
        "x RT wall",
        "detector CPU",
        "vs decode",
        "recall",
        "spill",
        "kept",
    ):
        table.add_column(col, justify="right")
    for r in rows:
        table.add_row(
            r["model"],
            f"{r['sample_hz']:g}",
            f"{r['x_realtime_per_cpu']:.1f}",
            f"{r['x_realtime_wall']:.1f}",
            f"{r['detector_cpu_s'] / r['cpu_s']:.0%}",
            f"{r['ratio_to_decode']:.2f}",
            f"{r['recall']:.3f}",
            f"{r['spill']:.3f}",
            f"{r['kept_fraction']:.3f}",
        )
    console.print(table)
    console.print(
        f"baseline: PyAV decode alone {args.duration / base:.1f} x real time per CPU second; truth {truth}"
    )
    out = {
        "benchmark": "pipeline",
        "stage": "filter",
        "host": platform.node(),
        "load": os.getloadavg(),
        "duration_s": args.duration,
        "decode_x_realtime_per_cpu": args.duration / base,
        "truth": truth,
        "rows": rows,
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(out, indent=2) + "\n")
    console.print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
