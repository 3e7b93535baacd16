"""TIAGo mobile manipulator (robosuite MJCF, holonomic base, Robotiq 2F-85): joints, limits, kinematics."""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from telerig.errors import RobotError
from telerig.ir.types import FloatArray
from telerig.robots.base import JointLimits
from telerig.robots.models.arm import GRIPPER_PREFIX, load_gripper
from telerig.robots.models.arms import ROBOTIQ_2F85
from telerig.robots.models.mjcf import (
    VISUAL_GROUPS,
    compile_kinematic,
    compile_spec,
    load_spec,
    robosuite_assets,
    set_physics_options,
)

__all__ = [
    "TIAGO_ACCELERATION",
    "TIAGO_ARM_JOINTS",
    "TIAGO_BASE_JOINTS",
    "TIAGO_EE_SITE",
    "TIAGO_ELBOW_SITE",
    "TIAGO_HOME",
    "TIAGO_JOINTS",
    "TIAGO_VELOCITY",
    "TiagoScene",
    "build_tiago_kinematics",
    "load_tiago",
    "tiago_scene",
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
_GRIPPER_PREFIX = GRIPPER_PREFIX
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
TIAGO_VELOCITY = (1.0, 1.0, 1.5, 0.07, 1.95, 1.95, 2.35, 2.35, 1.95, 1.76)
TIAGO_ACCELERATION = (1.0, 1.0, 2.0, 0.5, 6.0, 6.0, 6.0, 6.0, 8.0, 8.0)

_ARM_ARMATURE = 0.05  # reflected rotor inertia [kg m^2]
_TIMESTEP = 0.002  # [s]


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


def load_tiago(*, kinematic: bool) -> mujoco.MjSpec:
    """The TIAGo MJCF with planar base joints, the elbow site and the gripper, without actuators.

    The left arm and head are welded (:data:`_FROZEN`); the gripper is rigid if ``kinematic``.

    Raises:
        DependencyError: robosuite (the model source) is not installed.
        RobotError: the model file is missing or lacks a body or joint used here.
    """
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
    return spec


def build_tiago_kinematics(*, drawn: bool = False) -> TiagoScene:
    """Build the kinematic model for control: exactly the 10 controlled joints, rigid gripper, no world.

    ``qpos`` of this model is ``q`` in :data:`TIAGO_JOINTS` order (``nq == nv == 10``), and every
    site and body is where it is in :func:`telerig.robots.sim.tiago.build_tiago_scene` for the same ``q``.
    With ``drawn`` it keeps the geoms only a camera draws (for whoever draws it, e.g. the web scene);
    without them it builds in a fraction of the time (:func:`~telerig.robots.models.mjcf.compile_kinematic`).

    Raises:
        DependencyError: robosuite (the model source) is not installed.
        RobotError: a model file is missing or does not compile.
    """
    spec = load_tiago(kinematic=True)
    return tiago_scene(compile_spec(spec) if drawn else compile_kinematic(spec), kinematic=True)


def _frozen(values: tuple[float, ...]) -> FloatArray:
    arr = np.array(values, dtype=np.float64)
    arr.flags.writeable = False
    return arr


def tiago_scene(model: mujoco.MjModel, *, kinematic: bool, objects: tuple[str, ...] = ()) -> TiagoScene:
    """The :class:`TiagoScene` of a compiled TIAGo ``model`` (kinematic, or a simulated scene)."""
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
        velocity=np.array(TIAGO_VELOCITY),
        acceleration=np.array(TIAGO_ACCELERATION),
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
