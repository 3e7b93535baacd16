"""What a simulated camera frame costs with the robots' full and simplified visual meshes.

The robot models' visual meshes are CAD exports (the UR5e's: 137 557 faces); on a host without a
GPU (MuJoCo through OSMesa/llvmpipe) drawing them is most of a camera frame. ``compile_spec``
simplifies the visual-only meshes to ``VISUAL_MESH_FACES`` faces each (quadric error, physics
untouched). For each scene, in the same run:

- build [s]: the scene builder with every face (baseline), simplified with empty caches (the first
  build on a machine: one extra compile and the simplification), with the meshes on disk only (the
  first build in a new process: a robot process, the next ``telerig run``), and again in this
  process (cache full); the disk cache is a temporary directory of this run;
- faces drawn: mesh faces in the camera's geom groups (``VISUAL_GROUPS``);
- CPU-ms per frame (``time.process_time``, this process, ``update_scene`` + ``render``) at 640x480
  and 160x120, ``--frames`` frames after 3 warm-up frames, from the scene's ``scene`` camera;
- ratio = full / simplified; the two 640x480 images side by side in ``--out`` for the eye.

Run with MUJOCO_GL=osmesa on a host without a GPU (egl where there is one).

Usage: MUJOCO_GL=osmesa python benchmarks/render_cost.py [--frames 20] [--faces 2000]
       [--scenes arm,panda,tiago,g1]
       [--out benchmarks/results/render_cost]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

os.environ.setdefault("MUJOCO_GL", "osmesa")
os.environ["TELERIG_CACHE_DIR"] = tempfile.mkdtemp(prefix="render-cost-")  # not the user's cache

import mujoco
import numpy as np
from PIL import Image
from rich.console import Console
from rich.table import Table

from telerig.robots.models import visual_meshes
from telerig.robots.models.mjcf import VISUAL_GROUPS
from telerig.robots.models.visual_meshes import VISUAL_MESH_FACES, visual_mesh_budget
from telerig.robots.sim.humanoid import build_humanoid_scene
from telerig.robots.sim.scene import build_arm_scene
from telerig.robots.sim.tiago import build_tiago_scene

ROOT = Path(__file__).resolve().parents[1]
SIZES = ((640, 480), (160, 120))
SCENES: dict[str, Callable[[], mujoco.MjModel]] = {
    "arm": lambda: build_arm_scene("ur5e_robotiq85").model,
    "panda": lambda: build_arm_scene("panda").model,
    "tiago": lambda: build_tiago_scene().model,
    "g1": lambda: build_humanoid_scene().model,
}


def drawn_faces(model: mujoco.MjModel) -> int:
    """Mesh faces of the geoms a camera draws (groups in VISUAL_GROUPS)."""
    total = 0
    for g in range(model.ngeom):
        if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH and int(model.geom_group[g]) in VISUAL_GROUPS:
            total += int(model.mesh_facenum[model.geom_dataid[g]])
    return total


def render_cost(model: mujoco.MjModel, frames: int) -> tuple[dict[str, float], np.ndarray]:
    """CPU-ms per frame at each of SIZES, and the 640x480 image."""
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    option = mujoco.MjvOption()
    for group in range(len(option.geomgroup)):
        option.geomgroup[group] = int(group in VISUAL_GROUPS)
    camera: str | int = "scene" if mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, "scene") >= 0 else -1
    costs: dict[str, float] = {}
    image = np.zeros((1, 1, 3), np.uint8)
    for width, height in SIZES:
        with mujoco.Renderer(model, height, width) as renderer:
            for _ in range(3):
                renderer.update_scene(data, camera=camera, scene_option=option)
                renderer.render()
            start = time.process_time()
            for _ in range(frames):
                renderer.update_scene(data, camera=camera, scene_option=option)
                frame = renderer.render()
            costs[f"{width}x{height}"] = (time.process_time() - start) / frames * 1e3
            if width == SIZES[0][0]:
                image = frame.copy()
    return costs, image


def timed(build: Callable[[], mujoco.MjModel]) -> tuple[mujoco.MjModel, float]:
    start = time.perf_counter()
    model = build()
    return model, time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=20)
    parser.add_argument("--faces", type=int, default=VISUAL_MESH_FACES, help="faces per visual mesh")
    parser.add_argument("--scenes", default=",".join(SCENES))
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "render_cost")
    args = parser.parse_args()
    if args.frames < 1:
        parser.error("--frames must be >= 1")
    names = [n.strip() for n in args.scenes.split(",") if n.strip()]
    unknown = [n for n in names if n not in SCENES]
    if unknown:
        parser.error(f"unknown scene(s) {', '.join(unknown)}; choose from {', '.join(SCENES)}")
    args.out.mkdir(parents=True, exist_ok=True)
    console = Console()
    rows: list[dict[str, Any]] = []
    for name in names:
        console.print(f"[dim]{name}: building and rendering ...[/dim]")
        with visual_mesh_budget(0):
            SCENES[name]()  # the mesh files read once (OS cache, imports) before anything is timed
            full, build_full = timed(SCENES[name])
        with visual_mesh_budget(args.faces):
            visual_meshes.clear_cache(disk=True)  # the first simplified build on this machine
            _, build_cold = timed(SCENES[name])
            visual_meshes.clear_cache()  # the first in a new process: read from disk
            _, build_disk = timed(SCENES[name])
            simple, build_warm = timed(SCENES[name])
        cost_full, image_full = render_cost(full, args.frames)
        cost_simple, image_simple = render_cost(simple, args.frames)
        Image.fromarray(np.hstack([image_full, image_simple])).save(
            args.out / f"{name}_full_vs_simplified.png"
        )
        rows.append(
            {
                "scene": name,
                "faces_full": drawn_faces(full),
                "faces_simplified": drawn_faces(simple),
                "build_full_s": build_full,
                "build_simplified_cold_s": build_cold,
                "build_simplified_disk_s": build_disk,
                "build_simplified_warm_s": build_warm,
                "cpu_ms_full": cost_full,
                "cpu_ms_simplified": cost_simple,
                "ratio": {size: cost_full[size] / cost_simple[size] for size in cost_full},
            }
        )
    table = Table(
        title=f"Camera frame CPU cost, visual meshes <= {args.faces} faces each ({args.frames} frames)"
    )
    for column in ("scene", "faces full/simpl.", "build full/cold/disk/warm [s]"):
        table.add_column(column)
    for width, height in SIZES:
        table.add_column(f"{width}x{height} full/simpl. [CPU-ms]", justify="right")
        table.add_column("ratio", justify="right")
    for row in rows:
        cells = [
            row["scene"],
            f"{row['faces_full']} / {row['faces_simplified']}",
            " / ".join(
                f"{row[k]:.2f}"
                for k in (
                    "build_full_s",
                    "build_simplified_cold_s",
                    "build_simplified_disk_s",
                    "build_simplified_warm_s",
                )
            ),
        ]
        for width, height in SIZES:
            size = f"{width}x{height}"
            cells += [
                f"{row['cpu_ms_full'][size]:.1f} / {row['cpu_ms_simplified'][size]:.1f}",
                f"{row['ratio'][size]:.2f}",
            ]
        table.add_row(*cells)
    console.print(table)
    result = {
        "visual_mesh_faces": args.faces,
        "frames": args.frames,
        "mujoco_gl": os.environ.get("MUJOCO_GL"),
        "host": {"machine": platform.machine(), "cpus": os.cpu_count()},
        "scenes": rows,
    }
    path = args.out / "render_cost.json"
    path.write_text(json.dumps(result, indent=2))
    console.print(f"JSON: {path}; images: {args.out}/*_full_vs_simplified.png")


if __name__ == "__main__":
    main()
