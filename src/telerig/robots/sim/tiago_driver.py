"""MuJoCo-simulated TIAGo driver: holonomic base + torso + arm + Robotiq 2F-85, physics in real time."""

from __future__ import annotations

import logging
import math
import time

import mujoco
import numpy as np

from telerig.errors import RobotError
from telerig.ir.types import BaseVelocity, FloatArray, JointCommand, JointState, Pose, Stamp
from telerig.robots.base import JointLimits
from telerig.robots.models.arm import ArmScene
from telerig.robots.models.tiago import TiagoScene
from telerig.robots.sim.arm import MujocoArm
from telerig.robots.sim.tiago import build_tiago_scene

__all__ = ["MujocoTiago"]

_log = logging.getLogger(__name__)

#: TIAGo's ROS base frame, on the wheeled base 0.1 m above the floor; the scene's ``base_body`` (the
#: carrier of the planar base joints) lies on the floor, so it is no height reference.
_BASE_LINK = "base_link"


def _readonly(arr: FloatArray) -> FloatArray:
    out = np.array(arr, dtype=np.float64)
    out.flags.writeable = False
    return out


def _arm_view(scene: TiagoScene) -> ArmScene:
    """The torso, arm and gripper as a position-servoed arm: what :class:`MujocoArm` drives."""
    return ArmScene(
        model=scene.model,
        arm_joints=scene.arm_joints,
        arm_actuators=scene.arm_actuators,
        gripper_actuators=scene.gripper_actuators,
        gripper_joints=scene.gripper_joints,
        ee_site=scene.ee_site,
        base_body=scene.base_body,
        cameras=scene.cameras,
        home=_readonly(scene.home[3:]),
        visual_groups=scene.visual_groups,
        velocity_limit=_readonly(scene.limits.velocity[3:]),
        acceleration_limit=_readonly(scene.limits.acceleration[3:]),
        gripper_open=scene.gripper_open,
        gripper_closed=scene.gripper_closed,
        objects=scene.objects,
    )


def _whole_view(scene: TiagoScene) -> ArmScene:
    """All ten commanded joints (base first) in driver order: what the rig and cameras see."""
    return ArmScene(
        model=scene.model,
        arm_joints=scene.joints,
        arm_actuators=scene.base_actuators + scene.arm_actuators,
        gripper_actuators=scene.gripper_actuators,
        gripper_joints=scene.gripper_joints,
        ee_site=scene.ee_site,
        base_body=scene.base_body,
        cameras=scene.cameras,
        home=scene.home,
        visual_groups=scene.visual_groups,
        velocity_limit=scene.limits.velocity,
        acceleration_limit=scene.limits.acceleration,
        gripper_open=scene.gripper_open,
        gripper_closed=scene.gripper_closed,
        objects=scene.objects,
    )


