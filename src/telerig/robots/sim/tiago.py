"""MuJoCo TIAGo mobile manipulator (holonomic base, torso, right arm, Robotiq 2F-85) from robosuite assets."""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from telerig.errors import RobotError
from telerig.ir.types import FloatArray
from telerig.robots.base import JointLimits
from telerig.robots.sim.models import ROBOTIQ_2F85
from telerig.robots.sim.scene import (
    TABLE_TOP,
    VISUAL_GROUPS,
    actuate_gripper,
    add_room,
    add_table,
    compile_spec,
    load_gripper,
    load_spec,
    robosuite_assets,
    set_physics_options,
)

__all__ = [
    "TIAGO_ARM_JOINTS",
    "TIAGO_BASE_JOINTS",
    "TIAGO_EE_SITE",
    "TIAGO_ELBOW_SITE",
    "TIAGO_HOME",
    "TIAGO_JOINTS",
    "TiagoScene",
    "build_tiago_kinematics",
    "build_tiago_scene",
]

#: Planar base joints added on robosuite's ``base`` body: x and y slides along the world axes [m],
#: then a yaw hinge about the vertical axis through the base centre [rad].
TIAGO_BASE_JOINTS = ("base_x", "base_y", "base_yaw")
#: The manipulation chain: torso lift [m] and robosuite's six right-arm joints [rad]. robosuite's
#: TIAGo arm has six joints (PAL's seventh wrist joint is not modelled), so with the torso the
#: chain from the base to the hand has 7 DoF, as on the real robot.
TIAGO_ARM_JOINTS = (
    "torso_lift_joint",
    "arm_right_1_joint",
    "arm_right_2_joint",
    "arm_right_3_joint",
    "arm_right_4_joint",
    "arm_right_5_joint",
    "arm_right_6_joint",
)
#: All controlled joints, in the order of ``q`` everywhere in telerig: base then arm. Length 10.
TIAGO_JOINTS = TIAGO_BASE_JOINTS + TIAGO_ARM_JOINTS
_GRIPPER_PREFIX = "gripper/"
#: Grasp-point site of the Robotiq 2F-85 on the right hand; z points out of the gripper.
TIAGO_EE_SITE = "gripper/grip_site"
#: Site at the right elbow (origin of ``arm_right_4_link``, the elbow joint).
TIAGO_ELBOW_SITE = "right_elbow"
#: Home configuration, order of :data:`TIAGO_JOINTS`: base at the origin facing +x, torso 0.15 m up,
#: the right hand in front of the body at table height with the gripper pointing forward.
TIAGO_HOME = (0.0, 0.0, 0.0, 0.15, 0.68, -0.53, 1.54, 1.62, -1.04, -0.74)

# Joints robosuite models that telerig does not control, welded at these angles [rad]: the left
# arm tucked against the body, the head looking down at the table in front.
_FROZEN = {
    "head_1_joint": 0.0,
    "head_2_joint": -0.6,
    "arm_left_1_joint": 0.0,
    "arm_left_2_joint": -0.9,
    "arm_left_3_joint": 1.45,
    "arm_left_4_joint": 1.7,
    "arm_left_5_joint": -1.5,
    "arm_left_6_joint": 0.5,
}

# Speed limits: PAL's TIAGo URDF (torso 0.07 m/s, arm joints 1.95 / 2.35 / 1.76 rad/s for the
# joints robosuite keeps) and a holonomic base at 1 m/s and 1.5 rad/s (robosuite's null mobile base
# ctrlrange). PAL publishes no acceleration limits; these are conservative teleoperation values.
_VELOCITY = (1.0, 1.0, 1.5, 0.07, 1.95, 1.95, 2.35, 2.35, 1.95, 1.76)
_ACCELERATION = (1.0, 1.0, 2.0, 0.5, 6.0, 6.0, 6.0, 6.0, 8.0, 8.0)

# Position servos of the torso [N/m, N s/m] and arm joints [N m/rad, N m s/rad], on top of the
# joint damping robosuite sets (10..100 N m s/rad, 1000 N s/m on the torso). Force limits are
# robosuite's motor ranges (50 N m shoulder, 15 N m wrist, 1000 N torso).
_ARM_KP = (30000.0, 3000.0, 3000.0, 1500.0, 1500.0, 500.0, 500.0)
_ARM_KV = (2000.0, 150.0, 100.0, 60.0, 60.0, 15.0, 15.0)
_ARM_FORCE = (1000.0, 50.0, 50.0, 15.0, 15.0, 15.0, 15.0)
_ARM_ARMATURE = 0.05  # reflected rotor inertia [kg m^2]
# Base velocity servos [N s/m, N m s/rad] and their force limits [N, N m] (robosuite's 600).
_BASE_KV = (3000.0, 3000.0, 600.0)
_BASE_FORCE = (600.0, 600.0, 600.0)

