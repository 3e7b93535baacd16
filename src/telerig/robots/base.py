"""The robot driver interface: what every simulated and real robot implements."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from telerig.ir.types import BaseVelocity, FloatArray, GripperCommand, JointCommand, JointState, Pose, Wrench

__all__ = [
    "EpisodicTask",
    "GripperSensor",
    "JointLimits",
    "MobileBase",
    "ObjectSensor",
    "RobotDriver",
    "StandingRobot",
    "TaskCheck",
    "WrenchSensor",
]


@dataclass(frozen=True, slots=True)
class JointLimits:
    """Limits of the commanded joints, in driver joint order.

    Attributes:
        names: Joint names. Length n.
        lower: Lower position limits [rad]. Shape (n,).
        upper: Upper position limits [rad]. Shape (n,).
        velocity: Maximum speed [rad/s]. Shape (n,).
        acceleration: Maximum acceleration [rad/s^2]. Shape (n,).
    """

    names: tuple[str, ...]
    lower: FloatArray
    upper: FloatArray
    velocity: FloatArray
    acceleration: FloatArray

    def __post_init__(self) -> None:
        n = len(self.names)
        for attr in ("lower", "upper", "velocity", "acceleration"):
            arr = np.array(getattr(self, attr), dtype=np.float64)
            if arr.shape != (n,):
                raise ValueError(f"{attr} must have shape ({n},), got {arr.shape}")
            arr.flags.writeable = False
            object.__setattr__(self, attr, arr)
        if np.any(self.lower > self.upper):
            raise ValueError("lower limits must not exceed upper limits")
        if np.any(self.velocity <= 0) or np.any(self.acceleration <= 0):
            raise ValueError("velocity and acceleration limits must be positive")


@runtime_checkable
class RobotDriver(Protocol):
    """A robot telerig can command. Simulated and real drivers alike.

    Drivers never filter for safety themselves; the safety chain in front of
    them does. ``send`` and ``send_gripper`` return the command the driver
    actually applied (clipped to actuator range, stamped at the moment of
    application), which is what gets recorded next to the request.
    """

    @property
    def name(self) -> str: ...

    @property
    def joint_names(self) -> tuple[str, ...]:
        """Arm joints commanded by :meth:`send`, in order."""
        ...

    @property
    def limits(self) -> JointLimits: ...

    def connect(self) -> None:
        """Open the connection / start the simulation. Idempotent."""
        ...

    def read_state(self) -> JointState:
        """Latest measured joint state, stamped with its measurement time."""
        ...

    def send(self, command: JointCommand) -> JointCommand:
        """Apply joint position targets; return what was actually applied."""
        ...

    @property
    def has_gripper(self) -> bool:
        """Whether :meth:`send_gripper` moves something (a gripper, or a hand's open/close synergy).

        The runtime refuses a rig that binds a gripper input to a robot without one.
        """
        ...

    def send_gripper(self, command: GripperCommand) -> GripperCommand:
        """Apply a gripper opening; return what was actually applied.

        Raises ``RobotError`` naming the fix on a robot without a gripper (:attr:`has_gripper`).
        """
        ...

    def estop(self) -> None:
        """Emergency stop: hold position with actuators disabled or braked. Latches until reset."""
        ...

    def close(self) -> None:
        """Stop and release the robot. Idempotent."""
        ...


@runtime_checkable
class MobileBase(Protocol):
    """Optional capability of a driver with a wheeled base, commanded by planar velocity.

    The control node drives the base of a robot whose driver has this method (checked with
    ``isinstance``); drivers without a base need not implement it.
    """

    def send_base(self, command: BaseVelocity) -> BaseVelocity:
        """Apply a base velocity (base frame); return what was applied (clipped, stamped when applied)."""
        ...


@runtime_checkable
class GripperSensor(Protocol):
    """Optional capability of a driver that measures its gripper's opening (the ``gripper_state``
    stream); checked with ``isinstance`` together with :attr:`RobotDriver.has_gripper`."""

    def read_gripper(self) -> GripperCommand:
        """The measured opening (0 closed, 1 open; ``max_force`` 0), stamped at its measurement."""
        ...


@runtime_checkable
class WrenchSensor(Protocol):
    """Optional capability of a driver with a force/torque sensor (wrist F/T, or contact forces):
    the ``wrench`` stream."""

    @property
    def has_wrench_sensor(self) -> bool:
        """Whether this robot has the sensor (a driver class may serve robots with and without)."""
        ...

    def read_wrench(self) -> Wrench:
        """The load's force [N] and torque [N m] in the sensor frame, stamped at its measurement."""
        ...


@runtime_checkable
class StandingRobot(Protocol):
    """Optional capability of a humanoid or a mobile base: the height it stands at, and the pose of
    its pelvis or base when that is free to move (the fall gate's reference and measurement)."""

    @property
    def standing_height_m(self) -> float:
        """Height [m] of the pelvis (humanoid) or base (mobile robot) above the floor when standing."""
        ...

    @property
    def floating_base(self) -> bool:
        """Whether the pelvis or base can leave its standing height (:meth:`read_base_pose` then
        measures it); False when it is fixed or rides at a fixed height."""
        ...

    def read_base_pose(self) -> Pose:
        """The pelvis or base pose in the world frame (z up, floor at 0), stamped at its measurement."""
        ...


@runtime_checkable
class ObjectSensor(Protocol):
    """Optional capability of a simulated scene that observes its task objects (the ``object_pose``
    stream: one pose per object per control tick, ``stamp.source_id`` ``<robot>/<object>``)."""

    @property
    def observed_objects(self) -> tuple[str, ...]:
        """The objects whose poses go on ``object_pose``, e.g. ``("cube", "target")``; may be empty."""
        ...

    def read_object_pose(self, name: str) -> Pose:
        """Pose of object ``name`` in the world frame (z up), stamped at its measurement."""
        ...


@dataclass(frozen=True, slots=True)
class TaskCheck:
    """A task's success judged from the scene state at one moment.

    Attributes:
        success: Whether every condition holds.
        reason: One line: ``"ok"`` or the first condition that fails and by how much.
        values: The measured quantities behind it (units in their names, e.g. ``gripper_opening``,
            ``cube_offset_m``, ``joint_speed_rad_s``).
    """

    success: bool
    reason: str
    values: Mapping[str, float] = field(default_factory=dict)


@runtime_checkable
class EpisodicTask(Protocol):
    """Optional capability of a simulated scene with a randomized task: each episode the runtime
    resets it from a seed, and judges success from the scene state (never from the operator)."""

    @property
    def task_seed(self) -> int:
        """The configured base seed: episode ``k`` of a run uses seed ``task_seed + k``."""
        ...

    def begin_task(self, seed: int) -> Mapping[str, object]:
        """Put the task objects at the poses drawn from ``seed`` (at rest); returns what was drawn
        (JSON-ready: seed, object poses, target) for the episode's manifest."""
        ...

    def check_task(self) -> TaskCheck:
        """Judge the task from the scene state now; reads nothing that stamps a stream."""
        ...
