"""Config of the Universal Robots RTDE driver (registered as ``ur_rtde``)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import Field, model_validator

from telerig.config.schema import RobotConfig
from telerig.registry import ROBOTS

if TYPE_CHECKING:
    from telerig.robots.ur.driver import URRobot

__all__ = ["URRtdeConfig"]

Port = Annotated[int, Field(ge=1, le=65535)]


@ROBOTS.register
class URRtdeConfig(RobotConfig):
    """A Universal Robots arm over RTDE (state, servo targets) and URScript (servo loop, stops)."""

    type: Literal["ur_rtde"] = "ur_rtde"
    #: Controller IP address or host name.
    host: Annotated[str, Field(min_length=1)]
    rtde_port: Port = 30004
    script_port: Port = 30002
    #: RTDE state rate [Hz]: at most 500 on e-Series, 125 on CB3.
    control_rate_hz: Annotated[float, Field(gt=0, le=500)] = 125.0
    #: ``servoj`` time per loop cycle [s]: the controller period, 0.002 (e-Series) or 0.008 (CB3).
    servo_period_s: Annotated[float, Field(ge=0.002, le=0.1)] = 0.002
    #: ``servoj`` lookahead [s]: longer is smoother and lags more.
    servo_lookahead_s: Annotated[float, Field(ge=0.03, le=0.2)] = 0.1
    #: ``servoj`` proportional gain.
    servo_gain: Annotated[int, Field(ge=100, le=2000)] = 300
    #: The program stops the arm when no new command arrived for this long [s].
    watchdog_s: Annotated[float, Field(gt=0, le=1.0)] = 0.1
    #: First RTDE input register used (targets: 6 doubles from here; watchdog: this int register).
    #: 0 is free unless a fieldbus (EtherNet/IP, PROFINET) is enabled; then use 24.
    register_offset: Literal[0, 24] = 0
    #: Joint limits source: the arm model's datasheet values.
    limits: Literal["ur3e", "ur5e", "ur10e", "ur16e"] = "ur5e"
    #: The arm's model in :mod:`telerig.robots.models` (kinematics and collision geometry), e.g.
    #: ``ur5e_robotiq85``: IK and the workspace and self-collision guards need it. None: no model.
    model: str | None = None
    #: ``protective_stop`` latches on the robot (unlock on the pendant); ``stopj`` only decelerates.
    estop_action: Literal["protective_stop", "stopj"] = "protective_stop"
    gripper: Literal["none", "robotiq_urcap"] = "none"
    gripper_port: Port = 63352
    #: Connect and handshake timeout [s].
    timeout_s: Annotated[float, Field(gt=0, le=30)] = 2.0
    #: No state package for this long [s] counts as a lost connection.
    stale_timeout_s: Annotated[float, Field(gt=0, le=5)] = 0.5

    def control_rate(self) -> float:
        return self.control_rate_hz

    @model_validator(mode="after")
    def _known_model(self) -> URRtdeConfig:
        from telerig.robots.models import ARM_MODELS  # descriptions only: no MuJoCo import
        from telerig.robots.ur.limits import UR_JOINT_NAMES

        if self.model is None:
            return self
        arm = ARM_MODELS.get(self.model)
        known = ", ".join(n for n, m in ARM_MODELS.items() if m.joints == UR_JOINT_NAMES)
        if arm is None or arm.joints != UR_JOINT_NAMES:
            raise ValueError(f"model {self.model!r} is not a UR arm model. Available: {known}")
        return self

    @model_validator(mode="after")
    def _timing(self) -> URRtdeConfig:
        if self.watchdog_s < 2 * self.servo_period_s:
            raise ValueError(
                f"watchdog_s ({self.watchdog_s:g}) must be at least two servo periods "
                f"({2 * self.servo_period_s:g} s)"
            )
        if self.stale_timeout_s <= 2.0 / self.control_rate_hz:
            raise ValueError(
                f"stale_timeout_s ({self.stale_timeout_s:g}) must exceed two state periods "
                f"({2.0 / self.control_rate_hz:g} s at control_rate_hz {self.control_rate_hz:g})"
            )
        return self

    def build(self) -> URRobot:
        from telerig.robots.ur.driver import URRobot
        from telerig.robots.ur.limits import ur_limits
        from telerig.robots.ur.script import ServoProgram

        program = ServoProgram(
            int_register=self.register_offset,
            double_register=self.register_offset,
            period_s=self.servo_period_s,
            lookahead_s=self.servo_lookahead_s,
            gain=self.servo_gain,
            watchdog_cycles=max(1, round(self.watchdog_s / self.servo_period_s)),
        )
        return URRobot(
            self.host,
            name=self.id,
            rtde_port=self.rtde_port,
            script_port=self.script_port,
            control_rate_hz=self.control_rate_hz,
            program=program,
            limits=ur_limits(self.limits),
            estop_action=self.estop_action,
            gripper_port=self.gripper_port if self.gripper == "robotiq_urcap" else None,
            timeout_s=self.timeout_s,
            stale_timeout_s=self.stale_timeout_s,
            robot_model=self.model,
        )