_TIMESTEP = 0.002  # [s]
# Table in front of the robot (top at scene.TABLE_TOP = 0.8 m): centre x and half sizes [m].
_TABLE_CENTER_X = 1.05
_TABLE_HALF = (0.3, 0.5)
_CUP_RADIUS = 0.035  # [m]
_CUP_HALF_HEIGHT = 0.05  # [m]
_CUP_XY = (0.85, -0.2)  # [m], world frame


@dataclass(frozen=True, slots=True)
class TiagoScene:
    """A compiled TIAGo model and the names a controller or driver needs.

    Attributes:
        model: The compiled MuJoCo model.
        joints: Controlled joints, base then arm (:data:`TIAGO_JOINTS`). Length 10.
        base_joints: Planar base joints x [m], y [m] (world axes) and yaw [rad]. Length 3.
        arm_joints: Torso lift [m] and right-arm joints [rad]. Length 7.
        arm_actuators: Position servos of ``arm_joints`` (ctrl = target [m] or [rad]); empty in
            kinematic models.
        base_actuators: Velocity servos of ``base_joints`` (ctrl = joint velocity: world-frame
            x/y [m/s], yaw rate [rad/s]); empty in kinematic models.
        gripper_actuators: Finger position servos, ctrl 0 = open, 0.8 = closed [rad]; empty in
            kinematic models.
        gripper_joints: Finger joints driven by ``gripper_actuators``.
        gripper_open: ``gripper_actuators`` targets of the open gripper [rad]. Shape (2,) or (0,).
        gripper_closed: ``gripper_actuators`` targets of the closed gripper [rad]. Same shape.
        ee_site: Grasp-point site of the gripper.
        elbow_site: Site at the right elbow.
        base_body: The mobile base body; its frame is x forward, y left, z up, at floor level.
        cameras: Camera names, scene camera first.
        home: Home configuration, order of ``joints``. Shape (10,).
        limits: Position, velocity and acceleration limits of ``joints``; base x/y/yaw have
            infinite position limits.
        objects: Free bodies on the table (``cup``); empty in kinematic models.
        visual_groups: Geom groups a camera should draw.
    """

    model: mujoco.MjModel
    joints: tuple[str, ...]
    base_joints: tuple[str, ...]
    arm_joints: tuple[str, ...]
    arm_actuators: tuple[str, ...]
    base_actuators: tuple[str, ...]
    gripper_actuators: tuple[str, ...]
    gripper_joints: tuple[str, ...]
    gripper_open: FloatArray
    gripper_closed: FloatArray
    ee_site: str
    elbow_site: str
    base_body: str
    cameras: tuple[str, ...]
    home: FloatArray
    limits: JointLimits
    objects: tuple[str, ...] = ()
    visual_groups: tuple[int, ...] = VISUAL_GROUPS

    def qpos_indices(self) -> np.ndarray[tuple[int], np.dtype[np.intp]]:
        """Addresses of ``joints`` in ``MjData.qpos`` (and ``qvel``: all are 1-DoF). Shape (10,)."""
        return np.array([self.model.joint(j).qposadr[0] for j in self.joints], dtype=np.intp)

    def dof_indices(self) -> np.ndarray[tuple[int], np.dtype[np.intp]]:
        """Addresses of ``joints`` in ``MjData.qvel``. Shape (10,)."""
        return np.array([self.model.joint(j).dofadr[0] for j in self.joints], dtype=np.intp)


def _quat_mul(a: FloatArray, b: FloatArray) -> FloatArray:
    out = np.empty(4)
    mujoco.mju_mulQuat(out, a, b)
    return out


def _freeze_joints(spec: mujoco.MjSpec, angles: dict[str, float]) -> None:
    """Delete hinge joints, baking each angle into its body's orientation (about the joint anchor)."""
    resolved = spec.copy().compile()  # body orientations as the compiler resolves them (euler etc.)
    for name, angle in angles.items():
        joint = spec.joint(name)
        if joint is None:
            raise RobotError(f"joint '{name}' not found in the TIAGo model")
        body = joint.parent
        axis = np.asarray(joint.axis, dtype=np.float64)
        axis = axis / np.linalg.norm(axis)
        turn = np.empty(4)
        mujoco.mju_axisAngle2Quat(turn, axis, angle)
        quat = resolved.body(body.name).quat.copy()
        anchor = np.asarray(joint.pos, dtype=np.float64)
        rotated = np.empty(3)
        mujoco.mju_rotVecQuat(rotated, anchor, turn)
        # Rotating about the anchor p moves the body origin by R (p - Rot p) in the parent frame.
        offset = np.empty(3)
        mujoco.mju_rotVecQuat(offset, anchor - rotated, quat)
        body.pos = resolved.body(body.name).pos + offset
        body.alt.type = mujoco.mjtOrientation.mjORIENTATION_QUAT
        body.quat = _quat_mul(quat, turn)
        spec.delete(joint)


