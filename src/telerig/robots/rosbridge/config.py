"""Config of the rosbridge robot driver (registered as ``type: rosbridge``)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import Field, field_validator, model_validator

from telerig.config.schema import RobotConfig
from telerig.registry import ROBOTS

if TYPE_CHECKING:
    from telerig.robots.base import JointLimits
    from telerig.robots.rosbridge.driver import RosbridgeRobot

__all__ = ["RosbridgeConfig"]

Seconds = Annotated[float, Field(gt=0, le=60)]


@ROBOTS.register
class RosbridgeConfig(RobotConfig):
    """Any ROS robot through rosbridge_server: JointState in, JointTrajectory or Float64MultiArray out.

    ``joint_names`` are the robot's joint names as its JointState publishes them; ``lower`` /
    ``upper`` [rad] have one value per joint, ``velocity`` [rad/s] and ``acceleration``
    [rad/s^2] one per joint or one for all. For ``command_type: std_msgs/Float64MultiArray``
    list the joints in the controller's order. To dry-run a rig, point ``url`` at a running
    :class:`~telerig.robots.rosbridge.fake.FakeRosbridge`.
    """

    type: Literal["rosbridge"] = "rosbridge"
    url: str = "ws://127.0.0.1:9090"
    joint_names: tuple[str, ...]
    lower: tuple[float, ...]
    upper: tuple[float, ...]
    velocity: float | tuple[float, ...]
    acceleration: float | tuple[float, ...]
    state_topic: str = "/joint_states"
    command_topic: str = "/joint_trajectory_controller/joint_trajectory"
    command_type: Literal["trajectory_msgs/JointTrajectory", "std_msgs/Float64MultiArray"] = (
        "trajectory_msgs/JointTrajectory"
    )
    trajectory_time_s: Seconds = 0.1
    estop_topic: str | None = None
    timeout_s: Seconds = 2.0
    stale_timeout_s: Seconds = 0.5
    reconnect_s: Seconds = 0.5

    @field_validator("url")
    @classmethod
    def _ws_url(cls, value: str) -> str:
        if not value.startswith(("ws://", "wss://")):
            raise ValueError(
                f"url must start with ws:// or wss://, e.g. ws://192.168.1.10:9090; got {value!r}"
            )
        return value

    @model_validator(mode="after")
    def _limits_match(self) -> RosbridgeConfig:
        n = len(self.joint_names)
        if n == 0 or len(set(self.joint_names)) != n:
            raise ValueError("joint_names must list each joint once")
        for label in ("lower", "upper", "velocity", "acceleration"):
            value = getattr(self, label)
            if isinstance(value, tuple) and len(value) != n:
                raise ValueError(f"{label} has {len(value)} values for {n} joint_names")
        try:
            self.joint_limits()
        except ValueError as exc:
            raise ValueError(str(exc)) from None
        return self

    def joint_limits(self) -> JointLimits:
        """The limits as :class:`~telerig.robots.base.JointLimits` [rad], [rad/s], [rad/s^2]."""
        import numpy as np

        from telerig.robots.base import JointLimits

        n = len(self.joint_names)
        return JointLimits(
            names=self.joint_names,
            lower=np.array(self.lower),
            upper=np.array(self.upper),
            velocity=np.broadcast_to(np.asarray(self.velocity, dtype=np.float64), (n,)),
            acceleration=np.broadcast_to(np.asarray(self.acceleration, dtype=np.float64), (n,)),
        )

    def build(self) -> RosbridgeRobot:
        try:
            from telerig.robots.rosbridge.driver import RosbridgeRobot
        except ModuleNotFoundError as exc:
            from telerig.errors import DependencyError

            raise DependencyError(
                f"the rosbridge driver needs {exc.name!r}: pip install 'telerig[ros]'"
            ) from None

        return RosbridgeRobot(
            self.url,
            self.joint_limits(),
            name=self.id,
            state_topic=self.state_topic,
            command_topic=self.command_topic,
            command_type=self.command_type,
            trajectory_time_s=self.trajectory_time_s,
            estop_topic=self.estop_topic,
            timeout_s=self.timeout_s,
            stale_timeout_s=self.stale_timeout_s,
            reconnect_s=self.reconnect_s,
        )
