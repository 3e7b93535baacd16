"""Unitree G1 (29 DoF, example-robot-data's URDF): upper-body joints, home, limits, sites, kinematic model.

The same model, with the real robot's joint names and limits, stands for the simulated G1
(:mod:`telerig.robots.sim.humanoid`), the humanoid IK (:mod:`telerig.retarget.humanoid`) and the
real G1 driven over ``arm_sdk`` (:mod:`telerig.robots.unitree`): the commanded joints are the 17
arm_sdk joints (waist, left arm, right arm) in motor order.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import mujoco
import numpy as np

from telerig.errors import RobotError
from telerig.ir.types import FloatArray
from telerig.robots.models.mjcf import (
    compile_kinematic,
    compile_spec,
    example_robot_data_robots,
    set_physics_options,
)

__all__ = [
    "G1_PELVIS_HEIGHT",
    "HUMANOID_ACCELERATION_LIMIT",
    "HUMANOID_HOME",
    "HUMANOID_SITES",
    "HUMANOID_VELOCITY_LIMIT",
    "LEFT_ARM_JOINTS",
    "LEG_JOINTS",
    "RIGHT_ARM_JOINTS",
    "UPPER_BODY_JOINTS",
    "WAIST_JOINTS",
    "WAIST_YAW_JOINT",
    "HumanoidScene",
    "Support",
    "build_humanoid_kinematics",
    "g1_urdf",
    "humanoid_scene",
    "load_g1",
]

#: How the lower body is held: ``"fixed"`` bolts the pelvis to a stand (no free joint; simplest and
#: exactly repeatable); ``"harness"`` gives the pelvis a floating base held by a soft weld
#: constraint, like a gantry harness, so the pelvis pose is a simulated state that can sag or sway.
Support = Literal["fixed", "harness"]

#: Waist joints, motor order (12-14). The retargeter steers the yaw; roll and pitch hold home.
WAIST_JOINTS = ("waist_yaw_joint", "waist_roll_joint", "waist_pitch_joint")
#: The waist joint the skeleton's torso heading drives.
WAIST_YAW_JOINT = "waist_yaw_joint"
_ARM = ("shoulder_pitch", "shoulder_roll", "shoulder_yaw", "elbow", "wrist_roll", "wrist_pitch", "wrist_yaw")
#: Left arm joints, shoulder to hand (motors 15-21).
LEFT_ARM_JOINTS = tuple(f"left_{name}_joint" for name in _ARM)
#: Right arm joints, shoulder to hand (motors 22-28).
RIGHT_ARM_JOINTS = tuple(f"right_{name}_joint" for name in _ARM)
#: Joints the driver commands and the IK solves for: waist, left arm, right arm, the real robot's
#: arm_sdk motor order (:data:`telerig.robots.unitree.joints.G1_UPPER_BODY_NAMES`). Length 17.
UPPER_BODY_JOINTS = WAIST_JOINTS + LEFT_ARM_JOINTS + RIGHT_ARM_JOINTS
#: Leg joints (motors 0-11), held at the stance posture (all zero: legs straight, feet flat).
LEG_JOINTS = tuple(
    f"{side}_{name}_joint"
    for side in ("left", "right")
    for name in ("hip_pitch", "hip_roll", "hip_yaw", "knee", "ankle_pitch", "ankle_roll")
)
#: Home upper-body posture [rad], :data:`UPPER_BODY_JOINTS` order: the G1's zero pose, waist
#: straight, upper arms down, elbows bent 90 degrees so the forearms point forward (hands in front
#: of the belly), wrists straight. The real robot's controller holds the arms there too.
HUMANOID_HOME = (0.0,) * len(UPPER_BODY_JOINTS)
#: Pelvis height [m] standing on the legs at zero: the foot soles 3 mm above the floor.
G1_PELVIS_HEIGHT = 0.795

#: Anatomical sites the retargeter targets, by role: the shoulder centre, the elbow (on the elbow
#: axis) and the wrist (the wrist pitch/yaw centre, on the wrist roll axis, so only the shoulder and
#: elbow move it) of each arm, and the torso frame (on the torso link at shoulder height; x
#: forward, y left, z up at home).
HUMANOID_SITES = {
    "torso": "torso",
    "right_shoulder": "right_shoulder",
    "right_elbow": "right_elbow",
    "right_wrist": "right_wrist",
    "left_shoulder": "left_shoulder",
    "left_elbow": "left_elbow",
    "left_wrist": "left_wrist",
}
_SITE_PLACES = {  # site -> (body, position in the body [m]), from the URDF's joint origins
    "torso": ("torso_link", (0.0, 0.0, 0.24778)),
    # The shoulder roll joint: 14 mm below the pitch axis (the two axes do not meet on the G1).
    "right_shoulder": ("right_shoulder_pitch_link", (0.0, -0.038, -0.013831)),
    "left_shoulder": ("left_shoulder_pitch_link", (0.0, 0.038, -0.013831)),
    "right_elbow": ("right_elbow_link", (0.0, 0.0, 0.0)),
    "left_elbow": ("left_elbow_link", (0.0, 0.0, 0.0)),
    "right_wrist": ("right_wrist_pitch_link", (0.0, 0.0, 0.0)),
    "left_wrist": ("left_wrist_pitch_link", (0.0, 0.0, 0.0)),
}

#: Upper-body joint speed limit for teleoperation [rad/s]. The G1 motors reach 22-37 rad/s (URDF);
#: 3 rad/s is a conservative value that still follows a brisk human reach.
HUMANOID_VELOCITY_LIMIT = 3.0
#: Upper-body joint acceleration limit [rad/s^2]. A brisk human reach (0.6 m in 1.2 s, the shipped
#: BVH clip) needs about 30 rad/s^2 at the shoulder and elbow; 40 lets the arms follow it, well
#: below what the 25 N m arm motors give the light G1 arm (> 100 rad/s^2).
HUMANOID_ACCELERATION_LIMIT = 40.0

_TIMESTEP = 0.002  # [s]
_URDF = ("g1_description", "urdf", "g1_29dof_rev_1_0.urdf")


@dataclass(frozen=True, slots=True)
class HumanoidScene:
    """A compiled humanoid model and the names a driver or IK solver needs.

    Attributes:
        model: The compiled MuJoCo model.
        joints: Commanded upper-body joints, :data:`UPPER_BODY_JOINTS`. Length 17.
        actuators: Position actuators of ``joints``, same order; empty in kinematic models.
        sites: Anatomical sites by role (see :data:`HUMANOID_SITES`).
        pelvis_body: The pelvis body; it stands :data:`G1_PELVIS_HEIGHT` above the world origin
            (on the floor), robot x forward, y left, z up.
        support: How the lower body is held (see :data:`Support`); ``"fixed"`` in kinematic models.
        cameras: Camera names, scene camera first.
        home: Home configuration of ``joints`` [rad]. Shape (17,).
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


