"""Simplified visual meshes: the robots' CAD meshes cut to a face budget for the cameras, physics untouched.

The robot meshes are CAD exports: the UR5e's visual meshes have 137 557 faces, ~24 ms of llvmpipe
CPU per 640x480 camera frame, more than the rest of the scene; a software-rendered camera at 30 fps
then takes a core from the control loop. Cut to :data:`VISUAL_MESH_FACES` a mesh (quadric-error
edge collapse, ``fast-simplification``), they look the same at camera resolution and a frame costs
about half (benchmarks/render_cost.py: UR5e 34.3 -> 17.5 CPU-ms at 640x480, 28.3 -> 8.7 at 160x120,
and the images side by side). Only meshes that nothing but drawing uses are touched, so contacts,
masses and inertias stay bit-identical (tests/robots/sim/test_visual_meshes.py).
:func:`~telerig.robots.models.mjcf.compile_spec` applies it to every model it compiles.

The simplification is most of a scene's build (UR5e scene: ~1.5 of 2.1 s on the 2-core VM), and a
robot process, the gate process and every ``telerig run`` would pay it again: simplified meshes are
kept per process and on disk, in ``$TELERIG_CACHE_DIR/visual-meshes`` (else
``$XDG_CACHE_HOME/telerig/visual-meshes``, else ``~/.cache/telerig/visual-meshes``). An entry is
named by everything its content depends on (the mesh file's path, size and modification time, its
scale and frame, the budget, the MuJoCo and fast-simplification versions, the entry format); one
that does not read back as a valid mesh is simplified again, and a cache that cannot be written
only costs the time.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib.metadata
import logging
import math
import os
import tempfile
import threading
import zipfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path

import mujoco
import numpy as np
from numpy.typing import NDArray

from telerig.errors import DependencyError

__all__ = [
    "VISUAL_MESH_FACES",
    "budget",
    "cache_dir",
    "check_budget",
    "clear_cache",
    "compile_simplified",
    "drawn_only_geoms",
    "strip_drawn_only",
    "visual_mesh_budget",
]

_log = logging.getLogger(__name__)

#: Most faces a robot's visual-only mesh keeps when a model compiles (0: keep every face); 1 000 a
#: mesh looks the same at camera resolution. Physics never sees these meshes.
VISUAL_MESH_FACES = 1_000

_BUDGET: ContextVar[int] = ContextVar("visual_mesh_faces", default=VISUAL_MESH_FACES)


@contextmanager
def visual_mesh_budget(faces: int) -> Iterator[None]:
    """Models compiled inside keep at most ``faces`` faces per visual-only mesh (0: every face).

    For whoever builds models through the scene builders (which call ``mjcf.compile_spec``): a lab
    that wants full-detail camera images, the render-cost benchmark's baseline.

    Raises:
        ValueError: ``faces`` is negative or in (0, 4).
    """
    check_budget(faces)
    token = _BUDGET.set(faces)
    try:
        yield
    finally:
        _BUDGET.reset(token)


def check_budget(faces: int) -> int:
    """``faces`` if it is a valid budget: 0 (keep every face) or >= 4.

    Raises:
        ValueError: it is not.
    """
    if faces < 0 or 0 < faces < _MIN_FACES:
        raise ValueError(f"visual_mesh_faces must be 0 (keep every face) or >= {_MIN_FACES}, got {faces}")
    return faces


def clear_cache(*, disk: bool = False) -> None:
    """Forget the simplified meshes of this process; with ``disk``, the cached files too (the next
    build simplifies again: benchmarks)."""
    with _SIMPLIFIED_LOCK:
        _SIMPLIFIED.clear()
        if disk:
            for path in cache_dir().glob("*.npz"):
                with contextlib.suppress(OSError):
                    path.unlink()


def cache_dir() -> Path:
    """Where simplified meshes are kept between processes (see the module docstring)."""
    root = os.environ.get("TELERIG_CACHE_DIR")
    if root:
        return Path(root) / "visual-meshes"
    xdg = os.environ.get("XDG_CACHE_HOME", "")
    base = Path(xdg) if os.path.isabs(xdg) else Path.home() / ".cache"
    return base / "telerig" / "visual-meshes"


def budget() -> int:
    """The budget in force: the innermost :func:`visual_mesh_budget`, else :data:`VISUAL_MESH_FACES`."""
    return _BUDGET.get()


def compile_simplified(
    spec: mujoco.MjSpec,
    faces: int,
    *,
    groups: tuple[int, ...],
    compile: Callable[[mujoco.MjSpec], mujoco.MjModel],
) -> mujoco.MjModel:
    """Compile ``spec`` with the meshes its drawn-only geoms use simplified to ``faces`` faces.

    Only what drawn, non-colliding geoms that add nothing to a body's mass show is simplified (see
    :func:`drawn_only_geoms`); a mesh that a collision geom uses too (URDF models use one file for
    both) is split: the drawn geoms get a simplified copy (``<name>:visual``), the collision geom
    keeps the original. Contacts, masses and inertias are exactly those of the full model; the
    camera draws a fraction of the triangles. Simplified meshes are kept per process (keyed on the
    mesh file, its scale and the budget): the first build of a model pays one extra compile and
    the simplification, a later build of it one compile as before.

    Args:
        spec: The model, as built (not compiled before); simplified meshes become user meshes.
        faces: Most faces per drawn mesh, >= 4 (see :func:`check_budget`).
        groups: The geom groups a camera draws (``mjcf.VISUAL_GROUPS``).
        compile: Compiles a spec (``mjcf``'s, which words a failure as a RobotError).
    """
    drawn = drawn_only_geoms(spec, groups)
    users = _mesh_users(spec)
    pending: list[tuple[mujoco.MjsMesh, list[mujoco.MjsGeom], _Key | None]] = []
    for name, geoms in drawn.items():
        mesh = spec.mesh(name)
        key = _mesh_key(spec, mesh, faces)
        with _SIMPLIFIED_LOCK:
            cached = _SIMPLIFIED.get(key) if key is not None else None
        if cached is None and key is not None and (cached := _disk_get(key)) is not None:
            with _SIMPLIFIED_LOCK:
                _SIMPLIFIED[key] = cached
        if cached is None:
            pending.append((mesh, geoms, key))
        elif cached is not _UNCHANGED:
            _use_simplified(spec, mesh, geoms, len(users[name]) > len(geoms), cached)
    if not pending:
        return compile(spec)
    # The meshes are read from a compiled copy: a mesh compiled from its file keeps the file's
    # normals, which would not match new faces.
    full = spec.copy()
    model = compile(full)
    changed = False
    for mesh, geoms, key in pending:
        simplified = _simplify(model, full.mesh(mesh.name).id, faces)
        if key is not None:
            result = simplified if simplified is not None else _UNCHANGED
            with _SIMPLIFIED_LOCK:
                _SIMPLIFIED[key] = result
            _disk_put(key, result)
        if simplified is not None:
            _use_simplified(spec, mesh, geoms, len(users[mesh.name]) > len(geoms), simplified)
            changed = True
    return compile(spec) if changed else model


def drawn_only_geoms(spec: mujoco.MjSpec, groups: tuple[int, ...]) -> dict[str, list[mujoco.MjsGeom]]:
    """Mesh name -> the geoms using it that only draw it: what can be simplified, physics untouched.

    Such a geom is in ``groups`` (the groups a camera draws), has ``contype = conaffinity = 0``
    (no contacts), adds nothing to its body's mass or inertia (the body has an explicit
    ``<inertial>``, or the geom is outside the compiler's inertia group range or has zero
    mass/density) and has no textured material (simplification drops texture coordinates); its
    mesh is read from a file.
    """
    compiler = spec.compiler
    lo, hi = (int(g) for g in compiler.inertiagrouprange)
    from_geom = compiler.inertiafromgeom
    textured = {material.name for material in spec.materials if any(texture for texture in material.textures)}

    def drawn_only(geom: mujoco.MjsGeom) -> bool:
        if geom.group not in groups or geom.contype != 0 or geom.conaffinity != 0:
            return False
        if geom.material in textured:
            return False
        massless = geom.mass == 0 or (math.isnan(geom.mass) and geom.density == 0)
        explicit = bool(geom.parent.explicitinertial)
        adds_inertia = (
            lo <= geom.group <= hi
            and not massless
            and (
                from_geom == mujoco.mjtInertiaFromGeom.mjINERTIAFROMGEOM_TRUE
                or (from_geom == mujoco.mjtInertiaFromGeom.mjINERTIAFROMGEOM_AUTO and not explicit)
            )
        )
        return not adds_inertia

    files = {mesh.name for mesh in spec.meshes if mesh.file and mesh.name and not mesh.usertexcoord}
    drawn: dict[str, list[mujoco.MjsGeom]] = {}
    for name, geoms in _mesh_users(spec).items():
        if name in files:
            only = [geom for geom in geoms if drawn_only(geom)]
            if only:
                drawn[name] = only
    return drawn


def strip_drawn_only(spec: mujoco.MjSpec, groups: tuple[int, ...]) -> None:
    """Delete the geoms of ``spec`` that only draw (:func:`drawn_only_geoms`) and the meshes no other
    geom uses; physics and kinematics stay exactly as they were."""
    users = _mesh_users(spec)
    for name, geoms in drawn_only_geoms(spec, groups).items():
        for geom in geoms:
            spec.delete(geom)
        if len(geoms) == len(users[name]):
            spec.delete(spec.mesh(name))


def _mesh_users(spec: mujoco.MjSpec) -> dict[str, list[mujoco.MjsGeom]]:
    users: dict[str, list[mujoco.MjsGeom]] = {}
    for geom in spec.geoms:
        if geom.type == mujoco.mjtGeom.mjGEOM_MESH:
            users.setdefault(geom.meshname, []).append(geom)
    return users


def _use_simplified(
    spec: mujoco.MjSpec,
    mesh: mujoco.MjsMesh,
    geoms: list[mujoco.MjsGeom],
    shared: bool,
    simplified: tuple[_FloatArray, _IntArray],
) -> None:
    """Draw ``geoms`` with the simplified mesh: ``mesh`` itself, or a copy when others use it too."""
    if not shared:
        _set_user_mesh(mesh, *simplified)
        return
    name = f"{mesh.name}:visual"
    copy = spec.add_mesh(
        name=name,
        inertia=mesh.inertia,
        smoothnormal=mesh.smoothnormal,
        maxhullvert=mesh.maxhullvert,
        material=mesh.material,
    )
    _set_user_mesh(copy, *simplified)
    for geom in geoms:
        geom.meshname = name


_MIN_FACES = 4
_WELD_M = 1e-5
_AGGRESSIVENESS = 3.0
_FloatArray = NDArray[np.float64]
_IntArray = NDArray[np.int32]
_Key = tuple[str, tuple[float, ...], tuple[float, ...], tuple[float, ...], int, int]
#: Marks a cached mesh that was already within the budget.
_UNCHANGED: tuple[_FloatArray, _IntArray] = (np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int32))
_SIMPLIFIED: dict[_Key, tuple[_FloatArray, _IntArray]] = {}
_SIMPLIFIED_LOCK = threading.Lock()


def _mesh_key(spec: mujoco.MjSpec, mesh: mujoco.MjsMesh, faces: int) -> _Key | None:
    """Cache key of a mesh file read with this scale and reference frame; None: not cacheable.

    Only an absolute path (after the model's meshdir) names one file in every model; a relative
    one depends on the model's directory, so such a mesh is simplified at every build.
    """
    path = os.path.join(spec.meshdir, mesh.file) if spec.meshdir else mesh.file
    if not os.path.isabs(path):
        return None
    return (
        os.path.normpath(path),
        tuple(float(x) for x in mesh.scale),
        tuple(float(x) for x in mesh.refpos),
        tuple(float(x) for x in mesh.refquat),
        int(mesh.inertia),
        faces,
    )


#: Version of the cached files' layout and of what :func:`_simplify` does; a change renames every entry.
_CACHE_FORMAT = 1


def _disk_path(key: _Key) -> Path | None:
    try:
        stat = os.stat(key[0])
        simplifier = importlib.metadata.version("fast-simplification")
    except (OSError, importlib.metadata.PackageNotFoundError):
        return None
    named = (_CACHE_FORMAT, mujoco.__version__, simplifier, key, stat.st_size, stat.st_mtime_ns)
    return cache_dir() / (hashlib.sha256(repr(named).encode()).hexdigest()[:32] + ".npz")


def _disk_get(key: _Key) -> tuple[_FloatArray, _IntArray] | None:
    """The cached simplification of ``key``; None when there is none or it is not a valid mesh."""
    path = _disk_path(key)
    if path is None:
        return None
    try:
        # Opened here: np.load leaves a file it fails to parse open.
        with path.open("rb") as file, np.load(file, allow_pickle=False) as entry:
            vertices, faces = entry["vertices"], entry["faces"]
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
        return None
    if vertices.dtype != np.float64 or faces.dtype != np.int32:  # no cast that could wrap an index
        return None
    if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
        return None
    if not len(vertices) and not len(faces):
        return _UNCHANGED
    if len(faces) < _MIN_FACES or not np.all(np.isfinite(vertices)):
        return None
    if int(faces.min()) < 0 or int(faces.max()) >= len(vertices):
        return None
    return vertices, faces


def _disk_put(key: _Key, value: tuple[_FloatArray, _IntArray]) -> None:
    """Keep ``value`` for the next process (written whole, then renamed into place)."""
    path = _disk_path(key)
    if path is None:
        return
    written: str | None = None
    try:
        path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)  # no other user's meshes in it
        with tempfile.NamedTemporaryFile(dir=path.parent, suffix=".tmp", delete=False) as handle:
            written = handle.name
            np.savez(handle, vertices=value[0], faces=value[1])
        os.replace(written, path)
    except OSError as exc:
        _log.debug("cannot keep a simplified mesh in %s: %s", path.parent, exc)
        if written is not None:
            with contextlib.suppress(OSError):
                os.unlink(written)


def _simplify(model: mujoco.MjModel, mesh_id: int, faces: int) -> tuple[_FloatArray, _IntArray] | None:
    """Vertices (in the mesh file's frame, scaled) and faces of mesh ``mesh_id`` cut to ``faces``.

    Quadric-error edge collapse (fast-simplification, Garland-Heckbert). The compiled mesh is
    centred on its own inertial frame; ``mesh_pos``/``mesh_quat`` take it back to the frame the geom
    placement refers to, so the recompiled geom sits where the full mesh did. None: within budget.
    """
    try:
        import fast_simplification  # type: ignore[import-untyped]
    except ImportError as exc:
        raise DependencyError(
            "fast-simplification is not installed (it simplifies the robots' visual meshes). "
            "Install it with: pip install fast-simplification==0.2.0, or compile with visual_mesh_faces=0"
        ) from exc

    f0, nf = int(model.mesh_faceadr[mesh_id]), int(model.mesh_facenum[mesh_id])
    if nf <= faces:
        return None
    v0, nv = int(model.mesh_vertadr[mesh_id]), int(model.mesh_vertnum[mesh_id])
    vertices = np.asarray(model.mesh_vert[v0 : v0 + nv], dtype=np.float64)
    triangles = np.asarray(model.mesh_face[f0 : f0 + nf], dtype=np.int32)
    vertices, triangles = _weld(vertices, triangles)
    # The CAD exports split a part into one open mesh per material: collapsing the open borders
    # would tear gaps between the parts (and shrank the UR5e's forearm by 8 cm), so borders stay.
    # The budget is a target: a mesh whose borders hold many faces keeps more. Aggressiveness 3
    # (the library's default is 7) keeps every silhouette within 1 % of the part's size on the
    # UR5e and TIAGo meshes (7 cut up to 10 %: thin flanges went) at about the same face count.
    points, kept = fast_simplification.simplify(
        vertices, triangles, target_count=faces, preserve_border=True, agg=_AGGRESSIVENESS
    )
    kept = np.asarray(kept, dtype=np.int32)
    # Collapses can leave a triangle with a repeated corner; MuJoCo has no use for those.
    kept = kept[(kept[:, 0] != kept[:, 1]) & (kept[:, 1] != kept[:, 2]) & (kept[:, 0] != kept[:, 2])]
    if len(kept) < _MIN_FACES:
        return None
    rotation = np.zeros(9)
    mujoco.mju_quat2Mat(rotation, np.asarray(model.mesh_quat[mesh_id], dtype=np.float64))
    placed = np.asarray(points, dtype=np.float64) @ rotation.reshape(3, 3).T + model.mesh_pos[mesh_id]
    return placed, kept


def _weld(vertices: _FloatArray, triangles: _IntArray) -> tuple[_FloatArray, _IntArray]:
    """Merge vertices on the same 10 µm grid point; the triangles re-indexed.

    Files with per-corner normals load as a triangle soup (3 vertices a face) and edge collapse
    needs shared vertices. The grid coordinates pack into one int64 (21 bits an axis: 20 m) so the
    merge is a 1-D sort; a mesh larger than that sorts the rows instead.
    """
    grid = np.round((vertices - vertices.min(axis=0)) / _WELD_M).astype(np.int64)
    if int(grid.max(initial=0)) < 1 << 21:
        packed = (grid[:, 0] << 42) | (grid[:, 1] << 21) | grid[:, 2]
        _, first, index = np.unique(packed, return_index=True, return_inverse=True)
    else:
        _, first, index = np.unique(grid, axis=0, return_index=True, return_inverse=True)
    return vertices[first], index.reshape(-1)[triangles].astype(np.int32)


def _set_user_mesh(mesh: mujoco.MjsMesh, vertices: _FloatArray, faces: _IntArray) -> None:
    """Make ``mesh`` a user mesh of these (scaled, file-frame) vertices and faces."""
    mesh.file = ""
    mesh.content_type = ""
    mesh.scale = [1.0, 1.0, 1.0]
    mesh.refpos = [0.0, 0.0, 0.0]
    mesh.refquat = [1.0, 0.0, 0.0, 0.0]
    mesh.uservert = vertices.ravel().tolist()
    mesh.userface = faces.ravel().tolist()