def _wrap(angle: float) -> float:
    """``angle`` [rad] wrapped to [-pi, pi)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


class MujocoTiago(MujocoArm):
    """A simulated TIAGo implementing :class:`~telerig.robots.base.RobotDriver` and
    :class:`~telerig.robots.base.MobileBase` over ten joints: base x, y [m] (world axes), base yaw
    [rad], torso lift [m] and six arm joints [rad] (:data:`~telerig.robots.sim.tiago.TIAGO_JOINTS`).

    Torso, arm and gripper are :class:`MujocoArm`'s position servos (targets clipped to the joint
    ranges); the physics thread, stamps, e-stop latch and stepping are its too.

    The base is velocity-commanded, as a real holonomic base is (``cmd_vel``). Its position
    targets from :meth:`send` go through the safety chain like every other joint, and the driver
    turns them into velocity-servo commands: each target *step* ``Δ = target - previous target``
    is taken in the base frame of the previous target, re-expressed at the reference pose the
    base tracks, added to that reference, and fed forward as ``Δ / control_period_s``; a P term
    ``base_gain * (reference - measured)`` (yaw error wrapped) corrects drift. The result is
    clipped to the base speed limits and held until the next command, as a real base's velocity
    controller holds ``cmd_vel`` (send every control period; the control node does). A driver for
    a real base maps the same way, with odometry as the measurement. Because only steps matter,
    a base that was moved by :meth:`send_base` or stopped by the e-stop follows later position
    steps from where it is, without jumping back; with position commands alone the reference is
    exactly the commanded base pose.

    :meth:`send_base` adds a planar velocity in the base frame (controller-mode ``base_drive``);
    it is integrated into the reference over simulation time, so the base settles where the
    velocity took it when the command returns to zero.
    """

    def __init__(
        self,
        scene: TiagoScene | None = None,
        *,
        name: str = "tiago_sim",
        realtime: bool = True,
        max_catchup: int = 25,
        control_period_s: float = 0.01,
        base_gain: float = 5.0,
    ) -> None:
        """Create the driver (the physics starts on :meth:`connect`).

        Args:
            scene: Scene to simulate; :func:`~telerig.robots.sim.tiago.build_tiago_scene` when None.
            name: Driver name; the ``source_id`` of every stamp it produces.
            realtime: Step on a thread paced to the wall clock; False for :meth:`step`.
            max_catchup: Most steps the loop may run late before it drops the lag. >= 1.
            control_period_s: Period at which base targets arrive [s]: a target step is fed forward
                as the velocity ``step / control_period_s``. > 0.
            base_gain: P gain of the base position loop [1/s]; ``base_gain * control_period_s``
                must stay below 1 for the sampled loop to be stable. > 0.

        Raises:
            RobotError: the scene has no base or arm actuators (a kinematic model?).
            ValueError: ``control_period_s`` or ``base_gain`` is out of range.
        """
        tiago = scene if scene is not None else build_tiago_scene()
        if not tiago.arm_actuators or not tiago.base_actuators:
            raise RobotError("scene has no actuators (a kinematic model?); use build_tiago_scene()")
        if not (math.isfinite(control_period_s) and control_period_s > 0):
            raise ValueError(f"control_period_s must be > 0 s, got {control_period_s}")
        if not (math.isfinite(base_gain) and 0 < base_gain * control_period_s < 1):
            raise ValueError(
                f"base_gain must be > 0 and below 1 / control_period_s = {1 / control_period_s:g} 1/s, "
                f"got {base_gain}"
            )
        super().__init__(_arm_view(tiago), name=name, realtime=realtime, max_catchup=max_catchup)
        model = tiago.model
        self._tiago = tiago
        self._whole = _whole_view(tiago)
        self._all_qadr = tiago.qpos_indices()
        self._all_vadr = tiago.dof_indices()
        self._base_qadr = self._all_qadr[:3]
        self._base_vadr = self._all_vadr[:3]
        self._base_act = np.array([model.actuator(a).id for a in tiago.base_actuators])
        self._all_act = np.concatenate(
            (self._base_act, [model.actuator(a).id for a in tiago.arm_actuators])
        ).astype(int)
        self._base_vmax = model.actuator_ctrlrange[self._base_act, 1].copy()
        self._base_body = model.body(_BASE_LINK).id
        at_rest = mujoco.MjData(model)
        mujoco.mj_kinematics(model, at_rest)
        self._base_height = float(at_rest.xpos[self._base_body][2])
        self._period = float(control_period_s)
        self._gain = float(base_gain)
        self._joint_index = {j: i for i, j in enumerate(tiago.joints)}
        # Base servo state, guarded by the physics lock: the pose the servo tracks (world x, y [m],
        # yaw [rad]), the last position target received, the base-frame velocity from send_base
        # (vx, vy [m/s], wz [rad/s]) and the simulation time the reference was last advanced [s].
        self._ref = np.array(tiago.home[:3], dtype=np.float64)
        self._last_target = self._ref.copy()
        self._twist = np.zeros(3)
        self._t_ref = 0.0
        self._all_seq = 0
        self._send_seq = 0
        self._base_seq = 0

    # -- RobotDriver ------------------------------------------------------------------------

    @property
    def joint_names(self) -> tuple[str, ...]:
        """Base x, y, yaw, torso lift, six arm joints (:data:`~telerig.robots.sim.tiago.TIAGO_JOINTS`)."""
        return self._tiago.joints

    @property
    def limits(self) -> JointLimits:
        """The scene's limits: infinite position limits on the base, joint ranges elsewhere."""
        return self._tiago.limits

    @property
    def scene(self) -> ArmScene:
        """The whole robot (ten joints in driver order, ten-joint ``home``) with its cameras."""
        return self._whole

    @property
    def tiago(self) -> TiagoScene:
        """The simulated TIAGo scene (model, names, limits)."""
        return self._tiago

    def read_state(self) -> JointState:
        """Positions [m or rad], velocities [m/s or rad/s] and actuator forces [N or N m] of the ten joints.

        Base x/y and their velocities are in world axes. Stamped with the wall time of the latest
        physics step (``capture_ns``) and the simulation clock (``device_ns``).
        """
        self._require_connected()
        physics = self.physics
        with physics.lock:
            data = physics.data
            positions = data.qpos[self._all_qadr].copy()
            velocities = data.qvel[self._all_vadr].copy()
            efforts = data.actuator_force[self._all_act].copy()
            device_ns = round(data.time * 1e9)
            capture_ns = physics.read_stamp()
            seq = self._all_seq
            self._all_seq += 1
        stamp = Stamp(self.name, seq, device_ns=device_ns, capture_ns=capture_ns)
        return JointState(stamp, self.joint_names, positions, velocities, efforts)

    def send(self, command: JointCommand) -> JointCommand:
        """Set targets for the named joints (any subset, any order): torso and arm positions, base pose.

        Arm and torso targets are clipped to the joint ranges; base targets become velocity-servo
        commands (see the class docstring). While the e-stop is latched nothing moves and the held
        targets are returned (the base's is where it stopped).

        Returns:
            The targets in force for ``command.names`` after the call (base: the pose its servo
            tracks), stamped at that moment.

        Raises:
            RobotError: a joint name is unknown, or the driver is not connected.
        """
        self._require_connected()
        try:
            idx = np.array([self._joint_index[n] for n in command.names], dtype=int)
        except KeyError as exc:
            raise RobotError(
                f"{self.name}: joint {exc.args[0]!r} not found. Available: {', '.join(self.joint_names)}"
            ) from None
        positions = np.asarray(command.positions, dtype=np.float64)
        applied = np.empty(len(idx))
        arm = idx >= 3
        if np.any(arm):
            names = tuple(n for n, a in zip(command.names, arm, strict=True) if a)
            sent = super().send(JointCommand(command.stamp, names, positions[arm]))
            applied[arm] = sent.positions
        base = ~arm
        if np.any(base):
            with self.physics.lock:
                target = self._last_target.copy()
                target[idx[base]] = positions[base]
                reference = self._servo_base(target)
            applied[base] = reference[idx[base]]
        t = time.time_ns()
        seq = self._send_seq
        self._send_seq += 1
        return JointCommand(Stamp(self.name, seq, device_ns=t, capture_ns=t), command.names, applied)

    def send_base(self, command: BaseVelocity) -> BaseVelocity:
        """Drive the base at a planar velocity in its own frame: ``vx`` forward, ``vy`` left [m/s],
        ``wz`` counter-clockwise [rad/s], each clipped to the base speed limit.

        The velocity holds until the next call (send zero to stop); it adds to what position
        targets from :meth:`send` command. While the e-stop is latched the base stays stopped.

        Returns:
            The velocity applied (zero while e-stopped), stamped at that moment.

        Raises:
            RobotError: the driver is not connected.
        """
        self._require_connected()
        wanted = np.array([command.vx, command.vy, command.wz], dtype=np.float64)
        if not np.all(np.isfinite(wanted)):
            wanted = np.zeros(3)  # the safety layer rejects these; never turn NaN into motion
        twist = np.clip(wanted, -self._base_vmax, self._base_vmax)
        with self.physics.lock:
            self._servo_base(None)  # advance the reference under the old velocity first
            self._twist = np.zeros(3) if self.estopped else twist
            self._servo_base(None)
            applied = self._twist.copy()
            seq = self._base_seq
            self._base_seq += 1
            t = time.time_ns()
        return BaseVelocity(
            Stamp(self.name, seq, t, t), float(applied[0]), float(applied[1]), float(applied[2])
        )

    def estop(self) -> None:
        """Latch the emergency stop: arm and torso hold, the base velocity servos brake to a stop.

        The gripper keeps its last command, so a held object is not dropped.
        """
        super().estop()
        with self.physics.lock:
            self._twist = np.zeros(3)
            self._servo_base(None)

    def reset_estop(self) -> None:
        """Release the emergency stop; the base holds where it stopped until the next target step."""
        with self.physics.lock:
            self._ref = self._measured_base()
            self._t_ref = float(self.physics.data.time)
        super().reset_estop()

    def close(self) -> None:
        """Stop the base and release the driver; the physics stops with its last driver. Idempotent."""
        with self.physics.lock:
            self._twist = np.zeros(3)
            self.physics.data.ctrl[self._base_act] = 0.0
        super().close()

    @property
    def standing_height_m(self) -> float:
        """Height [m] of ``base_link`` (TIAGo's ROS base frame) above the floor; the base rides at it."""
        return self._base_height

    @property
    def floating_base(self) -> bool:
        """False: the base rides on planar joints at a fixed height (its x, y, yaw are joints)."""
        return False

    def read_base_pose(self) -> Pose:
        """The pose of ``base_link`` in the world frame, stamped like :meth:`read_state`.

        Raises:
            RobotError: the driver is not connected.
        """
        return self._body_pose(self._base_body)

    def base_pose(self) -> FloatArray:
        """Measured base pose: world x, y [m] and yaw [rad]. Shape (3,).

        Raises:
            RobotError: the driver is not connected.
        """
        self._require_connected()
        with self.physics.lock:
            return self._measured_base()

    # -- internals ----------------------------------------------------------------------------

    def _go_home(self, data: mujoco.MjData) -> None:
        """Arm at home, gripper open, base at its home pose and stopped (called under the lock)."""
        super()._go_home(data)
        home = np.array(self._tiago.home[:3], dtype=np.float64)
        data.qpos[self._base_qadr] = home
        data.qvel[self._base_vadr] = 0.0
        data.ctrl[self._base_act] = 0.0
        self._ref = home.copy()
        self._last_target = home.copy()
        self._twist = np.zeros(3)
        self._t_ref = float(data.time)

    def _measured_base(self) -> FloatArray:
        """Base pose from the physics data (call under the lock). Shape (3,)."""
        out: FloatArray = self.physics.data.qpos[self._base_qadr].copy()
        return out

    def _servo_base(self, target: FloatArray | None) -> FloatArray:
        """Advance the base reference and set the base velocity servos (call under the lock).

        Args:
            target: New base position target (world x, y [m], yaw [rad]); None to only integrate
                the ``send_base`` velocity up to now. Shape (3,).

        Returns:
            The reference pose the servo now tracks. Shape (3,).
        """
        data = self.physics.data
        now = float(data.time)
        dt = max(0.0, now - self._t_ref)
        self._t_ref = now
        ref = self._ref
        vx, vy, wz = self._twist
        if dt > 0.0 and (vx or vy or wz):
            yaw = ref[2] + 0.5 * wz * dt  # midpoint heading: exact for constant velocities to O(dt^3)
            c, s = math.cos(yaw), math.sin(yaw)
            ref[0] += (c * vx - s * vy) * dt
            ref[1] += (s * vx + c * vy) * dt
            ref[2] += wz * dt
        feed = np.zeros(3)
        if target is not None:
            step = target - self._last_target
            self._last_target = target.copy()
            if not self.estopped and np.any(step):
                # The step as the command meant it (in the base frame of the previous target),
                # applied at the pose the base is actually tracking.
                turn = ref[2] - (target[2] - step[2])
                c, s = math.cos(turn), math.sin(turn)
                world = np.array([c * step[0] - s * step[1], s * step[0] + c * step[1], step[2]])
                ref += world
                feed = world / self._period
        measured = self._measured_base()
        if self.estopped:
            self._ref = measured
            data.ctrl[self._base_act] = 0.0
            return measured.copy()
        c, s = math.cos(measured[2]), math.sin(measured[2])
        feed += np.array([c * vx - s * vy, s * vx + c * vy, wz])
        error = ref - measured
        error[2] = _wrap(float(error[2]))
        data.ctrl[self._base_act] = np.clip(feed + self._gain * error, -self._base_vmax, self._base_vmax)
        return ref.copy()
