"""Where robot model files come from (installed packages, found by path) and how they load into MuJoCo."""

from __future__ import annotations

import importlib.util
import math
import os
import threading
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path

import mujoco
import numpy as np
from numpy.typing import NDArray

from telerig.errors import DependencyError, RobotError

__all__ = [
    "COLLISION_GROUP",
    "VISUAL_GROUPS",
    "VISUAL_MESH_FACES",
    "compile_spec",
    "drawn_only_geoms",
    "example_robot_data_robots",
    "find",
    "load_spec",
    "package_dir",
    "robosuite_assets",
    "robosuite_models_assets",
    "set_physics_options",
    "visual_mesh_budget",
]

#: Geom group of the robots' collision meshes (robosuite's convention): what self-collision checks
#: and physics contacts use.
COLLISION_GROUP = 0
#: Geom groups a camera should draw: the robot's visual meshes (1) and the world (2), not the
#: robot's collision meshes (0), which would double the geometry to render.
VISUAL_GROUPS = (1, 2)
#: Most faces a robot's visual-only mesh keeps when a model compiles (0: keep every face). The
#: robot meshes are CAD exports (the UR5e's visual meshes: 137 557 faces, ~24 ms of llvmpipe CPU
#: per camera frame); 1 000 a mesh looks the same at camera resolution (benchmarks/render_cost.py
#: measures the cost and saves the images side by side). Physics never sees these meshes.
VISUAL_MESH_FACES = 1_000


def package_dir(module: str, install: str) -> Path:
    """Directory of an installed package that ships model files (it is never imported).

    Args:
        module: Import name, e.g. ``"robosuite"``.
        install: The command that installs it, for the error message.

    Raises:
        DependencyError: the package is not installed.
    """
    spec = importlib.util.find_spec(module)
    if spec is None or not spec.submodule_search_locations:
        raise DependencyError(
            f"{module} is not installed (it ships the robot models). Install it with: {install}"
        )
    return Path(next(iter(spec.submodule_search_locations)))


def robosuite_assets() -> Path:
    """Directory of robosuite's MJCF assets (``.../robosuite/models/assets``).

    robosuite is only a source of model files here; it is never imported (its own
    dependencies are not installed).

    Raises:
        DependencyError: robosuite is not installed.
    """
    return package_dir("robosuite", "pip install --no-deps robosuite==1.5.2") / "models" / "assets"


def robosuite_models_assets() -> Path:
    """Directory of robosuite-models' MJCF assets (``.../robosuite_models/assets``: G1, H1, Ability hands).

    Raises:
        DependencyError: robosuite-models is not installed.
    """
    return package_dir("robosuite_models", "pip install --no-deps robosuite-models==1.0.0") / "assets"


def example_robot_data_robots() -> Path:
    """Directory of example-robot-data's robot descriptions (``.../example-robot-data/robots``).

    example-robot-data is a cmeel wheel: data only, under ``<site-packages>/cmeel.prefix/share``.

    Raises:
        DependencyError: example-robot-data is not installed.
    """
    cmeel = package_dir("cmeel", "pip install example-robot-data==6.0.0")
    robots = cmeel.parent / "cmeel.prefix" / "share" / "example-robot-data" / "robots"
    if not robots.is_dir():
        raise DependencyError(
            "example-robot-data is not installed (it ships the Allegro hand and the G1 URDF). "
            "Install it with: pip install example-robot-data==6.0.0"
        )
    return robots


def load_spec(path: Path) -> mujoco.MjSpec:
    """Parse an MJCF file into a spec with absolute mesh paths and unique asset names.

    Raises:
        RobotError: the file is missing or does not parse.
    """
    if not path.is_file():
        raise RobotError(f"model file not found: {path}")
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise RobotError(f"cannot parse {path}: {exc}") from exc
    seen: set[tuple[str, str]] = set()
    for asset in root.findall("asset"):
        for element in list(asset):
            key = (element.tag, element.get("name", ""))
            # robosuite keeps the first of two same-named assets (robotiq_gripper_85.xml repeats one).
            if key[1] and key in seen:
                asset.remove(element)
                continue
            seen.add(key)
            file = element.get("file")
            if file is not None:
                element.set("file", str((path.parent / file).resolve()))
    try:
        return mujoco.MjSpec.from_string(ET.tostring(root, encoding="unicode"))
    except ValueError as exc:
        raise RobotError(f"cannot load {path}: {exc}") from exc


def find(items: list[object], name: str, kind: str) -> None:
    """Raise unless one of ``items`` (spec elements) is called ``name``.

    Raises:
        RobotError: naming the ``kind`` and the names that exist.
    """
    names = [getattr(item, "name", "") for item in items]
    if name not in names:
        raise RobotError(f"{kind} '{name}' not found. Available: {', '.join(n for n in names if n)}")


def set_physics_options(spec: mujoco.MjSpec, timestep: float) -> None:
    """Timestep [s], implicit-fast integration and grasp-friendly contacts on ``spec``."""
    spec.option.timestep = timestep
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    # Elliptic friction cones with a high impedance ratio stop a grasped object from creeping
    # out of the fingers (the usual MuJoCo setting for grasping; Menagerie's 2F-85 uses it too).
    spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    spec.option.impratio = 10.0


