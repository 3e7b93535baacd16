"""How a rig binding becomes control-loop parts: the retargeter protocols and what a config binds.

A rig binding names a device part, a robot and a robot target (``arm``, ``hand``, ``body``,
``gripper``, ``base``, ...). Its retargeter config turns it into :class:`Bound` parts through
``RetargeterConfig.bind(context)``; the runtime merges the parts of every binding of a robot
into that robot's control node. New retargeters plug in by implementing ``bind`` on their
config: neither the runtime nor the control node changes.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Protocol

from pydantic import JsonValue

from telerig.bus.topics import Topic
from telerig.errors import ConfigError
from telerig.ir.types import FloatArray, GripperCommand, JointCommand, Sample
from telerig.retarget.base_drive import BaseDrive
from telerig.robots.base import RobotDriver

__all__ = ["Aid", "BindContext", "Bound", "GripperRetargeter", "Residual", "Retargeter"]


class Residual(Protocol):
    """How well a retargeting step reached its target (e.g. :class:`~telerig.retarget.arm_ik.IKResult`)."""

    @property
    def flagged(self) -> bool:
        """True when the target was not reached within the retargeter's threshold."""
        ...

    def metrics(self) -> Mapping[str, float]:
        """Per-task errors to record every tick, e.g. ``{"position_error_m": 0.002}`` (SI units)."""
        ...


class Retargeter(Protocol):
    """One device stream → joint targets for the robot's commanded joints, called once per fresh sample.

    Implementations: arm pose IK (:class:`~telerig.retarget.arm.ArmPoseRetargeter`), dexterous hand
    vectors, humanoid body IK, the whole-body controller. It runs on the control thread and its
    output always goes through the robot's safety chain.
    """

    @property
    def accepts(self) -> tuple[type, ...]:
        """Sample classes it takes; the node counts other samples as wrong-type input and skips them."""
        ...

    def __call__(
        self, sample: Sample, q_current: FloatArray, dt: float
    ) -> tuple[JointCommand | None, Residual | None]:
        """Joint targets for ``sample`` (stamped with its stamp, joints in driver order) or None to send
        nothing this tick; and the residual, or None when no target was solved for.

        Args:
            sample: An instance of one of :attr:`accepts`.
            q_current: Last command sent to the driver [rad]. Shape (n,).
            dt: Control period [s].
        """
        ...

    def reset(self) -> None:
        """Forget anchors and filter state; called while the node drives the robot home."""
        ...


class GripperRetargeter(Protocol):
    """A device sample → gripper opening, or None when the sample carries nothing for the gripper."""

    def __call__(self, sample: Sample) -> GripperCommand | None: ...


class Aid(Protocol):
    """A live supervisory control (e.g. :class:`~telerig.retarget.scaling.ScaleKnob`,
    :class:`~telerig.retarget.fixtures.FixtureSet`) the node feeds and publishes."""

    #: Stream its state is published on (retained JSON); commands arrive on ``<stream>_command``.
    stream: str

    def update(self, sample: Sample) -> bool:
        """Take one device sample (buttons); return whether the state changed."""
        ...

    def command(self, text: str) -> bool:
        """Take one text command; return whether the state changed. ``ValueError`` when invalid."""
        ...

    def state(self) -> dict[str, JsonValue]:
        """The state a UI shows, as JSON values."""
        ...


@dataclass(frozen=True, slots=True)
class BindContext:
    """What a retargeter config gets to bind one rig binding.

    Attributes:
        rig: Rig name (topic prefix).
        robot_id: The bound robot's id in the rig.
        robot: The robot's driver (built and connected).
        target: The binding's robot target, e.g. ``"arm"``.
        device: The binding's device id.
        part: The binding's device part (stream name).
        devices: Ids of every device of the rig (for aids fed by another device).
        drives: ``(device, robot)`` of every binding of the rig (which robots a device drives).
    """

    rig: str
    robot_id: str
    robot: RobotDriver
    target: str
    device: str
    part: str
    devices: tuple[str, ...]
    drives: tuple[tuple[str, str], ...] = ()

    @property
    def where(self) -> str:
        """The binding, for error messages: ``binding vr0.right_controller → arm0.arm``."""
        return f"binding {self.device}.{self.part} → {self.robot_id}.{self.target}"

    @property
    def topic(self) -> str:
        """The bound device stream's topic."""
        return str(Topic(self.rig, self.device, self.part))

    def topic_of(self, device: str | None, part: str | None, *, what: str) -> str:
        """Topic of another device stream (defaults: this binding's); ``what`` names the field in errors."""
        device = device or self.device
        if device not in self.devices:
            raise ConfigError(
                f"{self.where}: {what}.device {device!r} is not a device of this rig. "
                f"Available: {', '.join(self.devices)}"
            )
        return str(Topic(self.rig, device, part or self.part))

    def require_target(self, retargeter: str, *valid: str) -> None:
        """Raise a one-line ConfigError unless the binding's target is one of ``valid``."""
        if self.target not in valid:
            raise ConfigError(
                f"{self.where}: retargeter {retargeter!r} cannot drive target {self.target!r}. "
                f"Valid: {', '.join(valid)}"
            )


@dataclass(slots=True)
class Bound:
    """Control-loop parts one binding contributes to its robot's control node.

    Attributes:
        joints: Drives the robot's commanded joints (at most one per robot).
        gripper: Drives the robot's gripper (at most one per robot).
        base: Drives a wheeled base (at most one per robot).
        aids: Live aids and the topics whose button samples operate them.
        feeds: Device stream topics and what takes their latest sample each tick (e.g. a
            :class:`~telerig.retarget.reach_plan.PlanMarker`: kept, not acted on, on the tick).
    """

    joints: Retargeter | None = None
    gripper: GripperRetargeter | None = None
    base: BaseDrive | None = None
    aids: list[tuple[str, Aid]] = field(default_factory=list)
    feeds: list[tuple[str, Callable[[Sample], None]]] = field(default_factory=list)
