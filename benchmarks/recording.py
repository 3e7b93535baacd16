"""Recorder load: N synthetic 640x480@30 cameras through VideoEncoder + M 100-200 Hz streams into MCAP.

Frames come from a precomputed synthetic source (moving gradients and squares with sensor
noise), so this measures the recorder, not a renderer. Each camera and each stream runs on its
own thread with an absolute schedule; the scheduled instant is the "true" capture time and the
stamp is taken when the source thread wakes, as a driver would. Streams go straight into
McapLog (default) or through an embedded Mosquitto broker and the Recorder node (``--broker``).
At the end the episode is committed with EpisodeStore and the commit is timed, then the cost of
hashing its files alone is measured.

Reported: recorder drops (frames refused by a full encoder queue, samples missing from the MCAP),
source misses apart (deadlines a synthetic source thread overslept by a period: the machine, not the
recorder), process CPU (CPU time / wall, in cores) and the recorder's part of it (less the CPU of the
same source threads picking frames and encoding samples with nothing recording, measured right after
in the same run), MB/s written, commit latency, and alignment
error read back from the files: per camera frame and stream, |recorded offset to the nearest
sample - true offset|, with the samples stamped at capture; beside it, the same error had the
sources been stamped when their Python thread woke up.

Usage: python benchmarks/recording.py [--cameras 6] [--streams 10] [--duration 20] [--broker]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import av
import numpy as np
from rich.console import Console
from rich.table import Table

from telerig.bus.topics import Topic
from telerig.cameras.encoder import VideoEncoder
from telerig.ir import wire
from telerig.ir.mcap_log import McapLog, iter_raw
from telerig.ir.types import JointState, Stamp, now_ns
from telerig.store.episodes import EpisodeStore

W, H, FPS = 640, 480, 30.0
RIG = "bench"
TARGET_COMMIT_S = 0.2
#: CPU of the recording itself: the process's CPU less that of the same sources when nothing records.
TARGET_RECORDER_CORES = 0.5
TARGET_ALIGN_P99_MS = 1.0
JOINTS = tuple(f"joint{i}" for i in range(7))
STREAM_RATES_HZ = (100.0, 125.0, 150.0, 175.0, 200.0)


def synthetic_frames(n: int, seed: int = 0) -> list[np.ndarray]:
    """``n`` RGB uint8 frames (H, W, 3): drifting gradients, two moving squares, sensor noise (sigma 3)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:H, 0:W].astype(np.float32)
    frames = []
    for i in range(n):
        phase = 2 * np.pi * i / n
        r = 128 + 90 * np.sin(x / 80 + phase)
        g = 128 + 90 * np.sin(y / 60 - phase)
        b = 128 + 60 * np.sin((x + y) / 120 + 2 * phase)
        image = np.stack([r, g, b], axis=-1)
        for k, (size, speed) in enumerate(((90, 7), (60, -11))):
            cx = int((W / 2 + speed * i) % (W - size))
            cy = int((H / 3 + 50 * k + 40 * np.sin(phase)) % (H - size))
            image[cy : cy + size, cx : cx + size] = (230, 40 + 150 * k, 60)
        image += rng.normal(0, 3, image.shape).astype(np.float32)
        frames.append(np.clip(image, 0, 255).astype(np.uint8))
    return frames


@dataclass
class SourceLog:
    """What one source thread did: true capture times and stamps [ns, common clock]."""

    name: str
    rate_hz: float
    truth_ns: list[int] = field(default_factory=list)
    stamp_ns: list[int] = field(default_factory=list)  # wake-up time of the source thread
    refused: int = 0  # encoder queue full (cameras)
    missed: int = 0  # deadlines passed without a sample (the source thread overran)


class Clock:
    """Maps monotonic deadlines to the common clock with one offset read at start."""

    def __init__(self) -> None:
        m0 = time.monotonic_ns()
        wall = now_ns()
        m1 = time.monotonic_ns()
        self.offset_ns = wall - (m0 + m1) // 2


