"""Configs of the Modbus drivers: the Inspire hand (Modbus TCP) and DH-Robotics grippers (Modbus RTU)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import Field, model_validator

from telerig.config.schema import RobotConfig
from telerig.registry import ROBOTS

if TYPE_CHECKING:
    from telerig.robots.modbus.dh_gripper import DHGripper
    from telerig.robots.modbus.inspire import InspireHand

__all__ = ["DHGripperConfig", "InspireHandConfig"]

Port = Annotated[int, Field(ge=1, le=65535)]
DeviceId = Annotated[int, Field(ge=0, le=247)]


@ROBOTS.register
class InspireHandConfig(RobotConfig):
    """An Inspire RH56 dexterous hand on Modbus TCP (six actuated DoF, angles in rad)."""

    type: Literal["inspire_hand"] = "inspire_hand"
    host: str = "192.168.11.210"
    port: Port = 6000
    device_id: DeviceId = 1
    joint_prefix: str = ""
    poll_rate_hz: Annotated[float, Field(gt=0, le=500)] = 100.0
    timeout_s: Annotated[float, Field(gt=0, le=5)] = 0.1
    stale_after_s: Annotated[float, Field(gt=0, le=30)] = 0.5
    speed: Annotated[int, Field(ge=0, le=1000)] = 1000
    force: Annotated[int, Field(ge=0, le=1000)] = 500
    full_stroke_s: Annotated[float, Field(gt=0, le=10)] = 0.8

    def build(self) -> InspireHand:
        from telerig.robots.modbus.inspire import InspireHand

        return InspireHand(
            self.host,
            self.port,
            device_id=self.device_id,
            name=self.id,
            joint_prefix=self.joint_prefix,
            poll_rate_hz=self.poll_rate_hz,
            timeout_s=self.timeout_s,
            stale_after_s=self.stale_after_s,
            speed=self.speed,
            force=self.force,
            full_stroke_s=self.full_stroke_s,
        )


@ROBOTS.register
class DHGripperConfig(RobotConfig):
    """A DH-Robotics parallel gripper (AG / PGE / PGC / CGC) on Modbus RTU, one DoF: the opening in m."""

    type: Literal["dh_gripper"] = "dh_gripper"
    transport: Literal["serial", "rtu_over_tcp"] = "serial"
    device: str = "/dev/ttyUSB0"
    baudrate: Literal[4800, 9600, 19200, 38400, 57600, 115200] = 115200
    parity: Literal["N", "E", "O"] = "N"
    stopbits: Literal[1, 2] = 1
    host: str | None = None
    port: Port = 502
    device_id: Annotated[int, Field(ge=1, le=247)] = 1
    joint_prefix: str = ""
    stroke_m: Annotated[float, Field(gt=0, le=1)] = 0.095
    rated_force_n: Annotated[float, Field(gt=0, le=10_000)] = 160.0
    full_stroke_s: Annotated[float, Field(gt=0, le=10)] = 0.7
    force_percent: Annotated[int, Field(ge=20, le=100)] = 50
    speed_percent: Annotated[int, Field(ge=1, le=100)] = 100
    initialize: bool = True
    #: Longest wait in ``connect`` for the initialization (fingers finding their end stop) [s].
    init_timeout_s: Annotated[float, Field(gt=0, le=60)] = 10.0
    poll_rate_hz: Annotated[float, Field(gt=0, le=200)] = 50.0
    timeout_s: Annotated[float, Field(gt=0, le=5)] = 0.1
    stale_after_s: Annotated[float, Field(gt=0, le=30)] = 0.5

    @model_validator(mode="after")
    def _transport(self) -> DHGripperConfig:
        if self.transport == "rtu_over_tcp" and not self.host:
            raise ValueError("host: required when transport is 'rtu_over_tcp' (the RS-485 gateway's address)")
        return self

    def build(self) -> DHGripper:
        from telerig.robots.modbus.dh_gripper import DHGripper

        return DHGripper(
            transport=self.transport,
            device=self.device,
            baudrate=self.baudrate,
            parity=self.parity,
            stopbits=self.stopbits,
            host=self.host or "127.0.0.1",
            port=self.port,
            device_id=self.device_id,
            name=self.id,
            joint_prefix=self.joint_prefix,
            stroke_m=self.stroke_m,
            rated_force_n=self.rated_force_n,
            full_stroke_s=self.full_stroke_s,
            force_percent=self.force_percent,
            speed_percent=self.speed_percent,
            initialize=self.initialize,
            init_timeout_s=self.init_timeout_s,
            poll_rate_hz=self.poll_rate_hz,
            timeout_s=self.timeout_s,
            stale_after_s=self.stale_after_s,
        )
