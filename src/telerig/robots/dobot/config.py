"""Config of the Dobot CR-series arm driver (registered as ``type: dobot``)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import Field

from telerig.config.schema import RobotConfig
from telerig.registry import ROBOTS

if TYPE_CHECKING:
    from telerig.robots.dobot.driver import DobotRobot

__all__ = ["DobotConfig"]

Port = Annotated[int, Field(ge=0, le=65535)]


@ROBOTS.register
class DobotConfig(RobotConfig):
    """A Dobot CR arm over TCP/IP: dashboard (29999), motion (30003) and 8 ms feedback (30004) ports.

    ``model: cr5`` selects the CR5 joint limits (see :data:`telerig.robots.dobot.driver.CR5_LIMITS`).
    V4 controllers take motion commands on the dashboard port: set ``protocol: v4`` and
    ``motion_port: null``. To dry-run a rig, point ``host`` at a running
    :class:`~telerig.robots.dobot.fake.FakeDobot`.
    """

    type: Literal["dobot"] = "dobot"
    model: Literal["cr5"] = "cr5"
    host: str = "192.168.5.1"
    dashboard_port: Port = 29999
    motion_port: Port | None = 30003
    feedback_port: Port = 30004
    protocol: Literal["v3", "v4"] = "v3"
    speed_factor: Annotated[int, Field(ge=1, le=100)] = 50
    servo_time_s: Annotated[float, Field(ge=0.004, le=3600)] | None = 0.1
    enable_on_connect: bool = True
    disable_on_close: bool = True
    gripper_tool_do: Annotated[int, Field(ge=1, le=2)] | None = None
    gripper_close_level: Literal[0, 1] = 1
    timeout_s: Annotated[float, Field(gt=0, le=60)] = 2.0
    stale_timeout_s: Annotated[float, Field(gt=0, le=10)] = 0.5

    def build(self) -> DobotRobot:
        from telerig.robots.dobot.driver import CR5_LIMITS, DobotRobot

        return DobotRobot(
            self.host,
            name=self.id,
            dashboard_port=self.dashboard_port,
            motion_port=self.motion_port,
            feedback_port=self.feedback_port,
            protocol=self.protocol,
            limits=CR5_LIMITS,
            speed_factor=self.speed_factor,
            servo_time_s=self.servo_time_s,
            enable_on_connect=self.enable_on_connect,
            disable_on_close=self.disable_on_close,
            gripper_tool_do=self.gripper_tool_do,
            gripper_close_level=self.gripper_close_level,
            timeout_s=self.timeout_s,
            stale_timeout_s=self.stale_timeout_s,
        )