_BUDGET: ContextVar[int] = ContextVar("visual_mesh_faces", default=VISUAL_MESH_FACES)


@contextmanager
def visual_mesh_budget(faces: int) -> Iterator[None]:
    """Models compiled inside keep at most ``faces`` faces per visual-only mesh (0: every face).

    For whoever builds models through the scene builders (which call :func:`compile_spec`): a lab
    that wants full-detail camera images, the render-cost benchmark's baseline.

    Raises:
        ValueError: ``faces`` is negative or in (0, 4).
    """
    _check_budget(faces)
    token = _BUDGET.set(faces)
    try:
        yield
    finally:
        _BUDGET.reset(token)


def _check_budget(faces: int) -> None:
    if faces < 0 or 0 < faces < _MIN_FACES:
        raise ValueError(f"visual_mesh_faces must be 0 (keep every face) or >= {_MIN_FACES}, got {faces}")


def compile_spec(spec: mujoco.MjSpec, *, visual_mesh_faces: int | None = None) -> mujoco.MjModel:
    """Compile ``spec``, the meshes its drawn-only geoms use simplified to ``visual_mesh_faces`` faces.

    Only what drawn, non-colliding geoms that add nothing to a body's mass show is simplified (see
    :func:`drawn_only_geoms`); a mesh that a collision geom uses too (URDF models use one file for
    both) is split: the drawn geoms get a simplified copy (``<name>:visual``), the collision geom
    keeps the original. Contacts, masses and inertias are exactly those of the full model; the
    camera draws a fraction of the triangles. Simplified meshes are kept per process (keyed on the
    mesh file, its scale and the budget): the first build of a model pays one extra compile and
    the simplification, a later build of it one compile as before.

    Args:
        spec: The model, as built (not compiled before); simplified meshes become user meshes.
        visual_mesh_faces: Most faces per drawn mesh; 0 keeps every face; None: the
            :func:`visual_mesh_budget` in force, else :data:`VISUAL_MESH_FACES`.

    Raises:
        RobotError: it does not compile (the MuJoCo message says why).
        ValueError: ``visual_mesh_faces`` is negative or in (0, 4).
    """
    if visual_mesh_faces is None:
        visual_mesh_faces = _BUDGET.get()
    _check_budget(visual_mesh_faces)
    drawn = drawn_only_geoms(spec) if visual_mesh_faces else {}
    users = _mesh_users(spec)
    pending: list[tuple[mujoco.MjsMesh, list[mujoco.MjsGeom], _Key | None]] = []
    for name, geoms in drawn.items():
        mesh = spec.mesh(name)
        key = _mesh_key(spec, mesh, visual_mesh_faces)
        with _SIMPLIFIED_LOCK:
            cached = _SIMPLIFIED.get(key) if key is not None else None
        if cached is None:
            pending.append((mesh, geoms, key))
        elif cached is not _UNCHANGED:
            _use_simplified(spec, mesh, geoms, len(users[name]) > len(geoms), cached)
    if not pending:
        return _compile(spec)
    # The meshes are read from a compiled copy: a mesh compiled from its file keeps the file's
    # normals, which would not match new faces.
    full = spec.copy()
    model = _compile(full)
    changed = False
    for mesh, geoms, key in pending:
        simplified = _simplify(model, full.mesh(mesh.name).id, visual_mesh_faces)
        if key is not None:
            with _SIMPLIFIED_LOCK:
                _SIMPLIFIED[key] = simplified if simplified is not None else _UNCHANGED
        if simplified is not None:
            _use_simplified(spec, mesh, geoms, len(users[mesh.name]) > len(geoms), simplified)
            changed = True
    return _compile(spec) if changed else model


def drawn_only_geoms(spec: mujoco.MjSpec) -> dict[str, list[mujoco.MjsGeom]]:
    """Mesh name -> the geoms using it that only draw it: what can be simplified, physics untouched.

    Such a geom is in :data:`VISUAL_GROUPS`, has ``contype = conaffinity = 0`` (no contacts), adds
    nothing to its body's mass or inertia (the body has an explicit ``<inertial>``, or the geom is
    outside the compiler's inertia group range or has zero mass/density) and has no textured
    material (simplification drops texture coordinates); its mesh is read from a file.
    """
    compiler = spec.compiler
    lo, hi = (int(g) for g in compiler.inertiagrouprange)
    from_geom = compiler.inertiafromgeom
    textured = {material.name for material in spec.materials if any(texture for texture in material.textures)}

    def drawn_only(geom: mujoco.MjsGeom) -> bool:
        if geom.group not in VISUAL_GROUPS or geom.contype != 0 or geom.conaffinity != 0:
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


def _compile(spec: mujoco.MjSpec) -> mujoco.MjModel:
    try:
        return spec.compile()
    except ValueError as exc:
        raise RobotError(f"cannot compile the {spec.modelname or 'robot'} scene: {exc}") from exc


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
