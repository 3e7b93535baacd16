"""Arm and gripper descriptions: MJCF, joints, home, limits, end-effector site, servo gains."""

from __future__ import annotations

import math
from dataclasses import dataclass

from telerig.errors import ConfigError

__all__ = ["ARM_MODELS", "GRIPPER_MODELS", "ArmModel", "GripperModel", "arm_model"]


@dataclass(frozen=True, slots=True)
class GripperModel:
    """A gripper MJCF from robosuite and how to actuate it.

    Names are as in the gripper's MJCF; a scene prefixes them (``gripper/`` on an arm).

    Attributes:
        name: Model name.
        mjcf: MJCF path relative to robosuite's ``models/assets`` directory.
        root_body: Body attached to the arm's flange.
        actuators: Position actuators of the fingers, as in the MJCF.
        joints: Finger joints the actuators drive, same order.
        open_ctrl: Actuator targets of the fully open gripper [rad] or [m], same order.
        closed_ctrl: Actuator targets of the fully closed gripper [rad] or [m], same order.
        kp: Finger servo stiffness [N m/rad] or [N/m].
        kv: Finger servo damping [N m s/rad] or [N s/m].
        grip_site: Site between the finger pads; its z axis points out of the gripper.
        couplings: ``(follower, leader, coef)`` joint equalities (``q_follower = coef * q_leader``)
            replacing the MJCF's soft linkage tendons; empty when the MJCF needs none.
        passive_damping: Damping [N m s/rad] and armature [kg m^2] of the finger joints that the
            servos do not drive directly (linkages); None keeps the MJCF's.
        exclude_internal: Disable contacts between the gripper's own bodies (overlapping linkage meshes).
        velocity: Finger speed limit of the actuated joints [rad/s] or [m/s] (vendor datasheet).
        acceleration: Finger acceleration limit [rad/s^2] or [m/s^2].
    """

    name: str
    mjcf: str
    root_body: str
    actuators: tuple[str, ...]
    joints: tuple[str, ...]
    open_ctrl: tuple[float, ...]
    closed_ctrl: tuple[float, ...]
    kp: float
    kv: float
    grip_site: str = "grip_site"
    couplings: tuple[tuple[str, str, float], ...] = ()
    passive_damping: tuple[float, float] | None = None
    exclude_internal: bool = False
    velocity: float = 1.0
    acceleration: float = 10.0


@dataclass(frozen=True, slots=True)
class ArmModel:
    """An arm MJCF from robosuite with its gripper, home pose, limits and position-servo gains.

    Attributes:
        name: Model name, as in a ``mujoco_arm`` robot config's ``model``.
        mjcf: Robot MJCF path relative to robosuite's ``models/assets`` directory.
        gripper: The gripper on the flange.
        flange_body: Arm body the gripper is attached to.
        base_bodies: Bodies welded to the base (no gravity compensation needed); the first is the base.
        joints: Arm joint names, base to tool. Length n.
        home: Home configuration [rad]: gripper above the table in front of the base, pointing down.
            Shape (n,).
        kp: Servo stiffness per joint [N m/rad]. Shape (n,).
        kv: Servo damping per joint [N m s/rad]. Shape (n,).
        force: Servo torque limit per joint [N m] (the vendor's maximum joint torque). Shape (n,).
        velocity: Joint speed limit [rad/s] (vendor datasheet). Shape (n,).
        acceleration: Joint acceleration limit [rad/s^2]. Shape (n,).
        armature: Reflected rotor inertia added to each arm joint [kg m^2].
    """

    name: str
    mjcf: str
    gripper: GripperModel
    flange_body: str
    base_bodies: tuple[str, ...]
    joints: tuple[str, ...]
    home: tuple[float, ...]
    kp: tuple[float, ...]
    kv: tuple[float, ...]
    force: tuple[float, ...]
    velocity: tuple[float, ...]
    acceleration: tuple[float, ...]
    armature: float = 0.1

    def __post_init__(self) -> None:
        n = len(self.joints)
        for attr in ("home", "kp", "kv", "force", "velocity", "acceleration"):
            if len(getattr(self, attr)) != n:
                raise ValueError(f"arm model {self.name!r}: {attr} must have {n} values, one per joint")