def run_source(
    log: SourceLog, clock: Clock, start_mono: int, end_mono: int, phase_ns: int, emit: Any
) -> None:
    """Wake at ``start + phase + k * period`` until ``end`` and ``emit(k, capture_ns)`` each tick.

    The sample is stamped with its true capture time (the deadline), as a device that stamps at
    capture (kernel buffer time, device clock) would; the wake-up time is kept beside it, to show
    what stamping on arrival in Python would have cost.
    """
    period = round(1e9 / log.rate_hz)
    deadline = start_mono + phase_ns
    k = 0
    while deadline < end_mono:
        wait = deadline - time.monotonic_ns()
        if wait > 0:
            time.sleep(wait / 1e9)
        wake_ns = now_ns()
        late = time.monotonic_ns() - deadline
        if late >= period:  # skip ticks we cannot catch up with, as a driver would
            missed = late // period
            log.missed += missed
            deadline += missed * period
            k += missed
        capture_ns = deadline + clock.offset_ns
        log.truth_ns.append(capture_ns)
        log.stamp_ns.append(wake_ns)
        if emit(k, capture_ns) is False:
            log.refused += 1
        deadline += period
        k += 1


def _percentiles(values: np.ndarray) -> dict[str, float]:
    if values.size == 0:
        return {"p50": 0.0, "p99": 0.0, "max": 0.0}
    return {
        "p50": float(np.percentile(values, 50)),
        "p99": float(np.percentile(values, 99)),
        "max": float(values.max()),
    }


def alignment_errors_ms(
    cameras: list[tuple[np.ndarray, np.ndarray]], streams: list[tuple[np.ndarray, np.ndarray]]
) -> np.ndarray:
    """Alignment error [ms] of each camera frame against the nearest sample of each stream.

    Each source is ``(recorded times, true capture times)`` [ns]; the error of a pair is
    |(recorded frame - recorded sample) - (true frame - true sample)|, the sample being the one
    nearest the frame in recorded time.
    """

    def error(recorded: np.ndarray, truth: np.ndarray) -> np.ndarray:
        # Each recorded time against the nearest true capture time (robust to lost samples).
        idx = np.clip(np.searchsorted(truth, recorded), 1, truth.size - 1)
        nearest = np.where(recorded - truth[idx - 1] <= truth[idx] - recorded, truth[idx - 1], truth[idx])
        return recorded - nearest

    errors = []
    for c_rec, c_truth in cameras:
        if c_rec.size < 2:
            continue
        c_err = error(c_rec, c_truth)
        for s_rec, s_truth in streams:
            if s_rec.size < 2:
                continue
            s_err = error(s_rec, s_truth)
            idx = np.clip(np.searchsorted(s_rec, c_rec), 1, s_rec.size - 1)
            nearest = np.where(c_rec - s_rec[idx - 1] <= s_rec[idx] - c_rec, idx - 1, idx)
            errors.append(np.abs(c_err - s_err[nearest]))
    return np.concatenate(errors) / 1e6 if errors else np.zeros(0)


def mp4_times_ns(path: Path, first_ns: int) -> np.ndarray:
    """Capture times [ns] of an MP4's frames as recorded: pts (µs) from the file + the first frame's time."""
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        pts = sorted(int(p.pts) for p in container.demux(stream) if p.pts is not None)
        scale = float(stream.time_base) * 1e9
    return first_ns + np.round(np.array(pts, dtype=np.float64) * scale).astype(np.int64)


def run_sources(sources: list[tuple[SourceLog, Any]], clock: Clock, duration_s: float) -> tuple[float, float]:
    """Run each ``(log, emit)`` on its own thread for ``duration_s``; the process's CPU and wall time [s]."""
    # The first encode imports and builds protobuf classes: not part of the run.
    wire.encode(JointState(Stamp("warmup", 0, 0, 0), JOINTS, np.zeros(7), np.zeros(7)))
    rng = np.random.default_rng(42)
    start_mono = time.monotonic_ns() + 200_000_000
    end_mono = start_mono + round(duration_s * 1e9)
    threads = [
        threading.Thread(
            target=run_source,
            args=(log, clock, start_mono, end_mono, int(rng.integers(0, 1e9 / log.rate_hz)), emit),
            daemon=True,
        )
        for log, emit in sources
    ]
    for t in threads:
        t.start()
    time.sleep(max(0.0, (start_mono - time.monotonic_ns()) / 1e9))
    cpu0, wall0 = time.process_time(), time.perf_counter()
    for t in threads:
        t.join()
    return time.process_time() - cpu0, time.perf_counter() - wall0


def make_sample(j: int) -> Any:
    """Stream ``j``'s device side: ``sample(k, capture_ns)`` -> the encoded JointState of tick ``k``."""
    name = f"dev{j}"
    base = np.random.default_rng(j).normal(0, 1, len(JOINTS))

    def sample(k: int, capture_ns: int) -> bytes:
        q = base + 0.01 * k
        return wire.encode(JointState(Stamp(name, k, capture_ns, capture_ns), JOINTS, q, q * 0.1))

    return sample


