"""MuJoCo dexterous hand (Inspire, Ability) on a fixed wrist over a table; mimic joints as equalities.

The hand is the robosuite / robosuite-models MJCF (meshes, masses, collision geometry), posed so
that its *hand frame* (:mod:`telerig.robots.models.hands`: x wrist to middle knuckle, z out of the
back of the hand) has the world's axes: palm down, fingers along world +x. Its 6 motors are
position servos on the actuated joints; every other joint follows its leader through a joint
equality constraint ``q_follower = offset + multiplier * q_leader`` (the real hand's linkage, the
same couplings the retargeter's kinematic model uses). Equality constraints were chosen over one
servo per joint because a linkage is rigid: a finger blocked at its tip must stop the whole
finger, which independent servos would not do. They are soft in MuJoCo; ``measure_mimic_error``
reports how far the physics strays from the relation (see ``tests/robots/sim/test_hand.py``).

:class:`MujocoHand` is a :class:`~telerig.robots.sim.arm.MujocoArm` whose "arm" is the 6 motors,
so it inherits the real-time physics thread, clipping, stamps and homing; ``send_gripper`` moves
all fingers together (open/close synergy) so a gripper binding drives a hand too.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from telerig.errors import RobotError
from telerig.ir.types import FloatArray, Handedness
from telerig.robots.models.arm import ArmScene
from telerig.robots.models.hands import HandKinematics, HandModelName, load_hand
from telerig.robots.models.mjcf import compile_spec, load_spec, set_physics_options
from telerig.robots.sim.arm import MujocoArm, SimPhysics
from telerig.robots.sim.scene import (
    TABLE_TOP,
    add_room,
    add_table,
)

__all__ = [
    "HAND_PHYSICS",
    "SIM_HAND_MODELS",
    "HandPhysics",
    "HandScene",
    "MimicJoint",
    "MujocoHand",
    "build_hand_scene",
    "measure_mimic_error",
]

_TIMESTEP = 0.002  # [s]
_HIDDEN_GROUP = 4  # debug sites: not drawn by the scene camera
#: Hand frame origin (the wrist) in the world [m]: the table top is 8.5 cm below the palm plane,
#: clear of the closed fist (the Inspire's thumb tip reaches 6.8 cm below it).
_WRIST = (0.0, 0.0, TABLE_TOP + 0.085)
#: Grasp objects, x-y in the hand frame [m]: a short can whose top the closing fingers wrap
#: around, and a ball beside the hand.
_CAN_CENTER = (0.085, -0.01)
_CAN_RADIUS = 0.016
_CAN_HALF_HEIGHT = 0.025
_BALL_CENTER = (0.09, -0.11)
_BALL_RADIUS = 0.02

#: Hand models :func:`build_hand_scene` simulates.
SIM_HAND_MODELS: tuple[HandModelName, ...] = ("inspire", "ability")


@dataclass(frozen=True, slots=True)
class MimicJoint:
    """A joint that follows a motor joint: ``q_follower = offset + multiplier * q_leader`` [rad]."""

    follower: str
    leader: str
    multiplier: float
    offset: float


@dataclass(frozen=True, slots=True)
class HandPhysics:
    """Actuation of one simulated hand model.

    Attributes:
        kp: Motor servo stiffness [N m/rad].
        kv: Motor servo damping [N m s/rad].
        force: Motor torque limit [N m].
        damping: Passive damping of every hand joint [N m s/rad].
        armature: Reflected rotor inertia of every hand joint [kg m^2].
        velocity: Motor joint speed limit [rad/s] (see the module constants for the source).
        acceleration: Motor joint acceleration limit [rad/s^2].
        closed: Synergy "closed" target of each motor as a fraction of its range from the open
            (neutral) pose toward the far bound; thumb first, :attr:`HandKinematics.actuated` order.
    """

    kp: float
    kv: float
    force: float
    damping: float
    armature: float
    velocity: float
    acceleration: float
    closed: tuple[float, ...]


#: Per-model actuation. Neither vendor publishes per-joint speed or acceleration limits, so these
#: are conservative values, not datasheet figures: 3 rad/s stays under the full-stroke speed the
#: Inspire Modbus driver assumes (2.75 rad in 0.8 s, 3.4 rad/s; ``robots/modbus``), and the same
#: value is used for the Ability Hand, whose maker calls it faster; 25 rad/s^2 reaches that speed
#: in 0.12 s. Torque limits are about 10 N of fingertip force 6-8 cm from the knuckle, rounded up.
HAND_PHYSICS: dict[HandModelName, HandPhysics] = {
    "inspire": HandPhysics(
        kp=5.0,
        kv=0.15,
        force=1.0,
        damping=0.02,
        armature=0.001,
        velocity=3.0,
        acceleration=25.0,
        closed=(0.8, 1.0, 0.95, 0.95, 0.95, 0.95),
    ),
    "ability": HandPhysics(
        kp=3.0,
        kv=0.1,
        force=1.0,
        damping=0.02,
        armature=0.001,
        velocity=3.0,
        acceleration=25.0,
        closed=(0.5, 0.6, 0.9, 0.9, 0.9, 0.9),
    ),
}


@dataclass(frozen=True, slots=True)
class HandScene(ArmScene):
    """A compiled hand scene: an :class:`~telerig.robots.models.arm.ArmScene` whose arm is the hand's motors.

    ``arm_joints`` are the actuated (motor) joints, ``gripper_actuators`` the same servos (the
    synergy), ``home`` the open hand. Extra attributes:

    Attributes:
        kinematics: The hand's kinematic model (the retargeter's; same joint names).
        mimic: Joints that follow a motor joint through an equality constraint.
        model_name: ``"inspire"`` or ``"ability"``.
    """

    kinematics: HandKinematics | None = None
    mimic: tuple[MimicJoint, ...] = ()
    model_name: str = ""


def _mimic_joints(kin: HandKinematics) -> tuple[MimicJoint, ...]:
    """The followers of ``q_full = A q_act + b``: rows of ``A`` that are not a unit vector."""
    out = []
    act = set(kin.actuated)
    for j, name in enumerate(kin.joint_names):
        if name in act:
            continue
        (cols,) = np.nonzero(kin.coupling[j])
        if cols.size != 1:
            raise RobotError(f"{kin.name}: joint '{name}' must follow exactly one motor joint")
        k = int(cols[0])
        out.append(MimicJoint(name, kin.actuated[k], float(kin.coupling[j, k]), float(kin.offset[j])))
    return tuple(out)


def _synergy(kin: HandKinematics, closed: tuple[float, ...]) -> tuple[FloatArray, FloatArray]:
    """Open (neutral) and closed motor targets [rad]; closed moves toward the bound farther from open."""
    open_q = kin.neutral()
    if len(closed) != len(kin.actuated):
        raise RobotError(f"{kin.name}: need {len(kin.actuated)} synergy fractions, got {len(closed)}")
    far = np.where(np.abs(kin.upper - open_q) >= np.abs(kin.lower - open_q), np.asarray(kin.upper), kin.lower)
    closed_q = open_q + np.asarray(closed) * (far - open_q)
    return open_q, closed_q


def build_hand_scene(
    model: HandModelName = "inspire",
    handedness: Handedness = "right",
    *,
    with_objects: bool = True,
    timestep: float = _TIMESTEP,
) -> HandScene:
    """Build a dexterous hand on a fixed wrist, palm down 8.5 cm over a 0.8 m table.

    The hand frame sits at (0, 0, 0.885) m in the world with the world's axes (fingers along +x,
    back of the hand up). Objects (``with_objects``): a 3.2 cm x 5 cm can (body ``can``) standing
    under the fingers, whose top a closing hand wraps around, and a 4 cm ball (``ball``) beside
    the hand.

    Args:
        model: ``"inspire"`` (6 motors, 12 joints) or ``"ability"`` (6 motors, 10 joints).
        handedness: Which hand.
        with_objects: Add the bar and the ball.
        timestep: Physics timestep [s]; the servo gains are tuned for 0.002 s.

    Raises:
        RobotError: unknown model, a model file is missing, or the scene does not compile.
        DependencyError: the package that ships the model is not installed.
    """
    if model not in HAND_PHYSICS:
        raise RobotError(f"no simulated hand {model!r}. Available: {', '.join(SIM_HAND_MODELS)}")
    if not 0 < timestep <= 0.004:
        raise ValueError(
            f"timestep must be in (0, 0.004] s for the finger servos to be stable, got {timestep}"
        )
    physics = HAND_PHYSICS[model]
    kin = load_hand(model, handedness)
    spec = load_spec(kin.source)
    spec.modelname = f"{kin.name}_table"
    spec.compiler.degree = False
    for site in spec.sites:  # the MJCF's markers; hidden from cameras
        site.group = _HIDDEN_GROUP
    for element in (*spec.sensors, *spec.tendons, *spec.actuators):
        spec.delete(element)
    set_physics_options(spec, timestep)

    # Pose the hand so its hand frame is at the wrist with the world's axes (palm down).
    for child in spec.worldbody.bodies:
        placed = kin.model.body(child.name)
        child.pos = np.asarray(_WRIST) + placed.pos
        child.quat = placed.quat.copy()
    hand_bodies = [b for b in spec.bodies if b.name != "world"]
    for body in hand_bodies:
        body.gravcomp = 1.0  # the motors hold the fingers against gravity, as the real drives do
    # Keypoint sites at the retargeter's points, to compare the physics with the kinematic model.
    for index, site_name in kin.keypoints.items():
        sid = kin.model.site(site_name).id
        body_name = kin.model.body(int(kin.model.site_bodyid[sid])).name
        spec.body(body_name).add_site(name=site_name, pos=kin.model.site_pos[sid], group=_HIDDEN_GROUP)
        del index

    names = {j.name for j in spec.joints}
    missing = [n for n in kin.joint_names if n not in names]
    if missing:
        raise RobotError(f"{kin.source.name}: joint(s) {', '.join(missing)} not in the physics model")
    for name in kin.joint_names:
        joint = spec.joint(name)
        joint.damping = [physics.damping, 0.0, 0.0]
        joint.armature = physics.armature
        joint.frictionloss = 0.0
    for k, name in enumerate(kin.actuated):
        lo, hi = float(kin.lower[k]), float(kin.upper[k])
        # The motor range is the one the couplings leave, so no follower ever meets its own limit.
        spec.joint(name).range = [lo, hi]
        act = spec.add_actuator(
            name=f"{name}_pos",
            target=name,
            trntype=mujoco.mjtTrn.mjTRN_JOINT,
            ctrlrange=[lo, hi],
            forcerange=[-physics.force, physics.force],
        )
        act.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
        act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
        act.set_to_position(kp=physics.kp, kv=physics.kv)
    mimic = _mimic_joints(kin)
    for m in mimic:
        eq = spec.add_equality(
            type=mujoco.mjtEq.mjEQ_JOINT,
            name1=m.follower,
            name2=m.leader,
            objtype=mujoco.mjtObj.mjOBJ_JOINT,
        )
        eq.name = f"mimic_{m.follower}"
        eq.data[:5] = [m.offset, m.multiplier, 0.0, 0.0, 0.0]
        eq.solref = [2 * timestep + 0.001, 1.0]  # as stiff as the timestep allows

    add_room(spec)
    add_table(spec, (0.1, 0.0), (0.3, 0.3))
    mount = spec.worldbody.add_body(name="mount", pos=list(_WRIST))
    mount.add_geom(  # the wrist post the hand hangs from (visual only)
        name="mount_post",
        type=mujoco.mjtGeom.mjGEOM_CYLINDER,
        size=[0.025, 0.15, 0],
        pos=[-0.05, 0, 0.16],
        rgba=[0.3, 0.3, 0.32, 1.0],
        group=2,
        contype=0,
        conaffinity=0,
    )
    top = TABLE_TOP + 2 * _CAN_HALF_HEIGHT - _WRIST[2]
    mount.add_site(name="grasp", pos=[_CAN_CENTER[0], _CAN_CENTER[1], top], group=_HIDDEN_GROUP)
    bodies: tuple[str, ...] = ()
    if with_objects:
        bodies = (_add_can(spec), _add_ball(spec))
    spec.worldbody.add_camera(
        name="scene", pos=[0.45, -0.35, 1.1], xyaxes=[0.6, 0.8, 0, -0.3, 0.22, 0.93], fovy=45
    )
    compiled = compile_spec(spec)
    open_q, closed_q = _synergy(kin, physics.closed)
    cameras = tuple(compiled.camera(i).name for i in range(compiled.ncam))
    actuators = tuple(f"{n}_pos" for n in kin.actuated)
    return HandScene(
        model=compiled,
        arm_joints=kin.actuated,
        arm_actuators=actuators,
        gripper_actuators=actuators,
        gripper_joints=kin.actuated,
        ee_site="grasp",
        base_body="mount",
        cameras=tuple(sorted(cameras, key=lambda c: c != "scene")),
        home=_frozen(open_q),
        velocity_limit=_frozen(np.full(len(actuators), physics.velocity)),
        acceleration_limit=_frozen(np.full(len(actuators), physics.acceleration)),
        gripper_open=_frozen(open_q),
        gripper_closed=_frozen(closed_q),
        objects=bodies,
        kinematics=kin,
        mimic=mimic,
        model_name=model,
    )


def _frozen(values: FloatArray) -> FloatArray:
    arr = np.array(values, dtype=np.float64)
    arr.flags.writeable = False
    return arr


def _add_can(spec: mujoco.MjSpec) -> str:
    """A free 50 g can standing on the table under the fingers."""
    x, y = _CAN_CENTER[0] + _WRIST[0], _CAN_CENTER[1] + _WRIST[1]
    body = spec.worldbody.add_body(name="can", pos=[x, y, TABLE_TOP + _CAN_HALF_HEIGHT])
    body.add_freejoint(name="can_free")
    body.add_geom(
        name="can",
        type=mujoco.mjtGeom.mjGEOM_CYLINDER,
        size=[_CAN_RADIUS, _CAN_HALF_HEIGHT, 0],
        mass=0.05,
        rgba=[0.2, 0.6, 0.3, 1.0],
        group=2,
        condim=4,
        friction=[1.5, 0.01, 0.001],
    )
    return "can"


def _add_ball(spec: mujoco.MjSpec) -> str:
    """A free 30 g ball on the table beside the hand; rolling friction brings it to rest."""
    x, y = _BALL_CENTER[0] + _WRIST[0], _BALL_CENTER[1] + _WRIST[1]
    body = spec.worldbody.add_body(name="ball", pos=[x, y, TABLE_TOP + _BALL_RADIUS])
    body.add_freejoint(name="ball_free")
    body.add_geom(
        name="ball",
        type=mujoco.mjtGeom.mjGEOM_SPHERE,
        size=[_BALL_RADIUS, 0, 0],
        mass=0.03,
        rgba=[0.95, 0.75, 0.1, 1.0],
        group=2,
        condim=6,
        friction=[1.0, 0.005, 0.0005],
    )
    return "ball"


def measure_mimic_error(model: mujoco.MjModel, data: mujoco.MjData, mimic: tuple[MimicJoint, ...]) -> float:
    """Largest ``|q_follower - (offset + multiplier * q_leader)|`` over the mimic joints [rad]."""
    worst = 0.0
    for m in mimic:
        qf = float(data.qpos[model.joint(m.follower).qposadr[0]])
        ql = float(data.qpos[model.joint(m.leader).qposadr[0]])
        worst = max(worst, abs(qf - (m.offset + m.multiplier * ql)))
    return worst


class MujocoHand(MujocoArm):
    """A simulated dexterous hand, implementing :class:`~telerig.robots.base.RobotDriver`.

    :meth:`send` commands the motor joints (:attr:`joint_names`, e.g. the Inspire's 6) [rad],
    clipped to the range the couplings leave; the mimic joints follow in the physics.
    :meth:`send_gripper` is a synergy: opening 1 is the open hand, 0 the closed grasp, every
    motor interpolated between the two. :meth:`read_state` reports the motor joints. Physics,
    stamps and lifecycle are :class:`~telerig.robots.sim.arm.MujocoArm`'s.
    """

    def __init__(
        self,
        scene: HandScene | None = None,
        *,
        name: str = "hand_sim",
        realtime: bool = True,
        max_catchup: int = 25,
    ) -> None:
        """Create the driver (the physics starts on :meth:`connect`).

        Args:
            scene: Scene to simulate; :func:`build_hand_scene` (Inspire, right) when None.
            name: Driver name; the ``source_id`` of every stamp it produces.
            realtime: Step on a thread paced to the wall clock; False for :meth:`step`.
            max_catchup: Most steps the loop may run late before it drops the lag. >= 1.
        """
        hand_scene = scene if scene is not None else build_hand_scene()
        if hand_scene.kinematics is None:
            raise RobotError(f"{name}: the scene has no hand model; build it with build_hand_scene()")
        physics = SimPhysics(hand_scene.model, name=name, realtime=realtime, max_catchup=max_catchup)
        super().__init__(hand_scene, name=name, physics=physics)
        self._hand = hand_scene
        model = hand_scene.model
        self._motor_qadr = np.array([model.joint(j).qposadr[0] for j in hand_scene.arm_joints])
        self._motor_act = np.array([model.actuator(a).id for a in hand_scene.arm_actuators])
        self._follow = [
            (int(model.joint(m.follower).qposadr[0]), int(model.joint(m.leader).qposadr[0]), m)
            for m in hand_scene.mimic
        ]
        open_q, closed_q = hand_scene.gripper_open, hand_scene.gripper_closed
        if open_q is None or closed_q is None:
            raise RobotError(
                f"{name}: the scene has no open/closed synergy; build it with build_hand_scene()"
            )
        self._closing = np.sign(closed_q - open_q)
        physics.attach(self._place_followers)  # after the arm's home: followers match their leaders

    @property
    def hand_scene(self) -> HandScene:
        """The simulated scene with the hand's kinematic model and mimic joints."""
        return self._hand

    @property
    def kinematics(self) -> HandKinematics:
        """The hand's kinematic model (what the retargeter solves on)."""
        assert self._hand.kinematics is not None
        return self._hand.kinematics

    def mimic_error(self) -> float:
        """Largest deviation of a mimic joint from its coupling right now [rad]."""
        with self.locked() as (model, data):
            return measure_mimic_error(model, data, self._hand.mimic)

    def estop(self) -> None:
        """Latch the emergency stop: every motor holds where it is, but never looser than commanded.

        A finger pressing on an object keeps its (more closed) target, so stopping never drops
        a grasp, as the real hands' non-backdrivable drives do; commands are ignored until
        :meth:`reset_estop`.
        """

        def hold(data: mujoco.MjData) -> None:
            q = data.qpos[self._motor_qadr]
            ctrl = data.ctrl[self._motor_act]
            tighter = self._closing * (ctrl - q) > 0.0
            data.ctrl[self._motor_act] = np.where(
                tighter, ctrl, np.clip(q, self.limits.lower, self.limits.upper)
            )

        self._link.latch(hold)

    def _place_followers(self, data: mujoco.MjData) -> None:
        for follower, leader, m in self._follow:
            data.qpos[follower] = m.offset + m.multiplier * data.qpos[leader]
