"""MuJoCo scene of a UR5e with a Robotiq 2F-85 gripper on a table, built from robosuite assets."""

from __future__ import annotations

import importlib.util
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from telerig.errors import DependencyError, RobotError
from telerig.ir.types import FloatArray

__all__ = [
    "ARM_JOINTS",
    "EE_SITE",
    "GRIPPER_ACTUATORS",
    "GRIPPER_JOINTS",
    "HOME_QPOS",
    "VISUAL_GROUPS",
    "ArmScene",
    "build_arm_kinematics",
    "build_arm_scene",
    "robosuite_assets",
]

#: UR5e arm joints, base to tool.
ARM_JOINTS = (
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
)
_GRIPPER_PREFIX = "gripper/"
#: Grasp-point site between the finger pads (robosuite's ``grip_site``).
EE_SITE = "gripper/grip_site"
#: Robotiq 2F-85 position actuators (one per finger), ctrl 0 = open, 0.8 = closed [rad].
GRIPPER_ACTUATORS = ("gripper/finger_1", "gripper/finger_2")
#: Finger joints driven by :data:`GRIPPER_ACTUATORS`, same order.
GRIPPER_JOINTS = ("gripper/finger_joint", "gripper/right_outer_knuckle_joint")
#: Home arm configuration [rad]: gripper about 0.3 m above the table, pointing down.
HOME_QPOS = (0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0)

# Position servo gains per joint, stiffness [N m/rad] and damping [N m s/rad]: about critically
# damped for the joint inertias at home (2.2 kg m^2 shoulder, 0.1 wrist): 90 % of a small step in
# under 0.1 s, no overshoot at 2 ms. (Menagerie's 2000/400 is overdamped and lags ~0.2 s.)
# Force limits are robosuite's, the UR5e maximum joint torques.
_ARM_KP = (4000.0, 4000.0, 4000.0, 500.0, 500.0, 500.0)
_ARM_KV = (160.0, 160.0, 160.0, 15.0, 15.0, 15.0)
_ARM_FORCE = (150.0, 150.0, 150.0, 28.0, 28.0, 28.0)
_ARM_ARMATURE = 0.1  # reflected rotor inertia [kg m^2], Menagerie value

# Four-bar linkage of each finger as joint couplings (mimic joints of the Robotiq URDF):
# the inner knuckle turns with the outer knuckle, the inner finger counter-rotates so the
# pads stay parallel. robosuite approximates this with soft tendons, which fight the servo.
_FINGER_COUPLINGS = (
    ("gripper/left_inner_knuckle_joint", "gripper/finger_joint", 1.0),
    ("gripper/left_inner_finger_joint", "gripper/finger_joint", -1.0),
    ("gripper/right_inner_knuckle_joint", "gripper/right_outer_knuckle_joint", 1.0),
    ("gripper/right_inner_finger_joint", "gripper/right_outer_knuckle_joint", -1.0),
)

_TIMESTEP = 0.002  # [s]
#: Geom groups a camera should draw: the robot's visual meshes (1) and the world (2), not the
#: robot's collision meshes (0), which would double the geometry to render.
VISUAL_GROUPS = (1, 2)
_TABLE_TOP = 0.8  # table height [m]
_TABLE_HALF = (0.45, 0.6, _TABLE_TOP / 2)  # [m]
_TABLE_CENTER_X = 0.35  # [m], robot base at x = 0 on the table's back half
_CUBE_HALF = 0.02  # [m]
_CUBE_POS = (0.5, 0.13, _TABLE_TOP + _CUBE_HALF)  # [m], world frame


