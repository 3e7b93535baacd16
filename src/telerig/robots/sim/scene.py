"""MuJoCo scenes of an arm with a gripper on a table (UR5e + Robotiq 2F-85, Panda), from robosuite assets."""

from __future__ import annotations

import importlib.util
import xml.etree.ElementTree as ET
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, runtime_checkable

import mujoco
import numpy as np

from telerig.errors import DependencyError, RobotError
from telerig.ir.types import FloatArray
from telerig.robots.sim import objects
from telerig.robots.sim.models import UR5E_ROBOTIQ85, ArmModel, GripperModel, arm_model

__all__ = [
    "ARM_JOINTS",
    "EE_SITE",
    "GRIPPER_ACTUATORS",
    "GRIPPER_JOINTS",
    "HOME_QPOS",
    "SIM_SCENES",
    "TABLE_TOP",
    "VISUAL_GROUPS",
    "ArmScene",
    "SimRobot",
    "build_arm_kinematics",
    "build_arm_scene",
    "register_sim_scene",
    "package_dir",
    "robosuite_assets",
    "robosuite_models_assets",
]

#: UR5e arm joints, base to tool.
ARM_JOINTS = UR5E_ROBOTIQ85.joints
_GRIPPER_PREFIX = "gripper/"
#: Grasp-point site of the UR5e's Robotiq between the finger pads (robosuite's ``grip_site``).
EE_SITE = _GRIPPER_PREFIX + UR5E_ROBOTIQ85.gripper.grip_site
#: Robotiq 2F-85 position actuators (one per finger), ctrl 0 = open, 0.8 = closed [rad].
GRIPPER_ACTUATORS = tuple(_GRIPPER_PREFIX + a for a in UR5E_ROBOTIQ85.gripper.actuators)
#: Finger joints driven by :data:`GRIPPER_ACTUATORS`, same order.
GRIPPER_JOINTS = tuple(_GRIPPER_PREFIX + j for j in UR5E_ROBOTIQ85.gripper.joints)
#: UR5e home configuration [rad]: gripper about 0.3 m above the table, pointing down.
HOME_QPOS = UR5E_ROBOTIQ85.home

_TIMESTEP = 0.002  # [s]
#: Geom groups a camera should draw: the robot's visual meshes (1) and the world (2), not the
#: robot's collision meshes (0), which would double the geometry to render.
VISUAL_GROUPS = (1, 2)
#: Height of the table top above the floor [m]; the robot base stands on it.
TABLE_TOP = 0.8
_TABLE_HALF = (0.45, 0.6, TABLE_TOP / 2)  # [m]
_TABLE_CENTER_X = 0.35  # [m], robot base at x = 0 on the table's back half
_CUBE_POS = (0.5, 0.13)  # [m], world frame


@dataclass(frozen=True, slots=True)
class ArmScene:
    """A compiled arm scene and the names a driver or IK solver needs.

    Attributes:
        model: The compiled MuJoCo model (timestep 0.002 s).
        arm_joints: Arm joint names, base to tool. Length n (6 or 7).
        arm_actuators: Position actuators of the arm joints, same order; empty in kinematic models.
        gripper_actuators: Gripper position actuators. Empty in kinematic models.
        gripper_joints: Actuated finger joints, one per gripper actuator.
        ee_site: Grasp-point site, between the finger pads; z axis points out of the gripper.
        base_body: Robot base body; IK targets are expressed in its frame.
        cameras: Camera names, scene camera first.
        home: Home arm configuration [rad]. Shape (n,).
        visual_groups: Geom groups a camera should draw.
        velocity_limit: Joint speed limits [rad/s]. Shape (n,). None: the UR5e's (pi rad/s).
        acceleration_limit: Joint acceleration limits [rad/s^2]. Shape (n,). None: the UR5e's (8).
        gripper_open: Gripper actuator targets when fully open [rad] or [m]. Shape
            (len(gripper_actuators),). None: each actuator's lower ctrl limit.
        gripper_closed: Gripper actuator targets when fully closed. Same shape. None: the upper limit.
        objects: Free bodies of the task object set (reset by the driver's ``reset_objects``).
        arm_model: Name of the arm model (``build_arm_kinematics(arm_model)`` gives its IK model).
    """

    model: mujoco.MjModel
    arm_joints: tuple[str, ...]
    arm_actuators: tuple[str, ...]
    gripper_actuators: tuple[str, ...]
    gripper_joints: tuple[str, ...]
    ee_site: str
    base_body: str
    cameras: tuple[str, ...]
    home: FloatArray
    visual_groups: tuple[int, ...] = VISUAL_GROUPS
    velocity_limit: FloatArray | None = None
    acceleration_limit: FloatArray | None = None
    gripper_open: FloatArray | None = None
    gripper_closed: FloatArray | None = None
    objects: tuple[str, ...] = ()
    arm_model: str = "ur5e_robotiq85"


