"""Unitree G1 humanoid (robosuite-models MJCF): upper-body joints, home, limits, sites, kinematic model."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import mujoco
import numpy as np

from telerig.errors import RobotError
from telerig.ir.types import FloatArray
from telerig.robots.models.mjcf import compile_spec, load_spec, robosuite_models_assets, set_physics_options

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
    "Support",
    "build_humanoid_kinematics",
    "humanoid_scene",
    "load_g1",
]

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


def load_g1(*, kinematic: bool, support: Support, timestep: float) -> mujoco.MjSpec:
    """The G1 MJCF with the anatomical sites, without actuators and sensors; legs rigid if ``kinematic``.

    The free joint goes when ``kinematic`` or ``support == "fixed"``.

    Raises:
        DependencyError: robosuite-models is not installed.
        RobotError: the model file is missing or lacks a joint or body used here.
    """
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


def build_humanoid_kinematics() -> HumanoidScene:
    """Kinematics-only G1 for IK: pelvis fixed, legs rigid, the 11 upper-body joints free.

    The pelvis stands where it does in :func:`telerig.robots.sim.humanoid.build_humanoid_scene`, so
    world coordinates match.
    """
    spec = load_g1(kinematic=True, support="fixed", timestep=_TIMESTEP)
    return humanoid_scene(compile_spec(spec), "fixed", actuated=False)


def humanoid_scene(
    model: mujoco.MjModel, support: Support, *, actuated: bool, objects: tuple[str, ...] = ()
) -> HumanoidScene:
    """The :class:`HumanoidScene` of a compiled G1 ``model`` (kinematic, or a simulated scene)."""
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


def _readonly(arr: FloatArray) -> FloatArray:
    arr.flags.writeable = False
    return arr
