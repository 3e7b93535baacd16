"""Kinematic model of an arm with its gripper, built from the arm's model description alone (no world)."""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from telerig.ir.types import FloatArray
from telerig.robots.models.arms import ArmModel, GripperModel, arm_model
from telerig.robots.models.mjcf import (
    VISUAL_GROUPS,
    compile_kinematic,
    compile_spec,
    find,
    load_spec,
    robosuite_assets,
    set_physics_options,
)

__all__ = [
    "FT_SITE",
    "GRIPPER_PREFIX",
    "ArmScene",
    "arm_scene",
    "build_arm_kinematics",
    "load_arm",
    "load_gripper",
]

#: Prefix of the gripper's names when it is attached to an arm's flange.
GRIPPER_PREFIX = "gripper/"
#: Site of a simulated arm's wrist force/torque sensor (at the flange, where the gripper mounts; after
#: the arm's prefix); its sensors are ``<site>_force`` and ``<site>_torque``.
FT_SITE = "ft_sensor"
_TIMESTEP = 0.002  # [s]


@dataclass(frozen=True, slots=True)
class ArmScene:
    """A compiled arm model (kinematic, or a simulated scene) and the names a driver or IK solver needs.

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
        ft_site: Site of the wrist force/torque sensor (sensors ``<ft_site>_force`` and
            ``<ft_site>_torque``, MuJoCo's force and torque sensors); ``None`` without one.
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
    ft_site: str | None = None


def load_gripper(gripper: GripperModel, *, actuated: bool) -> mujoco.MjSpec:
    """The gripper's MJCF as a spec, cleaned: debug sites hidden, F/T sensors and linkage tendons removed.

    Args:
        gripper: The gripper's model description.
        actuated: Keep the finger joints (a simulated gripper); False makes it rigid (IK, guards).

    Raises:
        DependencyError: robosuite (the model source) is not installed.
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
    for actuator in list(spec.actuators):  # replaced by the simulation's finger servos
        spec.delete(actuator)
    find(list(spec.bodies), gripper.root_body, "gripper body")
    if not actuated:
        for joint in list(spec.joints):
            spec.delete(joint)
    return spec


def load_arm(model: ArmModel, *, kinematic: bool) -> mujoco.MjSpec:
    """The arm's MJCF with the gripper on its flange (prefixed :data:`GRIPPER_PREFIX`), without actuators.

    Args:
        model: The arm's model description.
        kinematic: Rigid gripper (no finger joints).

    Raises:
        DependencyError: robosuite (the model source) is not installed.
        RobotError: a model file is missing or lacks a body or joint the description names.
    """
    spec = load_spec(robosuite_assets() / model.mjcf)
    for actuator in list(spec.actuators):  # torque motors, replaced by position servos
        spec.delete(actuator)
    gripper = load_gripper(model.gripper, actuated=not kinematic)
    find(list(spec.bodies), model.flange_body, "body")
    frame = spec.body(model.flange_body).add_frame()
    frame.attach_body(gripper.body(model.gripper.root_body), GRIPPER_PREFIX, "")
    for name in model.joints:
        find(list(spec.joints), name, "joint")
        spec.joint(name).armature = model.armature
    return spec


def build_arm_kinematics(model: str = "ur5e_robotiq85", *, drawn: bool = False) -> ArmScene:
    """Build the kinematic model for IK and the safety guards: arm joints only, a rigid gripper, no world.

    The robot base sits at the world origin, so world and base frames coincide; the ``ee_site`` is
    at the same place on the gripper as in a simulated scene of the arm. Collision geometry is the
    MJCF's (robot and gripper meshes of geom group
    :data:`~telerig.robots.models.mjcf.COLLISION_GROUP`).

    Args:
        model: Arm model name, a key of :data:`~telerig.robots.models.arms.ARM_MODELS`.
        drawn: Keep the geoms only a camera draws (simplified; for whoever draws the model, e.g.
            the web scene); without them (the default) it builds in a fraction of the time
            (:func:`~telerig.robots.models.mjcf.compile_kinematic`).

    Raises:
        ConfigError: no such arm model.
        DependencyError: robosuite (the model source) is not installed.
        RobotError: a model file is missing or does not compile.
    """
    arm = arm_model(model)
    spec = load_arm(arm, kinematic=True)
    spec.modelname = arm.name
    set_physics_options(spec, _TIMESTEP)
    for joint in list(spec.joints):  # rigid gripper: IK moves only the arm
        if joint.name not in arm.joints:
            spec.delete(joint)
    compiled = compile_spec(spec) if drawn else compile_kinematic(spec)
    return arm_scene(compiled, arm, prefix="", kinematic=True)


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
    ft_site = prefix + FT_SITE
    has_ft = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, ft_site) >= 0
    gripper = arm.gripper
    grip_prefix = prefix + GRIPPER_PREFIX
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
        ft_site=ft_site if has_ft else None,
    )