@runtime_checkable
class SimRobot(Protocol):
    """A simulated robot with its scene, steppable for tests (``realtime=False``)."""

    def connect(self) -> None: ...

    def close(self) -> None: ...

    def step(self, n: int = 1) -> None: ...

    def reset_objects(self) -> None: ...

    def locked(self) -> AbstractContextManager[tuple[mujoco.MjModel, mujoco.MjData]]: ...


#: Every shipped simulated scene, by name: a factory of its robot, stepped (``realtime=False``),
#: not connected. The robot holds home after ``connect()``. Modules register with
#: :func:`register_sim_scene`; one parametrized test builds and steps each.
SIM_SCENES: dict[str, Callable[[], SimRobot]] = {}


def register_sim_scene(name: str) -> Callable[[Callable[[], SimRobot]], Callable[[], SimRobot]]:
    """Decorator: register a factory of a stepped simulated robot under ``name`` in :data:`SIM_SCENES`."""

    def register(factory: Callable[[], SimRobot]) -> Callable[[], SimRobot]:
        if name in SIM_SCENES and SIM_SCENES[name] is not factory:
            raise ValueError(f"sim scene {name!r} is registered twice")
        SIM_SCENES[name] = factory
        return factory

    return register


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


_load_spec = load_spec  # the name sibling modules used before it was public


def _find(items: list[object], name: str, kind: str) -> None:
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


def load_gripper(gripper: GripperModel, *, actuated: bool) -> mujoco.MjSpec:
    """The gripper's MJCF as a spec, cleaned: debug sites hidden, F/T sensors and linkage tendons removed.

    Raises:
        RobotError: the MJCF is missing or lacks ``gripper.root_body``.
    """
    spec = load_spec(robosuite_assets() / gripper.mjcf)
    # robosuite merges the gripper XML into the arm's, whose compiler reads radians.
    spec.compiler.degree = False
    for site in spec.sites:  # robosuite's debug markers; hidden from cameras (group 4)
        site.group = 4
    for sensor in list(spec.sensors):  # F/T sensors on a site that is not needed here
        spec.delete(sensor)
    if gripper.couplings:
        for tendon in list(spec.tendons):  # soft linkage springs, replaced by joint couplings
            spec.delete(tendon)
    for actuator in list(spec.actuators):  # replaced by the model's servos in actuate_gripper
        spec.delete(actuator)
    _find(list(spec.bodies), gripper.root_body, "gripper body")
    if not actuated:
        for joint in list(spec.joints):
            spec.delete(joint)
    return spec


def _load_robot(model: ArmModel, *, kinematic: bool) -> mujoco.MjSpec:
    """The arm's MJCF with the gripper on its flange (prefixed ``gripper/``), without actuators."""
    spec = load_spec(robosuite_assets() / model.mjcf)
    for actuator in list(spec.actuators):  # torque motors, replaced by position servos
        spec.delete(actuator)
    gripper = load_gripper(model.gripper, actuated=not kinematic)
    _find(list(spec.bodies), model.flange_body, "body")
    frame = spec.body(model.flange_body).add_frame()
    frame.attach_body(gripper.body(model.gripper.root_body), _GRIPPER_PREFIX, "")
    for name in model.joints:
        _find(list(spec.joints), name, "joint")
        spec.joint(name).armature = model.armature
    return spec


def actuate_gripper(spec: mujoco.MjSpec, gripper: GripperModel, prefix: str) -> None:
    """Add the gripper's finger servos, linkage couplings and contact exclusions to ``spec``.

    ``prefix`` is what the gripper's names carry in ``spec`` (e.g. ``gripper/``).
    """
    for actuator, joint in zip(gripper.actuators, gripper.joints, strict=True):
        full = prefix + joint
        _find(list(spec.joints), full, "gripper joint")
        lo, hi = spec.joint(full).range
        act = spec.add_actuator(
            name=prefix + actuator, target=full, trntype=mujoco.mjtTrn.mjTRN_JOINT, ctrlrange=[lo, hi]
        )
        act.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
        act.set_to_position(kp=gripper.kp, kv=gripper.kv)
    for joint, leader, coef in gripper.couplings:
        eq = spec.add_equality(
            type=mujoco.mjtEq.mjEQ_JOINT,
            name1=prefix + joint,
            name2=prefix + leader,
            objtype=mujoco.mjtObj.mjOBJ_JOINT,
        )
        eq.data[:5] = [0.0, coef, 0.0, 0.0, 0.0]
        eq.solref = [0.005, 1.0]
    if gripper.exclude_internal:
        # The linkage parts overlap in the meshes; only contacts with the outside world matter.
        parts = [b.name for b in spec.bodies if b.name.startswith(prefix)]
        for i, first in enumerate(parts):
            for second in parts[i + 1 :]:
                spec.add_exclude(bodyname1=first, bodyname2=second)
    if gripper.passive_damping is not None:
        damping, armature = gripper.passive_damping
        for joint in spec.joints:
            if joint.name.startswith(prefix) and joint.name.removeprefix(prefix) not in gripper.joints:
                joint.damping = [damping, 0.0, 0.0]
                joint.armature = armature
        for name in gripper.joints:
            spec.joint(prefix + name).damping = [damping, 0.0, 0.0]
            spec.joint(prefix + name).armature = armature


