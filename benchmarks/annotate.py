"""telerig process stage 4 (annotate): what the client side costs per clip, model time left out.

The model's own latency depends on the GPU serving it; what telerig adds is decoding the clip,
scaling and JPEG-encoding the stills, base64, the request, validating the answer, hashing the clip
for the cache and the file locks of the host-wide limits. Measured on generated clips (640x480,
30 fps H.264, a keyframe every second), this process pinned to one CPU core
(``sched_setaffinity``), against the tests' chat-completions server (tests/process/chat_server.py)
in its own process on 127.0.0.1, answering at once (its CPU is not counted).

- baseline in the same run: a plain PyAV decode of every frame of the same clips, as video seconds
  per CPU second; each row's ratio = its rate / the baseline's;
- stills: ``sample_stills`` for N frames at 448 px (decodes up to the last still, encodes N JPEGs),
  and the base64 payload of one request [KiB] (the generated texture is noise: JPEG's worst case);
- long clips (``--long`` clips of ``--long-seconds``): 8 stills by seeking to the keyframe before
  each (the default for stills more than 2 s apart) against one decoding pass, and decode-all;
- stage: ``AnnotateStage.run`` with a model, cache empty (every clip one request), then again with
  the cache full (hash + cache read only); request payload bytes per clip; token totals as reported.

Usage: python benchmarks/annotate.py [--clips 8] [--seconds 3] [--frames 4,8,16] [--long 2]
       [--long-seconds 30] [--cpu 0]
       [--json benchmarks/results/annotate.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
import uuid
from fractions import Fraction
from pathlib import Path
from typing import Any

import av
import numpy as np
import psutil
from rich.console import Console
from rich.table import Table

from telerig.config.process import AnnotateSettings
from telerig.process import annotate
from telerig.process.annotate import AnnotateStage, sample_stills
from telerig.process.stage import Item, StageContext
from telerig.process.vlm import image_part

ROOT = Path(__file__).resolve().parents[1]
W, H, FPS = 640, 480, 30

_SERVER = """
import importlib.util, sys
spec = importlib.util.spec_from_file_location("chat_server", sys.argv[1])
mod = importlib.util.module_from_spec(spec); sys.modules["chat_server"] = mod; spec.loader.exec_module(mod)
srv = mod.ChatServer()
with srv.running():
    print(srv.url, flush=True)
    sys.stdin.read()
    print(len(srv.seen), len(srv.shape_errors), flush=True)
