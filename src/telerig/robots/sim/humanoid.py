"""Unitree G1 humanoid (robosuite-models MJCF) for upper-body teleoperation: scene, IK model and driver."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Literal

import mujoco
import numpy as np

from telerig.errors import RobotError
from telerig.ir.types import FloatArray
from telerig.robots.sim import objects
from telerig.robots.sim.arm import MujocoArm
from telerig.robots.sim.scene import (
    TABLE_TOP,
    ArmScene,
    add_room,
    add_table,
    compile_spec,
    load_spec,
    register_sim_scene,
    robosuite_models_assets,
    set_physics_options,
)

__all__ = [
    "HUMANOID_ACCELERATION_LIMIT",
    "HUMANOID_HOME",
    "HUMANOID_SITES",
    "HUMANOID_VELOCITY_LIMIT",
    "LEFT_ARM_JOINTS",
    "LEG_JOINTS",
    "RIGHT_ARM_JOINTS",
    "UPPER_BODY_JOINTS",
    "WAIST_JOINTS",
    "HumanoidScene",
    "MujocoHumanoid",
    "Support",
    "build_humanoid_kinematics",
    "build_humanoid_scene",
    "humanoid_arm_scene",
]

_log = logging.getLogger(__name__)

#: How the lower body is held: ``"fixed"`` bolts the pelvis to a stand (no free joint; simplest and
#: exactly repeatable); ``"harness"`` keeps the floating base and holds the pelvis with a soft weld
#: constraint, like a gantry harness, so the pelvis pose is a simulated state that can sag or sway.
Support = Literal["fixed", "harness"]

#: Waist joints (the robosuite G1 has waist yaw only).
WAIST_JOINTS = ("torso_joint",)
#: Right arm joints, shoulder to hand.
RIGHT_ARM_JOINTS = (
    "r_shoulder_pitch_joint",
    "r_shoulder_roll_joint",
    "r_shoulder_yaw_joint",
    "r_elbow_pitch_joint",
    "r_elbow_roll_joint",
)
#: Left arm joints, shoulder to hand.
LEFT_ARM_JOINTS = (
    "l_shoulder_pitch_joint",
    "l_shoulder_roll_joint",
    "l_shoulder_yaw_joint",
    "l_elbow_pitch_joint",
    "l_elbow_roll_joint",
)
#: Joints the driver commands and the IK solves for: waist, right arm, left arm. Length 11.
UPPER_BODY_JOINTS = WAIST_JOINTS + RIGHT_ARM_JOINTS + LEFT_ARM_JOINTS
#: Leg joints, held at the stance posture (all zero: knees slightly bent, feet flat).
LEG_JOINTS = tuple(
    f"{side}_leg_{name}_joint"
    for side in ("l", "r")
    for name in ("hip_pitch", "hip_roll", "hip_yaw", "knee", "ankle_pitch", "ankle_roll")
)
#: Home upper-body posture [rad], :data:`UPPER_BODY_JOINTS` order: waist straight, upper arms down
#: and slightly out, elbows bent about 70 degrees so the hands are in front of the belly.
HUMANOID_HOME = (0.0, 0.0, -0.15, 0.0, 0.35, 0.0, 0.0, 0.15, 0.0, 0.35, 0.0)

#: Anatomical sites the retargeter targets, by role: the shoulder centre (where the shoulder pitch
#: and roll axes meet), the elbow (on the elbow axis) and the wrist (hand mount) of each arm, and
#: the torso frame (on the torso link, at shoulder height; x forward, y left, z up at home).
HUMANOID_SITES = {
    "torso": "torso",
    "right_shoulder": "right_shoulder",
    "right_elbow": "right_elbow",
    "right_wrist": "right_wrist",
    "left_shoulder": "left_shoulder",
    "left_elbow": "left_elbow",
    "left_wrist": "left_wrist",
}
_SITE_PLACES = {  # site -> (body, position in the body [m])
    "torso": ("torso_link", (0.0, 0.0, 0.26)),
    # The shoulder roll axis meets the pitch axis here, so the point is fixed in the torso.
    "right_shoulder": ("r_shoulder_pitch_link", (0.0, -0.052, 0.0)),
    "left_shoulder": ("l_shoulder_pitch_link", (0.0, 0.052, 0.0)),
    "right_elbow": ("r_elbow_pitch_link", (0.0, 0.0, 0.0)),
    "left_elbow": ("l_elbow_pitch_link", (0.0, 0.0, 0.0)),
    "right_wrist": ("right_eef", (0.0, 0.0, 0.0)),
    "left_wrist": ("left_eef", (0.0, 0.0, 0.0)),
}

#: Upper-body joint speed limit for teleoperation [rad/s]. Unitree publishes motor speeds well
#: above this; 3 rad/s is a conservative value that still follows a brisk human reach.
HUMANOID_VELOCITY_LIMIT = 3.0
#: Upper-body joint acceleration limit [rad/s^2]. A brisk human reach (0.6 m in 1.2 s, the shipped
#: BVH clip) needs about 30 rad/s^2 at the shoulder and elbow; 40 lets the arms follow it, well
#: below what the 25 N m arm motors give the light G1 arm (> 100 rad/s^2).
HUMANOID_ACCELERATION_LIMIT = 40.0

_TIMESTEP = 0.002  # [s]
_ARMATURE = 0.05  # reflected rotor inertia [kg m^2] of every upper-body joint
# Position servo stiffness [N m/rad] and damping [N m s/rad], about critically damped for the
# link inertias at home plus armature; force limits [N m] from the G1 datasheet (waist 88,
# arm joints 25, rounded down).
_SERVO = {
    "torso_joint": (1000.0, 60.0, 88.0),
    "shoulder_pitch": (300.0, 12.0, 25.0),
    "shoulder_roll": (300.0, 12.0, 25.0),
    "shoulder_yaw": (200.0, 6.0, 25.0),
    "elbow_pitch": (200.0, 6.0, 25.0),
    "elbow_roll": (100.0, 3.0, 25.0),
}
# Leg joints are held at the stance by a stiff spring-damper (the position loop of a standing
# controller, without a commanded interface: the lower body is not teleoperated).
_LEG_STIFFNESS = 500.0  # [N m/rad]
_LEG_DAMPING = 20.0  # [N m s/rad]
_HARNESS_SOLREF = (0.02, 1.0)  # soft weld: time constant [s], damping ratio
_TABLE_CENTER = (0.5, 0.0)  # table in front of the robot, near edge 0.25 m from the pelvis [m]
_TABLE_HALF = (0.25, 0.5)  # [m]
_CUBE_XY = (0.35, -0.15)  # [m], in reach of the right hand


@dataclass(frozen=True, slots=True)
class HumanoidScene:
    """A compiled humanoid model and the names a driver or IK solver needs.

    Attributes:
        model: The compiled MuJoCo model.
        joints: Commanded upper-body joints, :data:`UPPER_BODY_JOINTS`. Length 11.
        actuators: Position actuators of ``joints``, same order; empty in kinematic models.
        sites: Anatomical sites by role (see :data:`HUMANOID_SITES`).
        pelvis_body: The pelvis body; in kinematic models its frame is the world frame's origin
            shifted up by the standing pelvis height (robot x forward, y left, z up).
        support: How the lower body is held (see :data:`Support`); ``"fixed"`` in kinematic models.
        cameras: Camera names, scene camera first.
        home: Home configuration of ``joints`` [rad]. Shape (11,).
        objects: Free bodies of the task object set (the cube on the table).
    """

    model: mujoco.MjModel
    joints: tuple[str, ...]
    actuators: tuple[str, ...]
    sites: dict[str, str]
    pelvis_body: str
    support: Support
    cameras: tuple[str, ...]
    home: FloatArray
    objects: tuple[str, ...] = ()


def _joint_kind(name: str) -> str:
    if name in WAIST_JOINTS:
        return name
    return name[2:].removesuffix("_joint")  # "r_shoulder_pitch_joint" -> "shoulder_pitch"


def _build_g1(*, kinematic: bool, support: Support, timestep: float) -> mujoco.MjSpec:
    spec = load_spec(robosuite_models_assets() / "robots" / "g1" / "robot.xml")
    spec.modelname = "g1_upper_body"
    set_physics_options(spec, timestep)
    for actuator in list(spec.actuators):  # torque motors, replaced by position servos below
        spec.delete(actuator)
    for sensor in list(spec.sensors):  # IMU on the torso, not needed here
        spec.delete(sensor)
    joints = {j.name: j for j in spec.joints}
    for name in (*UPPER_BODY_JOINTS, *LEG_JOINTS):
        if name not in joints:
            raise RobotError(f"joint '{name}' not found in the G1 model. Available: {', '.join(joints)}")
    for site, (body, pos) in _SITE_PLACES.items():
        found = spec.body(body)
        if found is None:
            raise RobotError(f"body '{body}' not found in the G1 model")
        found.add_site(name=site, pos=list(pos), size=[0.01, 0.0, 0.0], group=4)
    free = [j for j in spec.joints if j.type == mujoco.mjtJoint.mjJNT_FREE]
    if kinematic or support == "fixed":
        for joint in free:
            spec.delete(joint)
    if kinematic:
        # The IK moves the upper body only: the legs are rigid at the stance posture.
        for name in LEG_JOINTS:
            spec.delete(spec.joint(name))
        return spec

    # With the pelvis fixed, MuJoCo's parent-child contact filter no longer covers the waist (its
    # parent is welded to the world); its meshes overlap, so the pair is excluded explicitly.
    spec.add_exclude(bodyname1="pelvis", bodyname2="torso_link")
    # The upper body's weight is compensated as a passive force, as the robot's controller does with
    # joint torques; the pelvis and legs keep theirs, carried by the leg springs and the support.
    torso = spec.body("torso_link")
    for body in (torso, *torso.find_all(mujoco.mjtObj.mjOBJ_BODY)):
        body.gravcomp = 1.0
    for name in LEG_JOINTS:
        joint = spec.joint(name)
        joint.stiffness = [_LEG_STIFFNESS, 0.0, 0.0]
        joint.springref = 0.0
        joint.damping = [_LEG_DAMPING, 0.0, 0.0]
    for name in UPPER_BODY_JOINTS:
        joint = spec.joint(name)
        joint.armature = _ARMATURE
        joint.damping = [0.5, 0.0, 0.0]
        joint.frictionloss = 0.0
        kp, kv, force = _SERVO[_joint_kind(name)]
        lo, hi = float(joint.range[0]), float(joint.range[1])
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
    if support == "harness":
        weld = spec.add_equality(
            type=mujoco.mjtEq.mjEQ_WELD, name1="pelvis", objtype=mujoco.mjtObj.mjOBJ_BODY, name="harness"
        )
        # Zero relative quaternion: the weld holds the pose the pelvis has at qpos0.
        weld.data[:] = [0.0] * 10 + [1.0, 0.0]
        weld.solref = list(_HARNESS_SOLREF)
    return spec


def _add_world(spec: mujoco.MjSpec) -> tuple[str, ...]:
    add_room(spec)
    add_table(spec, _TABLE_CENTER, _TABLE_HALF)
    cube = objects.add_cube(spec, "cube", (*_CUBE_XY, TABLE_TOP))
    # Looks at the robot from the front-left, over the table.
    spec.worldbody.add_camera(
        name="scene", pos=[2.0, 1.0, 1.6], xyaxes=[-0.45, 0.89, 0.0, -0.3, -0.15, 0.94], fovy=50
    )
    return (cube,)


def build_humanoid_scene(*, support: Support = "fixed", timestep: float = _TIMESTEP) -> HumanoidScene:
    """The G1 standing at a table with a cube, upper body position-servoed, lower body held.

    Upper-body joints get position servos (ctrl = target [rad], limited to the joint range) and
    gravity compensation; the legs are held at the stance by stiff joint springs and, like the
    pelvis, keep their weight, which the support carries. The pelvis stands at 0.755 m with the
    feet a few millimetres above the floor; a 0.8 m table with a cube stands in front (x > 0.25 m).

    Args:
        support: How the lower body is held (see :data:`Support`).
        timestep: Physics step [s].

    Raises:
        DependencyError: robosuite-models is not installed.
        RobotError: the model file is missing or lacks a joint or body used here.
    """
    if support not in ("fixed", "harness"):
        raise ValueError(f"support must be 'fixed' or 'harness', got {support!r}")
    if not 0 < timestep <= 0.01:
        raise ValueError(f"timestep must be in (0, 0.01] s, got {timestep}")
    spec = _build_g1(kinematic=False, support=support, timestep=timestep)
    bodies = _add_world(spec)
    return _scene(compile_spec(spec), support, actuated=True, objects=bodies)


def build_humanoid_kinematics() -> HumanoidScene:
    """Kinematics-only G1 for IK: pelvis fixed, legs rigid, the 11 upper-body joints free.

    The pelvis stands where it does in :func:`build_humanoid_scene`, so world coordinates match.
    """
    spec = _build_g1(kinematic=True, support="fixed", timestep=_TIMESTEP)
    return _scene(compile_spec(spec), "fixed", actuated=False)


def _scene(
    model: mujoco.MjModel, support: Support, *, actuated: bool, objects: tuple[str, ...] = ()
) -> HumanoidScene:
    return HumanoidScene(
        model=model,
        joints=UPPER_BODY_JOINTS,
        actuators=tuple(f"{j}_pos" for j in UPPER_BODY_JOINTS) if actuated else (),
        sites=dict(HUMANOID_SITES),
        pelvis_body="pelvis",
        support=support,
        cameras=tuple(model.camera(i).name for i in range(model.ncam)),
        home=_readonly(np.array(HUMANOID_HOME)),
        objects=objects,
    )


def humanoid_arm_scene(scene: HumanoidScene) -> ArmScene:
    """``scene`` as a generic position-servoed robot without gripper: what :class:`MujocoArm` drives."""
    n = len(scene.joints)
    return ArmScene(
        model=scene.model,
        arm_joints=scene.joints,
        arm_actuators=scene.actuators,
        gripper_actuators=(),
        gripper_joints=(),
        ee_site=scene.sites["right_wrist"],
        base_body=scene.pelvis_body,
        cameras=scene.cameras,
        home=scene.home,
        velocity_limit=_readonly(np.full(n, HUMANOID_VELOCITY_LIMIT)),
        acceleration_limit=_readonly(np.full(n, HUMANOID_ACCELERATION_LIMIT)),
        gripper_open=_readonly(np.zeros(0)),
        gripper_closed=_readonly(np.zeros(0)),
        objects=scene.objects,
    )


def _readonly(arr: FloatArray) -> FloatArray:
    arr.flags.writeable = False
    return arr


class MujocoHumanoid(MujocoArm):
    """A simulated Unitree G1 whose upper body (waist + two 5-DoF arms) is teleoperated.

    Implements :class:`~telerig.robots.base.RobotDriver` for :data:`UPPER_BODY_JOINTS`
    (``send`` sets position targets [rad], clipped to the joint ranges); the real-time physics
    thread, stamping, e-stop and stepping are :class:`MujocoArm`'s. The robosuite G1 has no
    hands: :attr:`has_gripper` is False and :meth:`send_gripper` refuses (``RobotError``).
    """

    def __init__(
        self,
        scene: HumanoidScene | None = None,
        *,
        name: str = "g1_sim",
        realtime: bool = True,
        max_catchup: int = 25,
    ) -> None:
        """Create the driver (the physics starts on :meth:`connect`).

        Args:
            scene: Scene to simulate; :func:`build_humanoid_scene` when None.
            name: Driver name; the ``source_id`` of every stamp it produces.
            realtime: Step on a thread paced to the wall clock; False for :meth:`step`.
            max_catchup: Most steps the loop may run late before it drops the lag. >= 1.

        Raises:
            RobotError: the scene has no actuators (a kinematic model).
        """
        humanoid = scene if scene is not None else build_humanoid_scene()
        if not humanoid.actuators:
            raise RobotError("scene has no actuators (a kinematic model?); use build_humanoid_scene()")
        super().__init__(humanoid_arm_scene(humanoid), name=name, realtime=realtime, max_catchup=max_catchup)
        self._humanoid = humanoid
        self._pelvis = humanoid.model.body(humanoid.pelvis_body).id

    @property
    def humanoid(self) -> HumanoidScene:
        """The simulated humanoid scene (model, names, support)."""
        return self._humanoid

    def pelvis_pose(self) -> tuple[FloatArray, FloatArray]:
        """Pelvis position [m] (shape (3,)) and orientation (w, x, y, z) (shape (4,)), world frame.

        Raises:
            RobotError: the driver is not connected.
        """
        self._require_connected()
        with self.locked() as (_, data):
            return data.xpos[self._pelvis].copy(), data.xquat[self._pelvis].copy()


@register_sim_scene("g1_humanoid")
def _g1() -> MujocoHumanoid:
    return MujocoHumanoid(build_humanoid_scene(), name="g1_sim", realtime=False)