def _build_robot(*, kinematic: bool) -> mujoco.MjSpec:
    spec = load_spec(robosuite_assets() / "robots" / "tiago" / "robot.xml")
    spec.modelname = "tiago_robotiq85"
    set_physics_options(spec, _TIMESTEP)
    for actuator in list(spec.actuators):  # torque motors, replaced by servos below
        spec.delete(actuator)
    for site in spec.sites:  # robosuite's debug markers, hidden from cameras (group 4)
        site.group = 4
    for name in ("base", "right_hand", "arm_right_4_link", "torso_lift_link"):
        if spec.body(name) is None:
            raise RobotError(f"body '{name}' not found in the TIAGo model")
    _freeze_joints(spec, _FROZEN)

    base = spec.body("base")
    base.add_joint(name="base_x", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=[1, 0, 0])
    base.add_joint(name="base_y", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=[0, 1, 0])
    base.add_joint(name="base_yaw", type=mujoco.mjtJoint.mjJNT_HINGE, axis=[0, 0, 1])
    spec.body("arm_right_4_link").add_site(name=TIAGO_ELBOW_SITE, size=[0.02, 0, 0], group=4)
    gripper = load_gripper(ROBOTIQ_2F85, actuated=not kinematic)
    frame = spec.body("right_hand").add_frame()
    frame.attach_body(gripper.body(ROBOTIQ_2F85.root_body), _GRIPPER_PREFIX, "")
    for name in TIAGO_ARM_JOINTS:
        spec.joint(name).armature = _ARM_ARMATURE
    if kinematic:
        return spec

    # Everything the torso carries is gravity-compensated, as PAL's controllers do.
    for body in spec.body("torso_lift_link").find_all(mujoco.mjtObj.mjOBJ_BODY):
        body.gravcomp = 1.0
    spec.body("torso_lift_link").gravcomp = 1.0
    for name, kp, kv, force in zip(TIAGO_ARM_JOINTS, _ARM_KP, _ARM_KV, _ARM_FORCE, strict=True):
        joint = spec.joint(name)
        act = spec.add_actuator(
            name=f"{name}_pos",
            target=name,
            trntype=mujoco.mjtTrn.mjTRN_JOINT,
            ctrlrange=[float(joint.range[0]), float(joint.range[1])],
            forcerange=[-force, force],
        )
        act.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
        act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
        act.set_to_position(kp=kp, kv=kv)
    for name, kv, force, vmax in zip(TIAGO_BASE_JOINTS, _BASE_KV, _BASE_FORCE, _VELOCITY[:3], strict=True):
        act = spec.add_actuator(
            name=f"{name}_vel",
            target=name,
            trntype=mujoco.mjtTrn.mjTRN_JOINT,
            ctrlrange=[-vmax, vmax],
            forcerange=[-force, force],
        )
        act.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
        act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
        act.set_to_velocity(kv=kv)
    actuate_gripper(spec, ROBOTIQ_2F85, _GRIPPER_PREFIX)
    # The base rides on its planar joints at a fixed height: wheel and caster contacts with the
    # floor would only add friction against the velocity servos.
    for body in spec.body("base_link").find_all(mujoco.mjtObj.mjOBJ_BODY):
        if "wheel" in body.name or "caster" in body.name:
            spec.add_exclude(bodyname1="world", bodyname2=body.name)
    spec.add_exclude(bodyname1="world", bodyname2="base_link")
    return spec


def _add_world(spec: mujoco.MjSpec, *, with_cup: bool) -> tuple[str, ...]:
    add_room(spec)
    add_table(spec, (_TABLE_CENTER_X, 0.0), _TABLE_HALF)
    bodies: tuple[str, ...] = ()
    if with_cup:
        cup = spec.worldbody.add_body(name="cup", pos=[*_CUP_XY, TABLE_TOP + _CUP_HALF_HEIGHT])
        cup.add_freejoint(name="cup_free")
        cup.add_geom(
            name="cup",
            type=mujoco.mjtGeom.mjGEOM_CYLINDER,
            size=[_CUP_RADIUS, _CUP_HALF_HEIGHT, 0],
            mass=0.1,
            rgba=[0.9, 0.9, 0.95, 1.0],
            group=VISUAL_GROUPS[1],
            condim=4,
            friction=[1.5, 0.01, 0.001],
        )
        bodies = ("cup",)
    # Looks from the front-right at the robot, table and cup.
    spec.worldbody.add_camera(
        name="scene", pos=[2.6, -1.9, 2.0], xyaxes=[0.6, 0.8, 0.0, -0.35, 0.26, 0.9], fovy=50
    )
    return bodies