def _actuate_arm(spec: mujoco.MjSpec, model: ArmModel, prefix: str) -> None:
    """Gravity compensation, arm servos and gripper servos for the arm whose names carry ``prefix``."""
    # Gravity is compensated as a passive force, as the vendors' controllers do.
    fixed = {"world", *(prefix + b for b in model.base_bodies)}
    for body in spec.bodies:
        if body.name.startswith(prefix) and body.name not in fixed:
            body.gravcomp = 1.0
    for name, kp, kv, force in zip(model.joints, model.kp, model.kv, model.force, strict=True):
        joint = spec.joint(prefix + name)
        lo, hi = float(joint.range[0]), float(joint.range[1])  # targets stay inside the joint range
        act = spec.add_actuator(
            name=f"{prefix}{name}_pos",
            target=prefix + name,
            trntype=mujoco.mjtTrn.mjTRN_JOINT,
            ctrlrange=[lo, hi],
            forcerange=[-force, force],
        )
        act.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
        act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
        act.set_to_position(kp=kp, kv=kv)
    actuate_gripper(spec, model.gripper, prefix + _GRIPPER_PREFIX)


def add_room(spec: mujoco.MjSpec) -> None:
    """Rendering settings, a floor and two lights, tuned for real-time software rendering."""
    spec.visual.global_.offwidth = 1280
    spec.visual.global_.offheight = 960
    # Tuned for real-time software rendering (Mesa llvmpipe, no GPU): MSAA, shadows and
    # reflections cost 6x (150 ms → 24 ms per 640x480 frame on 2 cores without them).
    spec.visual.quality.offsamples = 0
    spec.visual.quality.shadowsize = 0
    spec.visual.headlight.ambient = [0.3, 0.3, 0.3]
    world = spec.worldbody
    spec.add_texture(
        name="grid",
        type=mujoco.mjtTexture.mjTEXTURE_2D,
        builtin=mujoco.mjtBuiltin.mjBUILTIN_CHECKER,
        rgb1=[0.25, 0.28, 0.32],
        rgb2=[0.35, 0.38, 0.42],
        width=256,
        height=256,
    )
    grid = spec.add_material(name="floor", texrepeat=[8, 8], reflectance=0.0)
    grid.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = "grid"
    world.add_geom(
        name="floor",
        type=mujoco.mjtGeom.mjGEOM_PLANE,
        size=[3, 3, 0.1],
        material="floor",
        group=VISUAL_GROUPS[1],
    )
    world.add_light(name="key", pos=[0.5, -1.0, 3.0], dir=[-0.1, 0.3, -1.0], castshadow=False)
    world.add_light(name="fill", pos=[-1.0, 1.0, 2.5], dir=[0.5, -0.4, -1.0], castshadow=False)


def add_table(spec: mujoco.MjSpec, center_xy: tuple[float, float], half_xy: tuple[float, float]) -> None:
    """A table (body ``table``, geom ``table_top``) with its top at :data:`TABLE_TOP` [m]."""
    table = spec.worldbody.add_body(name="table", pos=[center_xy[0], center_xy[1], TABLE_TOP / 2])
    table.add_geom(
        name="table_top",
        type=mujoco.mjtGeom.mjGEOM_BOX,
        size=[half_xy[0], half_xy[1], TABLE_TOP / 2],
        rgba=[0.55, 0.42, 0.3, 1.0],
        group=VISUAL_GROUPS[1],
    )


def _add_world(spec: mujoco.MjSpec, *, with_cube: bool) -> tuple[str, ...]:
    add_room(spec)
    add_table(spec, (_TABLE_CENTER_X, 0.0), _TABLE_HALF[:2])
    bodies = (objects.add_cube(spec, "cube", (*_CUBE_POS, TABLE_TOP)),) if with_cube else ()
    # Looks from the front-right at the arm, table and cube.
    spec.worldbody.add_camera(
        name="scene", pos=[1.6, 1.1, 1.65], xyaxes=[-0.57, 0.82, 0.0, -0.33, -0.23, 0.91], fovy=50
    )
    return bodies


