"""MuJoCo scenes of an arm with a gripper on a table (UR5e + Robotiq 2F-85, Panda), from robosuite assets."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import AbstractContextManager
from typing import Protocol, runtime_checkable

import mujoco

from telerig.robots.models.arm import FT_SITE, GRIPPER_PREFIX, ArmScene, arm_scene, load_arm
from telerig.robots.models.arms import UR5E_ROBOTIQ85, ArmModel, GripperModel, arm_model
from telerig.robots.models.mjcf import VISUAL_GROUPS, compile_spec, find, set_physics_options
from telerig.robots.sim import objects

__all__ = [
    "ARM_JOINTS",
    "EE_SITE",
    "GRIPPER_ACTUATORS",
    "GRIPPER_JOINTS",
    "HOME_QPOS",
    "TABLE_TOP",
    "SimRobot",
    "actuate_gripper",
    "add_room",
    "add_table",
    "build_arm_scene",
    "free_bodies",
]

#: UR5e arm joints, base to tool.
ARM_JOINTS = UR5E_ROBOTIQ85.joints
_GRIPPER_PREFIX = GRIPPER_PREFIX
#: Grasp-point site of the UR5e's Robotiq between the finger pads (robosuite's ``grip_site``).
EE_SITE = _GRIPPER_PREFIX + UR5E_ROBOTIQ85.gripper.grip_site
#: Robotiq 2F-85 position actuators (one per finger), ctrl 0 = open, 0.8 = closed [rad].
GRIPPER_ACTUATORS = tuple(_GRIPPER_PREFIX + a for a in UR5E_ROBOTIQ85.gripper.actuators)
#: Finger joints driven by :data:`GRIPPER_ACTUATORS`, same order.
GRIPPER_JOINTS = tuple(_GRIPPER_PREFIX + j for j in UR5E_ROBOTIQ85.gripper.joints)
#: UR5e home configuration [rad]: gripper about 0.3 m above the table, pointing down.
HOME_QPOS = UR5E_ROBOTIQ85.home

_TIMESTEP = 0.002  # [s]
#: Height of the table top above the floor [m]; the robot base stands on it.
TABLE_TOP = 0.8
_TABLE_HALF = (0.45, 0.6, TABLE_TOP / 2)  # [m]
_TABLE_CENTER_X = 0.35  # [m], robot base at x = 0 on the table's back half
_CUBE_POS = (0.5, 0.13)  # [m], world frame


@runtime_checkable
class SimRobot(Protocol):
    """A simulated robot with its scene, steppable for tests (``realtime=False``).

    Every shipped scene is built from robot configs: :func:`telerig.robots.sim.config.shipped_scenes`.
    """

    def connect(self) -> None: ...

    def close(self) -> None: ...

    def step(self, n: int = 1) -> None: ...

    def reset_objects(self) -> None: ...

    def locked(self) -> AbstractContextManager[tuple[mujoco.MjModel, mujoco.MjData]]: ...


def actuate_gripper(spec: mujoco.MjSpec, gripper: GripperModel, prefix: str) -> None:
    """Add the gripper's finger servos, linkage couplings and contact exclusions to ``spec``.

    ``prefix`` is what the gripper's names carry in ``spec`` (e.g. ``gripper/``).
    """
    for actuator, joint in zip(gripper.actuators, gripper.joints, strict=True):
        full = prefix + joint
        find(list(spec.joints), full, "gripper joint")
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
    _add_wrist_ft(spec, model, prefix)


def _add_wrist_ft(spec: mujoco.MjSpec, model: ArmModel, prefix: str) -> None:
    """A force/torque sensor between the flange and the gripper (site ``<prefix>ft_sensor`` at the
    gripper's mount, axes of the gripper's root body), as a wrist F/T sensor under a real gripper.

    MuJoCo's force and torque sensors give the parent's (the flange's) force and torque on the
    gripper's subtree at the site; the gripper's own weight is gravity-compensated like the arm's,
    so at rest they read the load alone.
    """
    root = spec.body(prefix + _GRIPPER_PREFIX + model.gripper.root_body)
    site = prefix + FT_SITE
    root.add_site(name=site, pos=[0.0, 0.0, 0.0], group=4)  # group 4: hidden from cameras
    sensors = (("force", mujoco.mjtSensor.mjSENS_FORCE), ("torque", mujoco.mjtSensor.mjSENS_TORQUE))
    for kind, sensor in sensors:
        spec.add_sensor(name=f"{site}_{kind}", type=sensor, objtype=mujoco.mjtObj.mjOBJ_SITE, objname=site)


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


def _add_world(
    spec: mujoco.MjSpec, *, with_cube: bool, target_zone: tuple[float, float, float] | None = None
) -> tuple[str, ...]:
    add_room(spec)
    add_table(spec, (_TABLE_CENTER_X, 0.0), _TABLE_HALF[:2])
    bodies = (objects.add_cube(spec, "cube", (*_CUBE_POS, TABLE_TOP)),) if with_cube else ()
    if target_zone is not None:
        objects.add_zone(spec, "target", (target_zone[0], target_zone[1], TABLE_TOP), half=target_zone[2])
    # Looks from the front-right at the arm, table and cube.
    spec.worldbody.add_camera(
        name="scene", pos=[1.6, 1.1, 1.65], xyaxes=[-0.57, 0.82, 0.0, -0.33, -0.23, 0.91], fovy=50
    )
    # Looks down at the table in front of the robot from its right: cube and target zone fill the
    # view (the 4 cm cube is ~7 % of the image height, ~2 % in "scene"), what a policy trained at
    # a hundred pixels needs to see where the cube is; the arm enters the view as it reaches down.
    spec.worldbody.add_camera(
        name="workspace", pos=[0.5, -0.6, 1.35], xyaxes=[1.0, 0.0, 0.0, 0.0, 0.646, 0.763], fovy=40
    )
    return bodies


def build_arm_scene(
    model: str = "ur5e_robotiq85",
    *,
    with_cube: bool = True,
    timestep: float = _TIMESTEP,
    target_zone: tuple[float, float, float] | None = None,
) -> ArmScene:
    """Build an arm scene: the robot base on a 0.8 m table at the world origin, a cube in front of it.

    The arm has position servos (ctrl = joint target [rad], clipped to the joint range) with
    gravity compensation; each finger has a position servo (see ``ArmScene.gripper_open`` and
    ``gripper_closed``). The world frame has z up; the robot base frame is at (0, 0, 0.8) m in the
    world, axes aligned with it.

    Args:
        model: Arm model name, a key of :data:`~telerig.robots.models.arms.ARM_MODELS`
            (``ur5e_robotiq85``, ``panda``).
        with_cube: Add a free 4 cm cube on the table in front of the robot (body ``cube``).
        timestep: Physics timestep [s]; the servo gains are tuned for 0.002 s (500 Hz).
        target_zone: A square place zone marked on the table (body ``target``, drawn, no
            contact): centre x, y [m] in the world and half edge [m]; none when None.

    Raises:
        ConfigError: no such arm model.
        DependencyError: robosuite (the model source) is not installed.
        RobotError: a model file is missing or does not compile.
    """
    if not 0 < timestep <= 0.01:
        raise ValueError(f"timestep must be in (0, 0.01] s for the arm servos to be stable, got {timestep}")
    arm = arm_model(model)
    spec = load_arm(arm, kinematic=False)
    spec.modelname = arm.name
    set_physics_options(spec, timestep)
    _actuate_arm(spec, arm, "")
    spec.body(arm.base_bodies[0]).pos = [0.0, 0.0, TABLE_TOP]
    bodies = _add_world(spec, with_cube=with_cube, target_zone=target_zone)
    return arm_scene(compile_spec(spec), arm, prefix="", objects=bodies)


def free_bodies(model: mujoco.MjModel) -> Iterator[int]:
    """Ids of the bodies with a free joint (the task objects)."""
    for j in range(model.njnt):
        if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:
            yield int(model.jnt_bodyid[j])