@dataclass(frozen=True, slots=True)
class ArmScene:
    """A compiled arm scene and the names a driver or IK solver needs.

    Attributes:
        model: The compiled MuJoCo model (timestep 0.002 s).
        arm_joints: Arm joint names, base to tool. Length 6.
        arm_actuators: Position actuators of the arm joints, same order; empty in kinematic models.
        gripper_actuators: Gripper position actuators; ctrl in [rad], low = open. Empty in kinematic models.
        gripper_joints: Actuated finger joints, one per gripper actuator.
        ee_site: Grasp-point site, between the finger pads; z axis points out of the gripper.
        base_body: Robot base body; IK targets are expressed in its frame.
        cameras: Camera names, scene camera first.
        visual_groups: Geom groups a camera should draw.
        home: Home arm configuration [rad]. Shape (6,).
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


def robosuite_assets() -> Path:
    """Directory of robosuite's MJCF assets (``.../robosuite/models/assets``).

    robosuite is only a source of model files here; it is never imported (its own
    dependencies are not installed).

    Raises:
        DependencyError: robosuite is not installed.
    """
    spec = importlib.util.find_spec("robosuite")
    if spec is None or not spec.submodule_search_locations:
        raise DependencyError(
            "robosuite is not installed (needed for the UR5e and Robotiq models). "
            "Install it with: pip install --no-deps robosuite==1.5.2"
        )
    return Path(next(iter(spec.submodule_search_locations))) / "models" / "assets"


def _load_spec(path: Path) -> mujoco.MjSpec:
    """Parse an MJCF file into a spec with absolute mesh paths and unique asset names."""
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


def _find(items: list[object], name: str, kind: str) -> None:
    names = [getattr(item, "name", "") for item in items]
    if name not in names:
        raise RobotError(f"{kind} '{name}' not found. Available: {', '.join(n for n in names if n)}")


def _build_robot(*, kinematic: bool) -> mujoco.MjSpec:
    assets = robosuite_assets()
    spec = _load_spec(assets / "robots" / "ur5e" / "robot.xml")
    gripper = _load_spec(assets / "grippers" / "robotiq_gripper_85.xml")
    # robosuite merges the gripper XML into the arm's, whose compiler reads radians.
    gripper.compiler.degree = False
    spec.modelname = "ur5e_robotiq85"
    spec.option.timestep = _TIMESTEP
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    # Elliptic friction cones with a high impedance ratio stop a grasped object from creeping
    # out of the fingers (the usual MuJoCo setting for grasping; Menagerie's 2F-85 uses it too).
    spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    spec.option.impratio = 10.0

    for actuator in list(spec.actuators):  # torque motors, replaced by position servos below
        spec.delete(actuator)
    for site in gripper.sites:  # robosuite's debug markers; hidden from cameras (group 4)
        site.group = 4
    for sensor in list(gripper.sensors):  # F/T sensors on a site that is not needed here
        gripper.delete(sensor)
    for tendon in list(gripper.tendons):  # soft linkage springs, replaced by joint couplings below
        gripper.delete(tendon)
    if kinematic:
        for actuator in list(gripper.actuators):
            gripper.delete(actuator)

    _find(list(spec.bodies), "right_hand", "body")
    _find(list(gripper.bodies), "robotiq_85_adapter_link", "gripper body")
    frame = spec.body("right_hand").add_frame()
    frame.attach_body(gripper.body("robotiq_85_adapter_link"), _GRIPPER_PREFIX, "")

    for name in ARM_JOINTS:
        _find(list(spec.joints), name, "joint")
        spec.joint(name).armature = _ARM_ARMATURE

    if kinematic:
        # Rigid gripper: IK moves only the arm, so the finger joints are dropped.
        for joint in list(spec.joints):
            if joint.name not in ARM_JOINTS:
                spec.delete(joint)
        return spec

    # Gravity is compensated as a passive force, as the UR controller does.
    for body in spec.bodies:
        if body.name not in ("world", "base", "fixed_base_link"):
            body.gravcomp = 1.0

    for name, kp, kv, force in zip(ARM_JOINTS, _ARM_KP, _ARM_KV, _ARM_FORCE, strict=True):
        joint = spec.joint(name)
        lo, hi = float(joint.range[0]), float(joint.range[1])  # targets stay inside the joint range
        act = spec.add_actuator(
            name=f"{name}_pos",
            target=name,
            trntype=mujoco.mjtTrn.mjTRN_JOINT,
            ctrlrange=[lo, hi],
            forcerange=[-force, force],
        )
        act.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
        act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
        act.set_to_position(kp=kp, kv=kv)

    for joint, leader, coef in _FINGER_COUPLINGS:
        eq = spec.add_equality(
            type=mujoco.mjtEq.mjEQ_JOINT, name1=joint, name2=leader, objtype=mujoco.mjtObj.mjOBJ_JOINT
        )
        eq.data[:5] = [0.0, coef, 0.0, 0.0, 0.0]
        eq.solref = [0.005, 1.0]
    # The linkage parts overlap in the meshes; only contacts with the outside world matter.
    parts = [b.name for b in spec.bodies if b.name.startswith(_GRIPPER_PREFIX)]
    for i, first in enumerate(parts):
        for second in parts[i + 1 :]:
            spec.add_exclude(bodyname1=first, bodyname2=second)
    for actuator in spec.actuators:
        if actuator.name in GRIPPER_ACTUATORS:
            actuator.set_to_position(kp=20.0, kv=0.5)
    for joint in spec.joints:
        if joint.name not in ARM_JOINTS:
            joint.damping = [0.05, 0.0, 0.0]
            joint.armature = 0.001
    return spec


def _add_world(spec: mujoco.MjSpec, *, with_cube: bool) -> None:
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
    table = world.add_body(name="table", pos=[_TABLE_CENTER_X, 0.0, _TABLE_TOP / 2])
    table.add_geom(
        name="table_top",
        type=mujoco.mjtGeom.mjGEOM_BOX,
        size=list(_TABLE_HALF),
        rgba=[0.55, 0.42, 0.3, 1.0],
        group=VISUAL_GROUPS[1],
    )
    if with_cube:
        cube = world.add_body(name="cube", pos=list(_CUBE_POS))
        cube.add_freejoint(name="cube_free")
        cube.add_geom(
            name="cube",
            type=mujoco.mjtGeom.mjGEOM_BOX,
            size=[_CUBE_HALF] * 3,
            mass=0.05,
            rgba=[0.85, 0.15, 0.15, 1.0],
            group=VISUAL_GROUPS[1],
            condim=4,
            friction=[1.5, 0.01, 0.001],
        )
    # Looks from the front-right at the arm, table and cube.
    world.add_camera(
        name="scene", pos=[1.6, 1.1, 1.65], xyaxes=[-0.57, 0.82, 0.0, -0.33, -0.23, 0.91], fovy=50
    )


def build_arm_scene(*, with_cube: bool = True, timestep: float = _TIMESTEP) -> ArmScene:
    """Build the UR5e + Robotiq 2F-85 scene: robot base on a 0.8 m table at the world origin.

    The arm has position servos (ctrl = joint target [rad], clipped to the joint range) with
    gravity compensation;
    each finger has a position servo (ctrl 0 = open, 0.8 = closed [rad]). The world frame
    has z up; the robot base frame is at (0, 0, 0.8) m in the world, axes aligned with it.

    Args:
        with_cube: Add a free 4 cm cube on the table in front of the robot (body ``cube``).
        timestep: Physics timestep [s]; the servo gains are tuned for 0.002 s (500 Hz).

    Raises:
        DependencyError: robosuite (the model source) is not installed.
        RobotError: a model file is missing or does not compile.
    """
    if not 0 < timestep <= 0.01:
        raise ValueError(f"timestep must be in (0, 0.01] s for the arm servos to be stable, got {timestep}")
    spec = _build_robot(kinematic=False)
    spec.option.timestep = timestep
    spec.body("base").pos = [0.0, 0.0, _TABLE_TOP]
    _add_world(spec, with_cube=with_cube)
    model = _compile(spec)
    return _scene(model, kinematic=False)


def build_arm_kinematics() -> ArmScene:
    """Build the kinematic model for IK: arm joints only, a rigid gripper, no world objects.

    The robot base sits at the world origin, so world and base frames coincide; the
    ``ee_site`` is at the same place on the gripper as in :func:`build_arm_scene`.

    Raises:
        DependencyError: robosuite (the model source) is not installed.
        RobotError: a model file is missing or does not compile.
    """
    return _scene(_compile(_build_robot(kinematic=True)), kinematic=True)


def _compile(spec: mujoco.MjSpec) -> mujoco.MjModel:
    try:
        return spec.compile()
    except ValueError as exc:
        raise RobotError(f"cannot compile the arm scene: {exc}") from exc


def _scene(model: mujoco.MjModel, *, kinematic: bool) -> ArmScene:
    cameras = tuple(model.camera(i).name for i in range(model.ncam))
    ordered = tuple(sorted(cameras, key=lambda c: c != "scene"))
    home = np.array(HOME_QPOS)
    home.flags.writeable = False
    return ArmScene(
        model=model,
        arm_joints=ARM_JOINTS,
        arm_actuators=() if kinematic else tuple(f"{j}_pos" for j in ARM_JOINTS),
        gripper_actuators=() if kinematic else GRIPPER_ACTUATORS,
        gripper_joints=() if kinematic else GRIPPER_JOINTS,
        ee_site=EE_SITE,
        base_body="base",
        cameras=ordered,
        home=home,
    )