#: Robotiq 2F-85: one servo per finger (ctrl 0 = open, 0.8 = closed [rad]); the four-bar linkage of
#: each finger as joint couplings (mimic joints of the Robotiq URDF): the inner knuckle turns with
#: the outer knuckle, the inner finger counter-rotates so the pads stay parallel. robosuite
#: approximates this with soft tendons, which fight the servo.
ROBOTIQ_2F85 = GripperModel(
    name="robotiq_2f85",
    mjcf="grippers/robotiq_gripper_85.xml",
    root_body="robotiq_85_adapter_link",
    actuators=("finger_1", "finger_2"),
    joints=("finger_joint", "right_outer_knuckle_joint"),
    open_ctrl=(0.0, 0.0),
    closed_ctrl=(0.8, 0.8),
    kp=20.0,
    kv=0.5,
    couplings=(
        ("left_inner_knuckle_joint", "finger_joint", 1.0),
        ("left_inner_finger_joint", "finger_joint", -1.0),
        ("right_inner_knuckle_joint", "right_outer_knuckle_joint", 1.0),
        ("right_inner_finger_joint", "right_outer_knuckle_joint", -1.0),
    ),
    passive_damping=(0.05, 0.001),
    exclude_internal=True,
    # 2F-85 datasheet: 20-150 mm/s closing speed over the 85 mm stroke (0.8 rad of finger_joint).
    velocity=0.8 * 150.0 / 85.0,
    acceleration=15.0,
)

#: Franka Hand: two prismatic fingers, 0-0.04 m each (the second one's axis is mirrored).
PANDA_HAND = GripperModel(
    name="panda_hand",
    mjcf="grippers/panda_gripper.xml",
    root_body="right_gripper",
    actuators=("gripper_finger_joint1", "gripper_finger_joint2"),
    joints=("finger_joint1", "finger_joint2"),
    open_ctrl=(0.04, -0.04),
    closed_ctrl=(0.0, 0.0),
    kp=1000.0,
    kv=0.0,  # robosuite's finger joints carry 100 N s/m of damping already
    # Franka Hand datasheet: 0.05 m/s per finger.
    velocity=0.05,
    acceleration=0.5,
)

GRIPPER_MODELS: dict[str, GripperModel] = {g.name: g for g in (ROBOTIQ_2F85, PANDA_HAND)}

_UR5E_JOINTS = (
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
)

#: UR5e + Robotiq 2F-85. Gains are about critically damped for the joint inertias at home
#: (2.2 kg m^2 shoulder, 0.1 wrist): 90 % of a small step in under 0.1 s, no overshoot at 2 ms
#: (Menagerie's 2000/400 is overdamped and lags ~0.2 s). Torque limits are the UR5e's maximum
#: joint torques; speed 180 deg/s for every joint (UR5e e-Series datasheet). Universal Robots
#: publishes no per-joint acceleration limit: 8 rad/s^2 is a conservative teleoperation value,
#: well above the URScript ``movej`` default of 1.4 rad/s^2.
UR5E_ROBOTIQ85 = ArmModel(
    name="ur5e_robotiq85",
    mjcf="robots/ur5e/robot.xml",
    gripper=ROBOTIQ_2F85,
    flange_body="right_hand",
    base_bodies=("base", "fixed_base_link"),
    joints=_UR5E_JOINTS,
    home=(0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0),
    kp=(4000.0, 4000.0, 4000.0, 500.0, 500.0, 500.0),
    kv=(160.0, 160.0, 160.0, 15.0, 15.0, 15.0),
    force=(150.0, 150.0, 150.0, 28.0, 28.0, 28.0),
    velocity=(math.pi,) * 6,
    acceleration=(8.0,) * 6,
)

#: Franka Emika Panda + Franka Hand (7 DoF). Limits from the Franka Control Interface datasheet
#: (joint speed 2.175/2.61 rad/s, acceleration 15/7.5/10/12.5/15/20/20 rad/s^2, torque 87/12 N m).
#: Gains critically damped for robosuite's joint-space inertias at home (2.4 kg m^2 at the shoulder,
#: 0.3 at the flange, 0.1 kg m^2 armature included).
PANDA = ArmModel(
    name="panda",
    mjcf="robots/panda/robot.xml",
    gripper=PANDA_HAND,
    flange_body="right_hand",
    base_bodies=("base", "link0"),
    joints=tuple(f"joint{i}" for i in range(1, 8)),
    # Gripper 0.3 m above the base plane at (0.45, 0, 0.3) m in the base frame, pointing straight down
    # (robosuite's init_qpos with the hand's 0.2 rad tilt taken out, solved with ArmIK).
    home=(0.0, -0.2505, 0.0, -2.4416, 0.0, 2.1911, 0.7854),
    kp=(4000.0, 4000.0, 4000.0, 4000.0, 500.0, 500.0, 500.0),
    kv=(200.0, 200.0, 170.0, 165.0, 35.0, 30.0, 25.0),
    force=(87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0),
    velocity=(2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61),
    acceleration=(15.0, 7.5, 10.0, 12.5, 15.0, 20.0, 20.0),
)

#: Arm models by name; ``mujoco_arm``'s ``model`` field takes these names.
ARM_MODELS: dict[str, ArmModel] = {m.name: m for m in (UR5E_ROBOTIQ85, PANDA)}


def arm_model(name: str) -> ArmModel:
    """The arm model called ``name``.

    Raises:
        ConfigError: no such model.
    """
    try:
        return ARM_MODELS[name]
    except KeyError:
        raise ConfigError(f"arm model {name!r} does not exist. Available: {', '.join(ARM_MODELS)}") from None
