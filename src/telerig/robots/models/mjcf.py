"""Where robot model files come from (installed packages, found by path) and how they load into MuJoCo."""

from __future__ import annotations

import importlib.util
import xml.etree.ElementTree as ET
from pathlib import Path

import mujoco

from telerig.errors import DependencyError, RobotError
from telerig.robots.models import visual_meshes

__all__ = [
    "COLLISION_GROUP",
    "VISUAL_GROUPS",
    "compile_kinematic",
    "compile_spec",
    "example_robot_data_robots",
    "find",
    "load_spec",
    "package_dir",
    "robosuite_assets",
    "robosuite_models_assets",
    "set_physics_options",
]

#: Geom group of the robots' collision meshes (robosuite's convention): what self-collision checks
#: and physics contacts use.
COLLISION_GROUP = 0
#: Geom groups a camera should draw: the robot's visual meshes (1) and the world (2), not the
#: robot's collision meshes (0), which would double the geometry to render.
VISUAL_GROUPS = (1, 2)


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


def compile_spec(spec: mujoco.MjSpec, *, visual_mesh_faces: int | None = None) -> mujoco.MjModel:
    """Compile ``spec``, the meshes only its camera-drawn geoms use simplified (:mod:`.visual_meshes`).

    Args:
        spec: The model, as built (not compiled before); simplified meshes become user meshes.
        visual_mesh_faces: Most faces per drawn mesh; 0 keeps every face; None: the
            ``visual_meshes.visual_mesh_budget`` in force, else ``visual_meshes.VISUAL_MESH_FACES``.

    Raises:
        RobotError: it does not compile (the MuJoCo message says why).
        ValueError: ``visual_mesh_faces`` is negative or in (0, 4).
    """
    faces = (
        visual_meshes.budget() if visual_mesh_faces is None else visual_meshes.check_budget(visual_mesh_faces)
    )
    if not faces:
        return _compile(spec)
    return visual_meshes.compile_simplified(spec, faces, groups=VISUAL_GROUPS, compile=_compile)


def compile_kinematic(spec: mujoco.MjSpec) -> mujoco.MjModel:
    """Compile ``spec`` to compute with, not to draw: the geoms only a camera draws are left out.

    IK, the safety guards, the quality gates and the exports need bodies, joints, sites and the
    collision geoms; what a camera alone draws (:func:`.visual_meshes.drawn_only_geoms`: no
    contacts, no mass) is most of a robot's mesh data, CAD exports of 10^5 faces. Without it the
    kinematic models build in a fresh process in 0.10 s instead of 1.44 s (UR5e), 0.86 instead of
    2.11 s (TIAGo: its collision meshes remain) and 0.44 instead of 1.51 s (G1) on the 2-core VM,
    and every body, joint, site and collision geom is the same.

    Raises:
        RobotError: it does not compile (the MuJoCo message says why).
    """
    visual_meshes.strip_drawn_only(spec, VISUAL_GROUPS)
    return _compile(spec)


def _compile(spec: mujoco.MjSpec) -> mujoco.MjModel:
    try:
        return spec.compile()
    except ValueError as exc:
        raise RobotError(f"cannot compile the {spec.modelname or 'robot'} scene: {exc}") from exc
