"""Simulated Unitree G1 (29 DoF, example-robot-data's URDF) for upper-body teleoperation: scene and driver.

The model itself (joints, home, limits, sites, kinematic model) is :mod:`telerig.robots.models.g1`,
shared with the IK and the real G1 driver (same joint names, order and limits).
"""

from __future__ import annotations

import logging

import mujoco
import numpy as np

from telerig.errors import RobotError
from telerig.ir.types import FloatArray, Pose
from telerig.robots.models.arm import ArmScene
from telerig.robots.models.g1 import (
    G1_PELVIS_HEIGHT,
    HUMANOID_ACCELERATION_LIMIT,
    HUMANOID_VELOCITY_LIMIT,
    LEG_JOINTS,
    UPPER_BODY_JOINTS,
    WAIST_JOINTS,
    HumanoidScene,
    Support,
    humanoid_scene,
    load_g1,
)
from telerig.robots.models.mjcf import compile_spec
from telerig.robots.sim import objects
from telerig.robots.sim.arm import MujocoArm
from telerig.robots.sim.scene import TABLE_TOP, add_room, add_table

__all__ = [
    "MujocoHumanoid",
    "build_humanoid_scene",
    "humanoid_arm_scene",
]

_TIMESTEP = 0.002  # [s]
_log = logging.getLogger(__name__)

_ARMATURE = 0.05  # reflected rotor inertia [kg m^2] of every upper-body joint
# Position servo stiffness [N m/rad] and damping [N m s/rad], about critically damped for the
# link inertias at home plus armature; force limits [N m] from the G1 datasheet (waist 88,
# arm joints 25, rounded down; the URDF's efforts: waist roll/pitch 35, wrist pitch/yaw 5).
_SERVO = {
    "waist_yaw_joint": (1000.0, 60.0, 88.0),
    "waist_roll_joint": (1000.0, 60.0, 35.0),
    "waist_pitch_joint": (1000.0, 60.0, 35.0),
    "shoulder_pitch": (300.0, 12.0, 25.0),
    "shoulder_roll": (300.0, 12.0, 25.0),
    "shoulder_yaw": (200.0, 6.0, 25.0),
    "elbow": (200.0, 6.0, 25.0),
    "wrist_roll": (100.0, 3.0, 25.0),
    "wrist_pitch": (50.0, 3.0, 5.0),
    "wrist_yaw": (50.0, 3.0, 5.0),
}
# Leg joints are held at the stance by a stiff spring-damper (the position loop of a standing
# controller, without a commanded interface: the lower body is not teleoperated).
_LEG_STIFFNESS = 500.0  # [N m/rad]
_LEG_DAMPING = 20.0  # [N m s/rad]
_HARNESS_SOLREF = (0.02, 1.0)  # soft weld: time constant [s], damping ratio
_TABLE_CENTER = (0.5, 0.0)  # table in front of the robot, near edge 0.25 m from the pelvis [m]
_TABLE_HALF = (0.25, 0.5)  # [m]
_CUBE_XY = (0.35, -0.15)  # [m], in reach of the right hand


def _joint_kind(name: str) -> str:
    if name in WAIST_JOINTS:
        return name
    # "right_shoulder_pitch_joint" -> "shoulder_pitch"
    return name.removeprefix("left_").removeprefix("right_").removesuffix("_joint")


def _build_g1(*, support: Support, timestep: float) -> mujoco.MjSpec:
    """The G1 with upper-body position servos, gravity compensation and the legs held at the stance."""
    spec = load_g1(kinematic=False, support=support, timestep=timestep)

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
    pelvis, keep their weight, which the support carries. The pelvis stands at 0.795 m with the
    feet a few millimetres above the floor; a 0.8 m table with a cube stands in front (x > 0.25 m).

    Args:
        support: How the lower body is held (see :data:`Support`).
        timestep: Physics step [s].

    Raises:
        DependencyError: example-robot-data is not installed.
        RobotError: the model file is missing or lacks a joint or body used here.
    """
    if support not in ("fixed", "harness"):
        raise ValueError(f"support must be 'fixed' or 'harness', got {support!r}")
    if not 0 < timestep <= 0.01:
        raise ValueError(f"timestep must be in (0, 0.01] s, got {timestep}")
    spec = _build_g1(support=support, timestep=timestep)
    bodies = _add_world(spec)
    return humanoid_scene(compile_spec(spec), support, actuated=True, objects=bodies)


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
    """A simulated Unitree G1 whose upper body (3-DoF waist + two 7-DoF arms) is teleoperated.

    Implements :class:`~telerig.robots.base.RobotDriver` for :data:`UPPER_BODY_JOINTS`
    (``send`` sets position targets [rad], clipped to the joint ranges); the real-time physics
    thread, stamping, e-stop and stepping are :class:`MujocoArm`'s. The G1's rubber hands have
    no fingers: :attr:`has_gripper` is False and :meth:`send_gripper` refuses (``RobotError``).

    It is a :class:`~telerig.robots.base.StandingRobot`: the pelvis stands at
    :data:`~telerig.robots.models.g1.G1_PELVIS_HEIGHT`; with ``support: harness`` the pelvis floats
    (its pose is the ``base_pose`` stream), with ``fixed`` it is bolted to its stand.
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

    @property
    def standing_height_m(self) -> float:
        """Pelvis height above the floor when standing [m]."""
        return G1_PELVIS_HEIGHT

    @property
    def floating_base(self) -> bool:
        """Whether the pelvis floats (``harness`` support) rather than being bolted to a stand."""
        return self._humanoid.support == "harness"

    def read_base_pose(self) -> Pose:
        """The pelvis pose in the world frame (z up, floor at 0), stamped like :meth:`read_state`.

        Raises:
            RobotError: the driver is not connected.
        """
        return self._body_pose(self._pelvis)

    def pelvis_pose(self) -> tuple[FloatArray, FloatArray]:
        """Pelvis position [m] (shape (3,)) and orientation (w, x, y, z) (shape (4,)), world frame.

        Raises:
            RobotError: the driver is not connected.
        """
        self._require_connected()
        with self.locked() as (_, data):
            return data.xpos[self._pelvis].copy(), data.xquat[self._pelvis].copy()
