"""Benchmark: the shipped mocap_humanoid rig live: IK tick inside the control loop, residuals, filter lag.

Runs ``src/telerig/config/rigs/mocap_humanoid.yaml`` (BVH body skeleton at 60 Hz → G1 upper body,
real-time physics at 500 Hz, embedded broker, recorder) through ``RigRuntime`` for one episode,
then reads the episode back: the per-tick IK solve time and wrist errors the control node
recorded on ``g1/residual``, and the input-to-actuation latency. Separately it measures the lag
the keypoint One-Euro filter adds to the right-wrist keypoint on the shipped clip: the time shift
that best aligns the filtered trajectory with the raw one. Timings on a shared 2-core machine
include scheduler noise; ``--camera`` keeps the rig's scene camera (rendered with OSMesa).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
from pathlib import Path
from typing import Any

os.environ.setdefault("MUJOCO_GL", "osmesa")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])

import numpy as np
from rich.console import Console
from rich.table import Table

from telerig.config import load_rig
from telerig.devices.mocap.fake import sample_bvh_path
from telerig.ir.mcap_log import read_residuals
from telerig.retarget.config import HumanoidBodyConfig, KeypointFilterConfig
from telerig.retarget.humanoid import KEYPOINTS, KeypointMap
from telerig.retarget.offline import load_skeletons
from telerig.runtime.process_settings import control_process
from telerig.runtime.rig import RigRuntime


def run_rig(duration_s: float, *, camera: bool) -> dict[str, Any]:
    rig = load_rig("mocap_humanoid")
    if not camera:
        rig = rig.model_copy(update={"cameras": []})
    with (
        tempfile.TemporaryDirectory() as root,
        control_process(),
        RigRuntime(rig, data_root=Path(root)) as runtime,
    ):
        result = runtime.run_episode(duration_s)
        residuals = [
            {"flagged": r.flagged, **r.metrics()}
            for topic, r, _ in read_residuals(result.path / "episode.mcap")
            if topic.endswith("/g1/residual")
        ]
        stats = runtime.controls["g1"].stats
    ik_ms = np.array([r["ik_time_s"] for r in residuals]) * 1e3
    wrist = np.array([[r["right_wrist_error_m"], r["left_wrist_error_m"]] for r in residuals]).max(axis=1)
    settled = wrist[len(wrist) // 3 :]
    return {
        "duration_s": duration_s,
        "camera": camera,
        "solves": len(residuals),
        "solve_rate_hz": len(residuals) / duration_s,
        "ik_p50_ms": float(np.median(ik_ms)),
        "ik_p99_ms": float(np.percentile(ik_ms, 99)),
        "ik_max_ms": float(ik_ms.max()),
        "flagged": int(sum(r["flagged"] for r in residuals)),
        "flagged_after_first_third": int(sum(r["flagged"] for r in residuals[len(residuals) // 3 :])),
        "wrist_error_median_mm": float(np.median(settled) * 1e3),
        "wrist_error_p95_mm": float(np.percentile(settled, 95) * 1e3),
        "latency_p50_ms": result.latency.p50_ms,
        "latency_p99_ms": result.latency.p99_ms,
        "safety_events": dict(stats.safety_events),
    }


def filter_lag(config: KeypointFilterConfig) -> dict[str, float]:
    """Lag [ms] of the filtered right-wrist keypoint behind the raw one on the shipped clip (3 passes)."""
    frames = load_skeletons(sample_bvh_path())
    keymap = KeypointMap("cmu")
    raw = np.array([keymap(f) for f in frames] * 3)  # (F, K, 3)
    rate = 60.0
    t = np.arange(len(raw)) / rate
    flt = config.build()
    out = np.array([flt(p, tk) for p, tk in zip(raw, t, strict=True)])
    wrist = KEYPOINTS.index("right_wrist")
    x, y = raw[len(frames) :, wrist], out[len(frames) :, wrist]  # after the first pass
    fine = np.arange(0.0, 0.1, 0.0005)  # candidate lags [s]
    tt = t[len(frames) :]
    err = [
        float(np.mean(np.sum((np.stack([np.interp(tt - s, tt, x[:, c]) for c in range(3)], 1) - y) ** 2, 1)))
        for s in fine
    ]
    speed = np.linalg.norm(np.diff(x, axis=0), axis=1) * rate
    return {
        "best_shift_ms": float(fine[int(np.argmin(err))] * 1e3),
        "max_error_mm": float(np.max(np.linalg.norm(y - x, axis=1)) * 1e3),
        "peak_wrist_speed_m_s": float(speed.max()),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=10.0, help="episode length [s]")
    parser.add_argument("--camera", action="store_true", help="keep the rig's scene camera")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/humanoid_rig.json"))
    args = parser.parse_args()
    console = Console(width=130)
    with console.status("running the mocap_humanoid rig"):
        live = run_rig(args.duration, camera=args.camera)
    rig_filter = HumanoidBodyConfig.model_validate(
        load_rig("mocap_humanoid").bindings[0].retargeter.model_dump()
    ).filter
    lag = filter_lag(rig_filter or KeypointFilterConfig())

    table = Table(title=f"mocap_humanoid rig, {args.duration:g} s, camera {'on' if args.camera else 'off'}")
    for col in ("metric", "value"):
        table.add_column(col, justify="left" if col == "metric" else "right")
    rows = [
        ("IK solves (one per skeleton)", f"{live['solves']} ({live['solve_rate_hz']:.1f} Hz)"),
        (
            "IK tick in the control loop p50 / p99 / max (ms)",
            f"{live['ik_p50_ms']:.2f} / {live['ik_p99_ms']:.2f} / {live['ik_max_ms']:.2f}",
        ),
        (
            "input-to-actuation latency p50 / p99 (ms)",
            f"{live['latency_p50_ms']:.2f} / {live['latency_p99_ms']:.2f}",
        ),
        (
            "flagged ticks (all / after the first third)",
            f"{live['flagged']} / {live['flagged_after_first_third']}",
        ),
        (
            "wrist error after the first third, median / p95 (mm)",
            f"{live['wrist_error_median_mm']:.1f} / {live['wrist_error_p95_mm']:.1f}",
        ),
        ("safety events", ", ".join(f"{k}: {v}" for k, v in live["safety_events"].items()) or "-"),
        ("keypoint filter lag on the right wrist (ms)", f"{lag['best_shift_ms']:.1f}"),
        (
            "keypoint filter max deviation (mm; peak wrist speed m/s)",
            f"{lag['max_error_mm']:.1f} ({lag['peak_wrist_speed_m_s']:.2f})",
        ),
    ]
    for name, value in rows:
        table.add_row(name, value)
    console.print(table)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"benchmark": "humanoid_rig", "live": live, "filter_lag": lag}, indent=2))
    console.print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