def build_tiago_scene(*, with_cup: bool = True, timestep: float = _TIMESTEP) -> TiagoScene:
    """Build the TIAGo physics scene: the robot at the world origin facing +x, a table in front.

    The torso and arm have position servos (ctrl = target [m] or [rad], clipped to the joint
    range) with gravity compensation; the base joints have velocity servos (ctrl = world-frame
    x/y velocity [m/s] and yaw rate [rad/s]); the fingers have position servos (0 open .. 0.8
    closed [rad]). The base rides at a fixed height, colliding with the table but not the floor.
    The left arm and head are rigid. World z is up; the table top is 0.75 m high, its near edge
    0.75 m in front of the base centre.

    Args:
        with_cup: Add a free cup (cylinder, 7 cm wide, 10 cm tall; body ``cup``) on the table.
        timestep: Physics timestep [s]; the servos are tuned for 0.002 s.

    Raises:
        DependencyError: robosuite (the model source) is not installed.
        RobotError: a model file is missing or does not compile.
    """
    if not 0 < timestep <= 0.005:
        raise ValueError(
            f"timestep must be in (0, 0.005] s for the TIAGo servos to be stable, got {timestep}"
        )
    spec = _build_robot(kinematic=False)
    spec.option.timestep = timestep
    bodies = _add_world(spec, with_cup=with_cup)
    return _scene(compile_spec(spec), kinematic=False, objects=bodies)


def build_tiago_kinematics() -> TiagoScene:
    """Build the kinematic model for control: exactly the 10 controlled joints, rigid gripper, no world.

    ``qpos`` of this model is ``q`` in :data:`TIAGO_JOINTS` order (``nq == nv == 10``), and every
    site and body is where it is in :func:`build_tiago_scene` for the same ``q``.

    Raises:
        DependencyError: robosuite (the model source) is not installed.
        RobotError: a model file is missing or does not compile.
    """
    return _scene(compile_spec(_build_robot(kinematic=True)), kinematic=True)


def _frozen(values: tuple[float, ...]) -> FloatArray:
    arr = np.array(values, dtype=np.float64)
    arr.flags.writeable = False
    return arr


def _scene(model: mujoco.MjModel, *, kinematic: bool, objects: tuple[str, ...] = ()) -> TiagoScene:
    cameras = tuple(model.camera(i).name for i in range(model.ncam))
    lower = np.full(len(TIAGO_JOINTS), -np.inf)
    upper = np.full(len(TIAGO_JOINTS), np.inf)
    for i, name in enumerate(TIAGO_JOINTS):
        jid = model.joint(name).id
        if model.jnt_limited[jid]:
            lower[i], upper[i] = model.jnt_range[jid]
    limits = JointLimits(
        names=TIAGO_JOINTS,
        lower=lower,
        upper=upper,
        velocity=np.array(_VELOCITY),
        acceleration=np.array(_ACCELERATION),
    )
    gripper = ROBOTIQ_2F85
    return TiagoScene(
        model=model,
        joints=TIAGO_JOINTS,
        base_joints=TIAGO_BASE_JOINTS,
        arm_joints=TIAGO_ARM_JOINTS,
        arm_actuators=() if kinematic else tuple(f"{j}_pos" for j in TIAGO_ARM_JOINTS),
        base_actuators=() if kinematic else tuple(f"{j}_vel" for j in TIAGO_BASE_JOINTS),
        gripper_actuators=() if kinematic else tuple(_GRIPPER_PREFIX + a for a in gripper.actuators),
        gripper_joints=() if kinematic else tuple(_GRIPPER_PREFIX + j for j in gripper.joints),
        gripper_open=_frozen(() if kinematic else gripper.open_ctrl),
        gripper_closed=_frozen(() if kinematic else gripper.closed_ctrl),
        ee_site=TIAGO_EE_SITE,
        elbow_site=TIAGO_ELBOW_SITE,
        base_body="base",
        cameras=tuple(sorted(cameras, key=lambda c: c != "scene")),
        home=_frozen(TIAGO_HOME),
        limits=limits,
        objects=objects,
    )
