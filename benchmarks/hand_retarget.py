"""Benchmark: telerig hand vector retargeting vs dex-retargeting's VectorOptimizer on one input; table + JSON.

Input: 20 s at 100 Hz of human hand motion (open/close, pinches of the thumb with each finger,
power grasp, finger waves, pointing) from the glove's parametric hand model
(:class:`telerig.devices.glove.kinematics.HandModel`) as 21 MediaPipe keypoints, with 1.5 mm of
seeded Gaussian tracking noise. Vectors: wrist to each fingertip the robot has (dex-retargeting's
``vector`` configs), expressed in the hand frame by :func:`telerig.retarget.hand.human_vectors`;
both solvers get the very same target vectors and the same scale.

Same model for both: dex-retargeting reads URDF, so it gets :func:`kinematic_urdf` of telerig's
kinematic model (mesh-free, re-rooted in the hand frame, mimic joints as ``<mimic>``, actuated
joint limits as telerig's). Both solve over the same actuated joints in the same box.
dex-retargeting runs with its defaults (Huber delta 0.02, norm_delta 4e-3, NLopt SLSQP, warm start
from the last solution) and its low-pass filter off; telerig's ``beta`` is set to the same
smoothing weight in the quadratic regime (``beta = norm_delta * m * 2 * huber_delta``).
The keypoint error of a frame is the mean over vectors of ``|| alpha v_i - f_i(q) ||``, computed
with telerig's forward kinematics for both solutions.

dex-retargeting (a benchmark-only dependency) lives in its own venv and runs in a subprocess::

    python3.11 -m venv .venv-bench
    .venv-bench/bin/pip install dex-retargeting==0.5.0 torch==2.13.0+cpu six==1.17.0

Without that venv only telerig's half runs.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

_FRAMES_HZ = 100.0
_NOISE_M = 0.0015


# -- dex-retargeting half: runs in .venv-bench, imports no telerig -------------------------------


def _dex_worker(job: Path) -> int:
    from dex_retargeting.retargeting_config import RetargetingConfig  # type: ignore[import-not-found]

    data = np.load(job)
    actuated = [str(s) for s in data["actuated"]]
    tips = [str(s) for s in data["task_links"]]
    cfg = RetargetingConfig.from_dict(
        {
            "type": "vector",
            "urdf_path": str(data["urdf_path"]),
            "target_joint_names": actuated,
            "target_origin_link_names": ["kp0"] * len(tips),
            "target_task_link_names": tips,
            "target_link_human_indices": np.array([[0] * len(tips), list(range(len(tips)))]),
            "scaling_factor": float(data["scale"]),
            "low_pass_alpha": -1.0,
        }
    )
    retargeting = cfg.build()
    names = list(retargeting.optimizer.robot.dof_joint_names)
    cols = [names.index(n) for n in actuated]
    vectors = data["vectors"]
    q0 = data["q0"]
    full0 = np.zeros(len(names))
    full0[cols] = q0
    retargeting.set_qpos(full0)
    qs = np.empty((len(vectors), len(actuated)))
    times = np.empty(len(vectors))
    for k, v in enumerate(vectors):
        t0 = time.perf_counter()
        q = retargeting.retarget(v)
        times[k] = time.perf_counter() - t0
        qs[k] = q[cols]
    np.savez(job.with_suffix(".out.npz"), q=qs, times=times)
    return 0


# -- telerig half ----------------------------------------------------------------------------------


def _min_jerk(u: float) -> float:
    u = min(1.0, max(0.0, u))
    return u * u * u * (10.0 + u * (-15.0 + 6.0 * u))


def human_sequence(seconds: float, rate_hz: float = _FRAMES_HZ, seed: int = 0) -> list[Any]:
    """Realistic right-hand motion as HandPose samples (21 keypoints [m], hand frame of the glove)."""
    from telerig.devices.glove.kinematics import HandModel
    from telerig.ir.types import HandPose, Stamp

    ext = (0.0, 0.05, 0.05, 0.05)
    curled = (0.0, 1.5, 1.7, 0.9)
    relaxed = (0.0, 0.25, 0.25, 0.1)
    half = (0.0, 0.8, 0.9, 0.5)
    thumb_open = (0.25, 0.0, 0.1, 0.1)
    open_ = (thumb_open, (0.08, *ext[1:]), ext, (-0.05, *ext[1:]), (-0.12, *ext[1:]))
    keys: list[tuple[str, tuple[tuple[float, ...], ...]]] = [
        ("open", open_),
        ("power grasp", ((-0.2, 0.6, 0.7, 0.5), curled, curled, curled, curled)),
        ("open", open_),
        ("pinch index", ((0.1, 0.7, 0.2, 0.2), (0.0, 0.6, 0.7, 0.4), relaxed, relaxed, relaxed)),
        ("pinch middle", ((-0.05, 0.8, 0.3, 0.2), relaxed, (0.0, 0.7, 0.75, 0.4), relaxed, relaxed)),
        ("pinch ring", ((-0.2, 0.9, 0.35, 0.25), relaxed, relaxed, (0.0, 0.8, 0.8, 0.4), relaxed)),
        ("pinch little", ((-0.35, 1.0, 0.4, 0.3), relaxed, relaxed, relaxed, (0.0, 0.9, 0.85, 0.45))),
        ("open", open_),
        ("point", ((-0.2, 0.5, 0.6, 0.4), ext, curled, curled, curled)),
        ("half close", ((0.0, 0.4, 0.3, 0.2), half, half, half, half)),
    ]
    model = HandModel.default()
    rng = np.random.default_rng(seed)
    n = int(seconds * rate_hz)
    dwell, blend, wave_s = 0.5, 0.6, 3.0
    step = dwell + blend
    cycle = len(keys) * step + wave_s
    samples = []
    for k in range(n):
        t = k / rate_hz
        tc = t % cycle
        if tc < len(keys) * step:
            i, r = divmod(tc, step)
            a = np.array(keys[int(i)][1])
            b = np.array(keys[(int(i) + 1) % len(keys)][1])
            angles = a + _min_jerk((r - dwell) / blend) * (b - a)
        else:  # finger wave: each finger flexes in turn, little to index
            ph = (tc - len(keys) * step) / wave_s
            angles = np.array(open_, dtype=np.float64)
            for f in range(1, 5):
                s = 0.5 - 0.5 * math.cos(2.0 * math.pi * (2.0 * ph - (4 - f) * 0.15))
                angles[f, 1:] = np.array(ext[1:]) + s * (np.array(curled[1:]) - np.array(ext[1:]))
        kp = model.keypoints(angles, "right") + rng.normal(0.0, _NOISE_M, (21, 3))
        samples.append(
            HandPose(
                stamp=Stamp("bench", k, int(t * 1e9), int(t * 1e9)),
                handedness="right",
                wrist_position=kp[0],
                wrist_orientation=np.array([1.0, 0.0, 0.0, 0.0]),
                keypoints=kp,
                keypoint_confidence=np.ones(21),
                frame_id="right_glove",
            )
        )
    return samples


def _stats(times: np.ndarray, errors: np.ndarray) -> dict[str, float]:
    return {
        "p50_ms": float(np.median(times) * 1e3),
        "p99_ms": float(np.percentile(times, 99) * 1e3),
        "mean_error_mm": float(errors.mean() * 1e3),
        "p99_error_mm": float(np.percentile(errors, 99) * 1e3),
    }


def bench_hand(name: str, seconds: float, bench_python: Path | None) -> dict[str, Any]:
    from telerig.retarget.hand import HandRetargeter, KeypointVectors, human_vectors
    from telerig.robots.models.hands import kinematic_urdf, load_hand

    hand = load_hand(name, "right")  # type: ignore[arg-type]
    tips = [i for i in (4, 8, 12, 16, 20) if i in hand.keypoints]
    vectors = KeypointVectors.of([(0, t) for t in tips])
    huber_delta, norm_delta = 0.02, 4e-3  # dex-retargeting's defaults
    beta = norm_delta * len(tips) * 2.0 * huber_delta
    retargeter = HandRetargeter(hand, vectors, beta=beta)
    samples = human_sequence(seconds)
    targets = []
    for s in samples:
        found = human_vectors(s, vectors)
        assert found is not None
        targets.append(found[0])
    v = np.array(targets)
    alpha = hand.default_scale
    n = len(samples)
    times = np.empty(n)
    q_ours = np.empty((n, len(hand.actuated)))
    for k, s in enumerate(samples):
        t0 = time.perf_counter()
        result = retargeter(s)
        times[k] = time.perf_counter() - t0
        assert result is not None
        q_ours[k] = result.command.positions
    fk = retargeter.optimizer

    def errors(qs: np.ndarray) -> np.ndarray:
        return np.array([np.linalg.norm(alpha * v[k] - fk.forward(qs[k]), axis=1).mean() for k in range(n)])

    row: dict[str, Any] = {
        "hand": hand.name,
        "actuated_joints": len(hand.actuated),
        "vectors": len(vectors),
        "scale": alpha,
        "beta": beta,
        "frames": n,
        "telerig": _stats(times, errors(q_ours)),
    }
    # The solve alone (without vector extraction), like the dex half is timed.
    solve_times = np.empty(n)
    retargeter.reset()
    q = hand.neutral()
    w = np.ones(len(vectors))
    for k in range(n):
        t0 = time.perf_counter()
        q = fk.solve(alpha * v[k], w, q).q
        solve_times[k] = time.perf_counter() - t0
    row["telerig_solve_only"] = {
        "p50_ms": float(np.median(solve_times) * 1e3),
        "p99_ms": float(np.percentile(solve_times, 99) * 1e3),
    }
    if bench_python is None:
        return row
    with tempfile.TemporaryDirectory(prefix="telerig-hand-bench-") as tmp:
        urdf = Path(tmp) / f"{hand.name}.urdf"
        urdf.write_text(kinematic_urdf(hand))
        job = Path(tmp) / "job.npz"
        np.savez(
            job,
            urdf_path=str(urdf),
            actuated=np.array(hand.actuated),
            task_links=np.array([f"kp{t}" for t in tips]),
            scale=alpha,
            vectors=v,
            q0=hand.neutral(),
        )
        env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
        proc = subprocess.run(
            [str(bench_python), __file__, "--dex-worker", str(job)],
            check=False,
            capture_output=True,
            text=True,
            env=env,
        )
        if proc.returncode != 0:
            row["dex_retargeting"] = {
                "error": proc.stderr.strip().splitlines()[-1] if proc.stderr else "failed"
            }
            return row
        out = np.load(job.with_suffix(".out.npz"))
        q_dex = np.clip(out["q"], hand.lower, hand.upper)  # SLSQP may overshoot the box by its 1e-3 epsilon
        row["dex_retargeting"] = _stats(out["times"], errors(q_dex))
        row["dex_retargeting"]["max_bound_violation_rad"] = float(
            np.max(np.maximum(hand.lower - out["q"], out["q"] - hand.upper).clip(min=0.0))
        )
    return row


def main() -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--hands", nargs="+", default=["inspire", "ability", "allegro"])
    parser.add_argument("--bench-python", type=Path, default=Path(".venv-bench/bin/python"))
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/hand_retarget.json"))
    parser.add_argument("--dex-worker", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.dex_worker is not None:
        return _dex_worker(args.dex_worker)

    from rich.console import Console
    from rich.table import Table

    console = Console(width=140)
    bench_python: Path | None = args.bench_python
    if bench_python is None or not bench_python.is_file():
        console.print(
            f"[yellow]{args.bench_python} not found: running telerig only. Install dex-retargeting with: "
            "python3.11 -m venv .venv-bench && .venv-bench/bin/pip install dex-retargeting==0.5.0 "
            "torch==2.13.0+cpu six==1.17.0[/yellow]"
        )
        bench_python = None
    rows = [bench_hand(h, args.seconds, bench_python) for h in args.hands]
    table = Table(
        title=f"Hand retargeting per frame, {args.seconds:g} s of motion at {_FRAMES_HZ:g} Hz (one core)"
    )
    for col in ("hand", "solver", "p50 ms", "p99 ms", "mean vector error mm", "p99 error mm"):
        table.add_column(col, justify="right")
    for r in rows:
        for solver in ("telerig", "dex_retargeting"):
            s = r.get(solver)
            if s is None:
                continue
            if "error" in s:
                table.add_row(r["hand"], solver, "-", "-", s["error"], "-")
                continue
            table.add_row(
                r["hand"],
                solver,
                f"{s['p50_ms']:.3f}",
                f"{s['p99_ms']:.3f}",
                f"{s['mean_error_mm']:.2f}",
                f"{s['p99_error_mm']:.2f}",
            )
    console.print(table)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(
        json.dumps({"benchmark": "hand_retarget", "python": sys.version.split()[0], "rows": rows}, indent=2)
    )
    console.print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