"""


def make_clips(folder: Path, n: int, seconds: float) -> list[Path]:
    """``n`` H.264 clips of a moving texture, ``seconds`` long each."""
    rng = np.random.default_rng(7)
    texture = rng.integers(0, 255, (H * 2, W * 2, 3), dtype=np.uint8)
    paths = []
    for i in range(n):
        path = folder / f"{uuid.UUID(int=i + 1)}.mp4"
        with av.open(str(path), "w") as container:
            stream = container.add_stream("libx264", rate=Fraction(FPS, 1))
            stream.width, stream.height, stream.pix_fmt = W, H, "yuv420p"
            stream.options = {"preset": "veryfast", "g": str(FPS)}
            for k in range(round(seconds * FPS)):
                y, x = (k * 3 + i * 17) % H, (k * 5) % W
                frame = av.VideoFrame.from_ndarray(
                    np.ascontiguousarray(texture[y : y + H, x : x + W]), "rgb24"
                )
                for packet in stream.encode(frame):
                    container.mux(packet)
            for packet in stream.encode():
                container.mux(packet)
        paths.append(path)
    return paths


def cpu_s() -> float:
    t = psutil.Process().cpu_times()
    return t.user + t.system


def timed(fn: Any) -> tuple[float, float, Any]:
    c0, w0 = cpu_s(), time.perf_counter()
    result = fn()
    return cpu_s() - c0, time.perf_counter() - w0, result


def decode_all(paths: list[Path]) -> int:
    frames = 0
    for p in paths:
        with av.open(str(p)) as c:
            frames += sum(1 for _ in c.decode(video=0))
    return frames


def run_stage(work: Path, clips_dir: Path, settings: AnnotateSettings) -> dict[str, float]:
    out = work / "items" / "bench" / "annotate"
    out.mkdir(parents=True, exist_ok=True)
    ctx = StageContext(out, work, {"clips": clips_dir}, settings, lambda _: None)
    item = Item("bench", "video", (), None, "0" * 64, {"task": "benchmark"})
    result = AnnotateStage().run(item, ctx)
    if result.status != "ok":
        raise SystemExit(f"stage {result.status}: {result.message}")
    return dict(result.metrics)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--clips", type=int, default=8)
    p.add_argument("--seconds", type=float, default=3.0)
    p.add_argument("--frames", default="4,8,16")
    p.add_argument("--long", type=int, default=2)
    p.add_argument("--long-seconds", type=float, default=30.0)
    p.add_argument("--cpu", type=int, default=0)
    p.add_argument("--json", type=Path, default=Path("benchmarks/results/annotate.json"))
    args = p.parse_args()
    console = Console(width=110)
    frame_counts = [int(x) for x in args.frames.split(",")]

    server = subprocess.Popen(
        [sys.executable, "-c", _SERVER, str(ROOT / "tests" / "process" / "chat_server.py")],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    assert server.stdout is not None
    assert server.stdin is not None
    url = server.stdout.readline().strip()
    os.sched_setaffinity(0, {args.cpu})  # after the server started: it keeps its own cores
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="telerig-bench-annotate-") as tmp:
        work = Path(tmp)
        clips_dir = work / "clips"
        clips_dir.mkdir()
        console.print(f"generating {args.clips} clips of {args.seconds:g} s ({W}x{H}, {FPS} fps)...")
        paths = make_clips(clips_dir, args.clips, args.seconds)
        entries = [{"uuid": p.stem, "file": p.name, "label": "move"} for p in paths]
        (clips_dir / "clips.json").write_text(json.dumps(entries))
        video_s = args.clips * args.seconds

        decode_all(paths[:1])  # warm up codecs and the page cache
        cpu, _, _ = timed(lambda: decode_all(paths))
        base = video_s / cpu
        rows.append({"step": "decode all (baseline)", "video_s_per_cpu_s": base, "ratio": 1.0})
        for n in frame_counts:
            cpu, wall, stills = timed(lambda n=n: [sample_stills(q, n) for q in paths])
            payload = sum(len(image_part(j)["image_url"]["url"]) for s in stills for j in s) / len(paths)
            rows.append(
                {
                    "step": f"{n} stills",
                    "video_s_per_cpu_s": video_s / cpu,
                    "ratio": video_s / cpu / base,
                    "payload_kib_per_clip": payload / 1024,
                }
            )
        if args.long:
            long_dir = work / "long"
            long_dir.mkdir()
            long_paths = make_clips(long_dir, args.long, args.long_seconds)
            long_s = args.long * args.long_seconds
            cpu, _, _ = timed(lambda: decode_all(long_paths))
            long_base = long_s / cpu
            rows.append({"step": "long: decode all", "video_s_per_cpu_s": long_base, "ratio": 1.0})
            gap = annotate._SEEK_GAP_S
            for label, seek_gap in (("one pass", 1e9), ("seeking", gap)):
                annotate._SEEK_GAP_S = seek_gap
                cpu, _, stills = timed(lambda: [sample_stills(q, 8) for q in long_paths])
                annotate._SEEK_GAP_S = gap
                rows.append(
                    {
                        "step": f"long: 8 stills, {label}",
                        "video_s_per_cpu_s": long_s / cpu,
                        "ratio": long_s / cpu / long_base,
                    }
                )
        for n in frame_counts:
            settings = AnnotateSettings(
                url=url, model=f"bench-{n}", frames=n, concurrency=4, requests_per_minute=100_000
            )
            cpu, wall, metrics = timed(lambda s=settings: run_stage(work, clips_dir, s))
            rows.append(
                {
                    "step": f"stage {n}, cold",
                    "video_s_per_cpu_s": video_s / cpu,
                    "ratio": video_s / cpu / base,
                    "clips_per_wall_s": args.clips / wall,
                    "requests": metrics["requests"],
                    "prompt_tokens": metrics["prompt_tokens"],
                }
            )
            cpu, wall, metrics = timed(lambda s=settings: run_stage(work, clips_dir, s))
            rows.append(
                {
                    "step": f"stage {n}, cached",
                    "video_s_per_cpu_s": video_s / cpu,
                    "ratio": video_s / cpu / base,
                    "clips_per_wall_s": args.clips / wall,
                    "requests": metrics["requests"],
                }
            )
    server.stdin.close()
    seen, shape_errors = server.stdout.readline().split()
    server.wait(timeout=10)
    if int(shape_errors):
        raise SystemExit(f"the server refused {shape_errors} of {seen} requests as malformed")

    table = Table(
        title=f"annotate client side: {args.clips} clips x {args.seconds:g} s, 1 core (cpu {args.cpu})"
    )
    for col in ("step", "video s/CPU s", "vs decode", "KiB/request", "clips/wall s", "requests"):
        table.add_column(col, justify="right" if col != "step" else "left")
    for r in rows:
        table.add_row(
            r["step"],
            f"{r['video_s_per_cpu_s']:.1f}",
            f"{r['ratio']:.2f}",
            f"{r['payload_kib_per_clip']:.0f}" if "payload_kib_per_clip" in r else "",
            f"{r['clips_per_wall_s']:.1f}" if "clips_per_wall_s" in r else "",
            f"{r['requests']:.0f}" if "requests" in r else "",
        )
    console.print(table)
    out = {
        "benchmark": "annotate",
        "host": platform.node(),
        "load_avg": os.getloadavg(),
        "clips": args.clips,
        "clip_seconds": args.seconds,
        "size": [W, H],
        "fps": FPS,
        "requests_seen_by_server": int(seen),
        "rows": rows,
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(out, indent=2) + "\n")
    console.print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
