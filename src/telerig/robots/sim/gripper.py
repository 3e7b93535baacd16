"""MuJoCo Robotiq 2F-85 on a fixed mount over a table: a 1-DoF industrial gripper driver and its scene."""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass
from types import TracebackType

import mujoco
import numpy as np

from telerig.errors import RobotError
from telerig.ir.types import GripperCommand, JointCommand, JointState, Stamp
from telerig.robots.base import JointLimits
from telerig.robots.models.arm import load_gripper
from telerig.robots.models.arms import ROBOTIQ_2F85, GripperModel
from telerig.robots.models.mjcf import VISUAL_GROUPS, compile_spec, set_physics_options
from telerig.robots.sim import objects
from telerig.robots.sim.arm import SimDriverLink, SimPhysics, SimStats
from telerig.robots.sim.scene import (
    TABLE_TOP,
    actuate_gripper,
    add_room,
    add_table,
)

__all__ = ["GripperScene", "MujocoGripper", "build_gripper_scene"]

_PREFIX = "gripper/"
_TIMESTEP = 0.002  # [s]
_CUBE_HALF = 0.025  # [m]: a 5 cm cube fits the 2F-85's 85 mm stroke
_GRIP_HEIGHT = TABLE_TOP + _CUBE_HALF  # grip site at the cube's centre [m], world frame


@dataclass(frozen=True, slots=True)
class GripperScene:
    """A compiled gripper-alone scene and the names its driver needs.

    Attributes:
        model: The compiled MuJoCo model.
        gripper: The gripper's description (actuators, joints, open/closed targets, limits).
        joint: The commanded finger joint (the leader of the linkage) [rad]; 0 = open.
        actuators: Finger servos; each gets the same target (the fingers mirror each other).
        grip_site: Site between the finger pads, over the cube's centre.
        cameras: Camera names, scene camera first.
        objects: Free bodies of the task object set.
        visual_groups: Geom groups a camera should draw.
    """

    model: mujoco.MjModel
    gripper: GripperModel
    joint: str
    actuators: tuple[str, ...]
    grip_site: str
    cameras: tuple[str, ...]
    objects: tuple[str, ...]
    visual_groups: tuple[int, ...] = VISUAL_GROUPS


def build_gripper_scene(*, with_cube: bool = True, timestep: float = _TIMESTEP) -> GripperScene:
    """Build a Robotiq 2F-85 pointing down from a fixed mount, its pads around a 5 cm cube on a table.

    The table top is at z = 0.8 m (world frame, z up); the grip site is 2.5 cm above it at the
    world's x-y origin, fingers closing along the world y axis.

    Args:
        with_cube: Add the free cube (body ``cube``) between the open fingers.
        timestep: Physics timestep [s].

    Raises:
        DependencyError: robosuite (the model source) is not installed.
        RobotError: a model file is missing or does not compile.
    """
    if not 0 < timestep <= 0.01:
        raise ValueError(
            f"timestep must be in (0, 0.01] s for the finger servos to be stable, got {timestep}"
        )
    model = ROBOTIQ_2F85
    spec = mujoco.MjSpec()
    spec.modelname = "robotiq_2f85_bench"
    spec.compiler.degree = False
    set_physics_options(spec, timestep)
    add_room(spec)
    add_table(spec, (0.0, 0.0), (0.3, 0.3))
    grip_offset = 0.145  # adapter to grip site along the gripper's z [m] (robosuite's eef body)
    # Pointing down: the gripper's z axis (out of the palm) along world -z.
    mount = spec.worldbody.add_body(
        name="mount", pos=[0.0, 0.0, _GRIP_HEIGHT + grip_offset], quat=[0, 1, 0, 0]
    )
    mount.add_geom(
        name="mount_post",
        type=mujoco.mjtGeom.mjGEOM_CYLINDER,
        size=[0.03, 0.15, 0],
        pos=[0, 0, -0.15],
        rgba=[0.3, 0.3, 0.32, 1.0],
        group=VISUAL_GROUPS[1],
        contype=0,
        conaffinity=0,
    )
    gripper = load_gripper(model, actuated=True)
    mount.add_frame().attach_body(gripper.body(model.root_body), _PREFIX, "")
    actuate_gripper(spec, model, _PREFIX)
    bodies = (objects.add_cube(spec, "cube", (0.0, 0.0, TABLE_TOP), half=_CUBE_HALF),) if with_cube else ()
    spec.worldbody.add_camera(
        name="scene", pos=[0.45, 0.3, 1.05], xyaxes=[-0.55, 0.83, 0, -0.25, -0.17, 0.95], fovy=45
    )
    compiled = compile_spec(spec)
    cameras = tuple(compiled.camera(i).name for i in range(compiled.ncam))
    return GripperScene(
        model=compiled,
        gripper=model,
        joint=_PREFIX + model.joints[0],
        actuators=tuple(_PREFIX + a for a in model.actuators),
        grip_site=_PREFIX + model.grip_site,
        cameras=tuple(sorted(cameras, key=lambda c: c != "scene")),
        objects=bodies,
    )


