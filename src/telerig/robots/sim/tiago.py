"""Simulated TIAGo: its servos, a table and a cup (the model: :mod:`telerig.robots.models.tiago`)."""

from __future__ import annotations

import mujoco

from telerig.robots.models.arm import GRIPPER_PREFIX
from telerig.robots.models.arms import ROBOTIQ_2F85
from telerig.robots.models.mjcf import VISUAL_GROUPS, compile_spec
from telerig.robots.models.tiago import (
    TIAGO_ARM_JOINTS,
    TIAGO_BASE_JOINTS,
    TIAGO_VELOCITY,
    TiagoScene,
    load_tiago,
    tiago_scene,
)
from telerig.robots.sim.scene import TABLE_TOP, actuate_gripper, add_room, add_table

__all__ = ["build_tiago_scene"]

# Position servos of the torso [N/m, N s/m] and arm joints [N m/rad, N m s/rad], on top of the
# joint damping robosuite sets (10..100 N m s/rad, 1000 N s/m on the torso). Force limits are
# robosuite's motor ranges (50 N m shoulder, 15 N m wrist, 1000 N torso).
_ARM_KP = (30000.0, 3000.0, 3000.0, 1500.0, 1500.0, 500.0, 500.0)
_ARM_KV = (2000.0, 150.0, 100.0, 60.0, 60.0, 15.0, 15.0)
_ARM_FORCE = (1000.0, 50.0, 50.0, 15.0, 15.0, 15.0, 15.0)
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


def _build_robot() -> mujoco.MjSpec:
    """The TIAGo with torso/arm position servos, base velocity servos and finger servos."""
    spec = load_tiago(kinematic=False)

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
    base = zip(TIAGO_BASE_JOINTS, _BASE_KV, _BASE_FORCE, TIAGO_VELOCITY[:3], strict=True)
    for name, kv, force, vmax in base:
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
    actuate_gripper(spec, ROBOTIQ_2F85, GRIPPER_PREFIX)
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
    spec = _build_robot()
    spec.option.timestep = timestep
    bodies = _add_world(spec, with_cup=with_cup)
    return tiago_scene(compile_spec(spec), kinematic=False, objects=bodies)