def sources_alone_cores(*, cameras: int, streams: int, duration_s: float) -> float:
    """CPU [cores] of the same source threads when nothing records: each camera picks its frame, each
    stream builds and encodes its sample. The baseline the recorder's own CPU is measured against."""
    frames = synthetic_frames(2)
    samples = [make_sample(j) for j in range(streams)]

    def camera_emit(k: int, capture_ns: int) -> bool:
        return frames[k % len(frames)] is not None

    def stream_emit(j: int) -> Any:
        return lambda k, capture_ns: samples[j](k, capture_ns) is not None

    cpu_s, wall_s = run_sources(
        [(SourceLog(f"cam{i}", FPS), camera_emit) for i in range(cameras)]
        + [
            (SourceLog(f"stream{j}", STREAM_RATES_HZ[j % len(STREAM_RATES_HZ)]), stream_emit(j))
            for j in range(streams)
        ],
        Clock(),
        duration_s,
    )
    return cpu_s / wall_s


def measure(
    *, cameras: int, streams: int, duration_s: float, broker: bool, codec: str, root: Path
) -> dict[str, Any]:
    """One recorded episode under load; returns the measurements."""
    store = EpisodeStore(root)
    draft = store.begin(rig=RIG, task="recording benchmark", operator="bench")
    frames = synthetic_frames(60)
    clock = Clock()
    encoders = [
        VideoEncoder(draft.camera_path(f"cam{i}"), width=W, height=H, fps=FPS, codec=codec)  # type: ignore[arg-type]
        for i in range(cameras)
    ]
    for enc in encoders:
        enc.start()
    cam_logs = [SourceLog(f"cam{i}", FPS) for i in range(cameras)]
    stream_logs = [SourceLog(f"stream{j}", STREAM_RATES_HZ[j % len(STREAM_RATES_HZ)]) for j in range(streams)]
    topics = [str(Topic(RIG, f"dev{j}", "joint_state")) for j in range(streams)]

    mcap: McapLog | None = None
    recorder: Any = None
    pub_bus: Any = None
    rec_bus: Any = None
    if broker:
        from telerig.bus.mqtt import MqttBus, connect_bus
        from telerig.record.recorder import Recorder

        rec_bus = connect_bus(None, client_id="recorder")
        pub_bus = MqttBus(rec_bus.broker.url, client_id="streams").connect()
        expected = {t: log.rate_hz for t, log in zip(topics, stream_logs, strict=True)}
        recorder = Recorder(RIG, rec_bus, expected)
        recorder.start(draft.mcap_path)
    else:
        mcap = McapLog(draft.mcap_path)

    def camera_emit(i: int) -> Any:
        enc, offset = encoders[i], 7 * i

        def emit(k: int, capture_ns: int) -> bool:
            return enc.submit(frames[(k + offset) % len(frames)], capture_ns)

        return emit

    def stream_emit(j: int) -> Any:
        topic, sample = topics[j], make_sample(j)

        def emit(k: int, capture_ns: int) -> None:
            payload = sample(k, capture_ns)
            if mcap is not None:
                mcap.write(topic, payload, log_time_ns=now_ns(), publish_time_ns=capture_ns)
            else:
                pub_bus.publish(topic, payload)

        return emit

    cpu_run, wall_run = run_sources(
        [(cam_logs[i], camera_emit(i)) for i in range(cameras)]
        + [(stream_logs[j], stream_emit(j)) for j in range(streams)],
        clock,
        duration_s,
    )
    cpu0, wall0 = time.process_time(), time.perf_counter()  # the encoders' drain and the MCAP's close

    t0 = time.perf_counter()
    results = [enc.finish() for enc in encoders]
    encoder_drain_s = time.perf_counter() - t0
    if broker:
        time.sleep(0.5)  # let the last QoS 0 messages arrive
        recorder.stop()
        recorder.close()
        pub_bus.close()
        rec_bus.close()
    else:
        assert mcap is not None
        mcap.close()
    cpu_total = cpu_run + time.process_time() - cpu0
    wall_total = wall_run + time.perf_counter() - wall0

    files = [p for p in draft.dir.rglob("*") if p.is_file()]
    total_bytes = sum(p.stat().st_size for p in files)
    video_bytes = sum(p.stat().st_size for p in files if p.suffix == ".mp4")
    t0 = time.perf_counter()
    manifest = draft.commit({"benchmark": "recording"})
    commit_s = time.perf_counter() - t0
    # What hashing alone costs (files in the page cache, as at commit): the part that grows with size.
    t0 = time.perf_counter()
    for entry in manifest.files:
        with open(draft.dir / entry.path, "rb") as f:
            hashlib.file_digest(f, "sha256")
    hash_s = time.perf_counter() - t0

    # Read back what was recorded: frame times from the MP4 pts, sample times from the MCAP.
    def arr(values: list[int]) -> np.ndarray:
        return np.array(values, dtype=np.int64)

    recorded: dict[str, list[int]] = {t: [] for t in topics}
    for topic, _, _, publish_ns in iter_raw(draft.dir / "episode.mcap"):
        if topic in recorded:
            recorded[topic].append(publish_ns)
    lost = sum(len(log.truth_ns) - len(recorded[t]) for t, log in zip(topics, stream_logs, strict=True))
    cam_recorded = [
        (mp4_times_ns(draft.dir / "cameras" / r.path.name, r.timestamps_ns[0]), arr(log.truth_ns))
        for r, log in zip(results, cam_logs, strict=True)
        if r.frames
    ]
    st_recorded = [
        (np.sort(arr(recorded[t])), arr(log.truth_ns)) for t, log in zip(topics, stream_logs, strict=True)
    ]
    align = alignment_errors_ms(cam_recorded, st_recorded)
    wake_align = alignment_errors_ms(
        [(arr(c.stamp_ns), arr(c.truth_ns)) for c in cam_logs],
        [(arr(s.stamp_ns), arr(s.truth_ns)) for s in stream_logs],
    )
    wake_late = np.concatenate([arr(x.stamp_ns) - arr(x.truth_ns) for x in cam_logs + stream_logs]) / 1e6
    per_camera = [
        {
            "name": log.name,
            "frames": r.frames,
            "encoder_drops": r.dropped,
            "missed_deadlines": log.missed,
            "MB": (draft.dir / "cameras" / r.path.name).stat().st_size / 1e6 if r.frames else 0.0,
        }
        for log, r in zip(cam_logs, results, strict=True)
    ]
    per_stream = [
        {
            "name": log.name,
            "rate_hz": log.rate_hz,
            "samples": len(log.stamp_ns),
            "missed_deadlines": log.missed,
        }
        for log in stream_logs
    ]
    return {
        "config": f"{cameras} cameras {W}x{H}@{FPS:g} {codec} + {streams} streams 100-200 Hz "
        + ("via Mosquitto + Recorder" if broker else "direct to McapLog"),
        "cameras": cameras,
        "streams": streams,
        "broker": broker,
        "duration_s": wall_run,
        "frames": sum(r.frames for r in results),
        "samples": sum(len(s.stamp_ns) for s in stream_logs),
        "encoder_drops": sum(c["encoder_drops"] for c in per_camera),
        "camera_missed_deadlines": sum(c["missed_deadlines"] for c in per_camera),
        "stream_missed_deadlines": sum(s["missed_deadlines"] for s in per_stream),
        "recorder_drops": sum(c["encoder_drops"] for c in per_camera) + lost,
        "samples_lost": lost,
        "cpu_cores_run": cpu_run / wall_run,
        "cpu_cores_with_finish": cpu_total / wall_total,
        "encoder_drain_s": encoder_drain_s,
        "MB_written": total_bytes / 1e6,
        "MBps": total_bytes / 1e6 / wall_run,
        "video_MBps": video_bytes / 1e6 / wall_run,
        "mcap_MB": (total_bytes - video_bytes) / 1e6,
        "commit_s": commit_s,
        "hash_s": hash_s,
        "hash_MBps": total_bytes / 1e6 / hash_s if hash_s > 0 else 0.0,
        "files": len(manifest.files),
        "alignment_ms": _percentiles(align),
        "alignment_if_stamped_on_wakeup_ms": _percentiles(wake_align),
        "source_wakeup_lateness_ms": _percentiles(wake_late),
        "per_camera": per_camera,
        "per_stream": per_stream,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cameras", type=int, nargs="+", default=[1, 6], help="camera counts to run")
    parser.add_argument("--streams", type=int, default=10, help="100-200 Hz streams")
    parser.add_argument("--duration", type=float, default=20.0, help="seconds per configuration")
    parser.add_argument("--codec", default="h264", choices=["h264", "av1"])
    parser.add_argument("--broker", action="store_true", help="also run streams through Mosquitto + Recorder")
    parser.add_argument("--switch-interval", type=float, default=0.001, help="GIL switch interval [s]")
    parser.add_argument(
        "--root",
        type=Path,
        default=None,
        help="folder for the episode stores, created if missing (default: /tmp)",
    )
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/recording.json"))
    args = parser.parse_args()
    console = Console(width=140)
    sys.setswitchinterval(args.switch_interval)  # as telerig run does (runtime.process_settings)
    runs = [(n, False) for n in args.cameras] + ([(max(args.cameras), True)] if args.broker else [])
    rows = []
    if args.root is not None:
        args.root.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=args.root) as tmp:
        for n, via_broker in runs:
            console.print(
                f"recording {n} cameras + {args.streams} streams for {args.duration:g} s"
                + (" through Mosquitto" if via_broker else "")
                + " ..."
            )
            row = measure(
                cameras=n,
                streams=args.streams,
                duration_s=args.duration,
                broker=via_broker,
                codec=args.codec,
                root=Path(tmp) / f"store-{n}-{int(via_broker)}",
            )
            row["sources_alone_cores"] = sources_alone_cores(
                cameras=n, streams=args.streams, duration_s=min(args.duration, 10.0)
            )
            row["recorder_cores"] = row["cpu_cores_run"] - row["sources_alone_cores"]
            rows.append(row)
    table = Table(title=f"recording load, {args.duration:g} s per row ({os.cpu_count()} cores, {args.codec})")
    columns = (
        "config", "frames", "samples", "recorder drops", "source misses", "CPU cores (recorder)", "MB/s",
        "commit s", "hash s", "align p99/max ms", "wake-stamped p99 ms",
    )  # fmt: skip
    for col in columns:
        table.add_column(col, justify="left" if col == "config" else "right")
    for r in rows:
        a, w = r["alignment_ms"], r["alignment_if_stamped_on_wakeup_ms"]
        table.add_row(
            f"{r['cameras']} cam + {r['streams']} streams" + (" via broker" if r["broker"] else ""),
            str(r["frames"]),
            str(r["samples"]),
            str(r["recorder_drops"]),
            f"{r['camera_missed_deadlines']}+{r['stream_missed_deadlines']}",
            f"{r['cpu_cores_run']:.2f} ({r['recorder_cores']:.2f})",
            f"{r['MBps']:.2f}",
            f"{r['commit_s']:.3f}",
            f"{r['hash_s']:.3f}",
            f"{a['p99']:.4f}/{a['max']:.4f}",
            f"{w['p99']:.2f}",
        )
    console.print(table)
    target = next((r for r in rows if r["cameras"] == 6 and r["streams"] == 10 and not r["broker"]), None)
    if target is not None:
        drops, commit, p99 = target["recorder_drops"], target["commit_s"], target["alignment_ms"]["p99"]
        cores = target["recorder_cores"]
        console.print(
            f"6 cameras + 10 streams: recorder drops {drops} "
            f"(target 0: {'met' if drops == 0 else 'MISSED'}); "
            f"recorder CPU {cores:.2f} cores (target <= {TARGET_RECORDER_CORES}: "
            f"{'met' if cores <= TARGET_RECORDER_CORES else 'MISSED'}); "
            f"commit {commit:.3f} s (target <= {TARGET_COMMIT_S} s: "
            f"{'met' if commit <= TARGET_COMMIT_S else 'MISSED'}); alignment p99 {p99:.4f} ms (target <= "
            f"{TARGET_ALIGN_P99_MS} ms: {'met' if p99 <= TARGET_ALIGN_P99_MS else 'MISSED'})"
        )
        if target["hash_MBps"] > 0:
            size = target["MBps"] * 300
            console.print(
                f"hashing runs at {target['hash_MBps']:.0f} MB/s: a 5-minute episode ({size:.0f} MB) "
                f"would spend ~{size / target['hash_MBps']:.2f} s hashing at commit"
            )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(
        json.dumps(
            {
                "benchmark": "recording",
                "machine": {
                    "cpus": os.cpu_count(),
                    "python": platform.python_version(),
                    "av": av.__version__,
                },
                "duration_s": args.duration,
                "switch_interval_s": args.switch_interval,
                "targets": {
                    "recorder_drops": 0,
                    "recorder_cores": TARGET_RECORDER_CORES,
                    "commit_s": TARGET_COMMIT_S,
                    "alignment_p99_ms": TARGET_ALIGN_P99_MS,
                },
                "results": rows,
            },
            indent=2,
        )
    )
    console.print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