class MujocoGripper:
    """A simulated parallel gripper alone, implementing :class:`~telerig.robots.base.RobotDriver`.

    Its one joint is the finger angle of the 2F-85's linkage [rad]: 0 fully open (85 mm), 0.8
    closed. :meth:`send` sets it directly; :meth:`send_gripper` maps the normalized opening onto
    it (1 = open). Both fingers get the same target. Physics runs as in
    :class:`~telerig.robots.sim.arm.MujocoArm` (real time on a thread, or :meth:`step`).
    """

    def __init__(
        self,
        scene: GripperScene | None = None,
        *,
        name: str = "gripper_sim",
        realtime: bool = True,
        max_catchup: int = 25,
    ) -> None:
        """Create the driver (the physics starts on :meth:`connect`).

        Args:
            scene: Scene to simulate; :func:`build_gripper_scene` when None.
            name: Driver name; the ``source_id`` of every stamp it produces.
            realtime: Step on a thread paced to the wall clock; False for :meth:`step`.
            max_catchup: Most steps the loop may run late before it drops the lag. >= 1.
        """
        self._scene = scene if scene is not None else build_gripper_scene()
        model = self._scene.model
        self._physics = SimPhysics(model, name=name, realtime=realtime, max_catchup=max_catchup)
        self._name = name
        self._model = model
        self._data = self._physics.data
        self._lock = self._physics.lock
        joint = model.joint(self._scene.joint)
        self._qadr = int(joint.qposadr[0])
        self._vadr = int(joint.dofadr[0])
        self._act = np.array([model.actuator(a).id for a in self._scene.actuators])
        self._open = np.array(self._scene.gripper.open_ctrl)
        self._closed = np.array(self._scene.gripper.closed_ctrl)
        lo, hi = (float(v) for v in model.jnt_range[joint.id])
        self._lo, self._hi = lo, hi
        self._limits = JointLimits(
            names=(self._scene.joint,),
            lower=np.array([lo]),
            upper=np.array([hi]),
            velocity=np.array([self._scene.gripper.velocity]),
            acceleration=np.array([self._scene.gripper.acceleration]),
        )
        self._physics.attach(self._init)
        self._link = SimDriverLink(self._physics, name)
        self._cmd_seq = 0
        self._grip_seq = 0
        self._state_seq = 0
        self._grip_state_seq = 0

    @property
    def physics(self) -> SimPhysics:
        """The physics this driver steps."""
        return self._physics

    @property
    def name(self) -> str:
        """Driver name, used as the stamps' ``source_id``."""
        return self._name

    @property
    def joint_names(self) -> tuple[str, ...]:
        """The one finger joint commanded by :meth:`send`."""
        return (self._scene.joint,)

    @property
    def limits(self) -> JointLimits:
        """Finger joint range [rad], datasheet finger speed [rad/s] and acceleration [rad/s^2]."""
        return self._limits

    @property
    def scene(self) -> GripperScene:
        """The simulated scene (model and names)."""
        return self._scene

    @property
    def estopped(self) -> bool:
        """Whether the emergency stop is latched."""
        return self._link.estopped

    def connect(self) -> None:
        """Reset the scene with the gripper open and start the physics. Idempotent.

        Raises:
            RobotError: the driver was closed.
        """
        self._link.connect()

    def read_state(self) -> JointState:
        """Finger joint position [rad], velocity [rad/s] and the first finger servo's torque [N m].

        Stamped with the wall time of the latest physics step and the simulation clock.
        """
        self._require_connected()
        with self._lock:
            data = self._data
            positions = np.array([data.qpos[self._qadr]])
            velocities = np.array([data.qvel[self._vadr]])
            efforts = np.array([data.actuator_force[self._act[0]]])
            device_ns = round(data.time * 1e9)
            capture_ns = self._physics.read_stamp()
            seq = self._state_seq
            self._state_seq += 1
        stamp = Stamp(self._name, seq, device_ns=device_ns, capture_ns=capture_ns)
        return JointState(stamp, self.joint_names, positions, velocities, efforts)

    def send(self, command: JointCommand) -> JointCommand:
        """Set the finger joint target [rad], clipped to its range; ignored while the e-stop is latched.

        Returns:
            The target in force after the call, stamped at that moment.

        Raises:
            RobotError: the joint name is not the gripper's, or the driver is not connected.
        """
        self._require_connected()
        if command.names != self.joint_names:
            raise RobotError(
                f"{self._name}: joints {command.names} not found. Available: {self._scene.joint}"
            )
        target = float(np.clip(command.positions[0], self._lo, self._hi))
        with self._lock:
            if not self._link.estopped:
                self._data.ctrl[self._act] = target
            applied = float(self._data.ctrl[self._act[0]])
            seq = self._cmd_seq
            self._cmd_seq += 1
            t = time.time_ns()
        return JointCommand(
            Stamp(self._name, seq, device_ns=t, capture_ns=t), self.joint_names, np.array([applied])
        )

    @property
    def has_gripper(self) -> bool:
        """Always: this robot is a gripper (or a hand with an open/close synergy)."""
        return True

    def send_gripper(self, command: GripperCommand) -> GripperCommand:
        """Set the opening (0 closed, 1 open; clipped to [0, 1]); ignored while the e-stop is latched.

        ``max_force`` is not simulated: the returned command has 0 (the default).

        Raises:
            RobotError: the driver is not connected.
        """
        self._require_connected()
        opening = float(np.clip(command.opening, 0.0, 1.0))
        span = self._open - self._closed
        with self._lock:
            if not self._link.estopped:
                self._data.ctrl[self._act] = self._closed + opening * span
            applied = float(np.mean((self._data.ctrl[self._act] - self._closed) / span))
            seq = self._grip_seq
            self._grip_seq += 1
            t = time.time_ns()
        return GripperCommand(Stamp(self._name, seq, device_ns=t, capture_ns=t), opening=applied)

    def read_gripper(self) -> GripperCommand:
        """The measured opening (0 closed, 1 open): the finger joint mapped like :meth:`send_gripper`'s
        targets (both fingers share the joint's servo targets), clipped to [0, 1]; stamped like
        :meth:`read_state`.

        Raises:
            RobotError: the driver is not connected.
        """
        self._require_connected()
        closed, span = float(self._closed[0]), float(self._open[0] - self._closed[0])
        with self._lock:
            opening = (float(self._data.qpos[self._qadr]) - closed) / span
            device_ns = round(self._data.time * 1e9)
            capture_ns = self._physics.step_ns
            seq = self._grip_state_seq
            self._grip_state_seq += 1
        stamp = Stamp(self._name, seq, device_ns=device_ns, capture_ns=capture_ns)
        return GripperCommand(stamp, opening=min(1.0, max(0.0, opening)))

    def estop(self) -> None:
        """Latch the emergency stop: the fingers hold where they are (a held object stays held)."""

        def hold(data: mujoco.MjData) -> None:
            held = float(np.clip(data.qpos[self._qadr], self._lo, self._hi))
            # Hold at least the commanded grip: stopping never loosens a grasp.
            data.ctrl[self._act] = np.maximum(data.ctrl[self._act], held)

        self._link.latch(hold)

    def reset_estop(self) -> None:
        """Release the emergency stop."""
        self._link.reset_estop()

    def close(self) -> None:
        """Stop the physics and release the driver. Idempotent."""
        self._link.close()

    def step(self, n: int = 1) -> None:
        """Advance the physics by ``n`` timesteps (``realtime=False`` only).

        Raises:
            RobotError: the driver runs in real time or is not connected.
        """
        self._link.step(n)

    def reset_objects(self) -> None:
        """Put the task objects back at their initial poses, at rest; the fingers are not touched."""
        self._physics.reset_objects()

    def locked(self) -> contextlib.AbstractContextManager[tuple[mujoco.MjModel, mujoco.MjData]]:
        """Hold the physics lock and yield ``(model, data)``; keep the block short."""
        return self._physics.locked()

    def stats(self) -> SimStats:
        """Physics-loop statistics since :meth:`connect`."""
        return self._physics.stats()

    def __enter__(self) -> MujocoGripper:
        self.connect()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def _init(self, data: mujoco.MjData) -> None:
        data.ctrl[self._act] = self._open

    def _require_connected(self) -> None:
        self._link.require_connected()