def build_arm_scene(
    model: str = "ur5e_robotiq85", *, with_cube: bool = True, timestep: float = _TIMESTEP
) -> ArmScene:
    """Build an arm scene: the robot base on a 0.8 m table at the world origin, a cube in front of it.

    The arm has position servos (ctrl = joint target [rad], clipped to the joint range) with
    gravity compensation; each finger has a position servo (see ``ArmScene.gripper_open`` and
    ``gripper_closed``). The world frame has z up; the robot base frame is at (0, 0, 0.8) m in the
    world, axes aligned with it.

    Args:
        model: Arm model name, a key of :data:`~telerig.robots.sim.models.ARM_MODELS`
            (``ur5e_robotiq85``, ``panda``).
        with_cube: Add a free 4 cm cube on the table in front of the robot (body ``cube``).
        timestep: Physics timestep [s]; the servo gains are tuned for 0.002 s (500 Hz).

    Raises:
        ConfigError: no such arm model.
        DependencyError: robosuite (the model source) is not installed.
        RobotError: a model file is missing or does not compile.
    """
    if not 0 < timestep <= 0.01:
        raise ValueError(f"timestep must be in (0, 0.01] s for the arm servos to be stable, got {timestep}")
    arm = arm_model(model)
    spec = _load_robot(arm, kinematic=False)
    spec.modelname = arm.name
    set_physics_options(spec, timestep)
    _actuate_arm(spec, arm, "")
    spec.body(arm.base_bodies[0]).pos = [0.0, 0.0, TABLE_TOP]
    bodies = _add_world(spec, with_cube=with_cube)
    return arm_scene(compile_spec(spec), arm, prefix="", objects=bodies)


def build_arm_kinematics(model: str = "ur5e_robotiq85") -> ArmScene:
    """Build the kinematic model for IK: arm joints only, a rigid gripper, no world objects.

    The robot base sits at the world origin, so world and base frames coincide; the
    ``ee_site`` is at the same place on the gripper as in :func:`build_arm_scene`.

    Raises:
        ConfigError: no such arm model.
        DependencyError: robosuite (the model source) is not installed.
        RobotError: a model file is missing or does not compile.
    """
    arm = arm_model(model)
    spec = _load_robot(arm, kinematic=True)
    spec.modelname = arm.name
    set_physics_options(spec, _TIMESTEP)
    for joint in list(spec.joints):  # rigid gripper: IK moves only the arm
        if joint.name not in arm.joints:
            spec.delete(joint)
    return arm_scene(compile_spec(spec), arm, prefix="", kinematic=True)


def compile_spec(spec: mujoco.MjSpec) -> mujoco.MjModel:
    """Compile ``spec``.

    Raises:
        RobotError: it does not compile (the MuJoCo message says why).
    """
    try:
        return spec.compile()
    except ValueError as exc:
        raise RobotError(f"cannot compile the {spec.modelname or 'robot'} scene: {exc}") from exc


def _frozen(values: tuple[float, ...] | FloatArray) -> FloatArray:
    arr = np.array(values, dtype=np.float64)
    arr.flags.writeable = False
    return arr


def arm_scene(
    model: mujoco.MjModel,
    arm: ArmModel,
    *,
    prefix: str,
    objects: tuple[str, ...] = (),
    kinematic: bool = False,
    scene_camera: str = "scene",
) -> ArmScene:
    """The :class:`ArmScene` of the arm named with ``prefix`` in a compiled ``model``."""
    cameras = tuple(model.camera(i).name for i in range(model.ncam))
    gripper = arm.gripper
    grip_prefix = prefix + _GRIPPER_PREFIX
    return ArmScene(
        model=model,
        arm_joints=tuple(prefix + j for j in arm.joints),
        arm_actuators=() if kinematic else tuple(f"{prefix}{j}_pos" for j in arm.joints),
        gripper_actuators=() if kinematic else tuple(grip_prefix + a for a in gripper.actuators),
        gripper_joints=() if kinematic else tuple(grip_prefix + j for j in gripper.joints),
        ee_site=grip_prefix + gripper.grip_site,
        base_body=prefix + arm.base_bodies[0],
        cameras=tuple(sorted(cameras, key=lambda c: c != scene_camera)),
        home=_frozen(arm.home),
        velocity_limit=_frozen(arm.velocity),
        acceleration_limit=_frozen(arm.acceleration),
        gripper_open=_frozen(() if kinematic else gripper.open_ctrl),
        gripper_closed=_frozen(() if kinematic else gripper.closed_ctrl),
        objects=objects,
        arm_model=arm.name,
    )


def free_bodies(model: mujoco.MjModel) -> Iterator[int]:
    """Ids of the bodies with a free joint (the task objects)."""
    for j in range(model.njnt):
        if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:
            yield int(model.jnt_bodyid[j])