def g1_urdf() -> Path:
    """Path of the G1 URDF example-robot-data ships (``.../g1_description/urdf/g1_29dof_rev_1_0.urdf``).

    Raises:
        DependencyError: example-robot-data is not installed.
    """
    return example_robot_data_robots().joinpath(*_URDF)


def load_g1(*, kinematic: bool, support: Support, timestep: float) -> mujoco.MjSpec:
    """The G1 URDF as a MuJoCo spec with the anatomical sites; legs rigid if ``kinematic``.

    Collision meshes are geom group 0, visual meshes group 1 without contacts (MuJoCo's URDF
    import). The pelvis stands at :data:`G1_PELVIS_HEIGHT`; it gets a free joint only when
    ``support == "harness"`` and not ``kinematic``.

    Raises:
        DependencyError: example-robot-data is not installed.
        RobotError: the model file is missing or lacks a joint or body used here.
    """
    path = g1_urdf()
    if not path.is_file():
        raise RobotError(f"model file not found: {path}")
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise RobotError(f"cannot parse {path}: {exc}") from exc
    meshes = path.parent.parent / "meshes"
    for mesh in root.iter("mesh"):  # "package://example-robot-data/.../meshes/x.STL" -> the file
        mesh.set("filename", str(meshes / mesh.get("filename", "").rsplit("/", 1)[-1]))
    extension = ET.SubElement(root, "mujoco")
    # Keep the visual meshes (a camera draws them) and every link as its own body (the sites).
    ET.SubElement(extension, "compiler", meshdir=str(meshes), discardvisual="false", fusestatic="false")
    try:
        spec = mujoco.MjSpec.from_string(ET.tostring(root, encoding="unicode"))
    except ValueError as exc:
        raise RobotError(f"cannot load {path}: {exc}") from exc
    spec.modelname = "g1_upper_body"
    set_physics_options(spec, timestep)
    joints = {j.name: j for j in spec.joints}
    for name in (*UPPER_BODY_JOINTS, *LEG_JOINTS):
        if name not in joints:
            raise RobotError(f"joint '{name}' not found in the G1 model. Available: {', '.join(joints)}")
    for site, (body, pos) in _SITE_PLACES.items():
        found = spec.body(body)
        if found is None:
            raise RobotError(f"body '{body}' not found in the G1 model")
        found.add_site(name=site, pos=list(pos), size=[0.01, 0.0, 0.0], group=4)
    pelvis = spec.body("pelvis")
    pelvis.pos = [0.0, 0.0, G1_PELVIS_HEIGHT]
    if not kinematic and support == "harness":
        pelvis.add_freejoint(name="floating_base_joint")
    if kinematic:
        # The IK moves the upper body only: the legs are rigid at the stance posture.
        for name in LEG_JOINTS:
            spec.delete(spec.joint(name))
    return spec


def build_humanoid_kinematics(*, drawn: bool = False) -> HumanoidScene:
    """Kinematics-only G1 for IK: pelvis fixed, legs rigid, the 17 upper-body joints free.

    The pelvis stands where it does in :func:`telerig.robots.sim.humanoid.build_humanoid_scene`, so
    world coordinates match. With ``drawn`` it keeps the visual meshes (for whoever draws it, e.g.
    the web scene); without them it builds in a fraction of the time
    (:func:`~telerig.robots.models.mjcf.compile_kinematic`).
    """
    spec = load_g1(kinematic=True, support="fixed", timestep=_TIMESTEP)
    return humanoid_scene(compile_spec(spec) if drawn else compile_kinematic(spec), "fixed", actuated=False)


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
