"""Config of the Unitree G1 driver (registered as ``type: unitree_g1``)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import Field, model_validator

from telerig.config.schema import RobotConfig
from telerig.registry import ROBOTS
from telerig.robots.unitree.joints import G1_UPPER_BODY, G1_UPPER_BODY_NAMES

if TYPE_CHECKING:
    from telerig.robots.base import JointLimits
    from telerig.robots.unitree.driver import UnitreeG1

__all__ = ["UnitreeG1Config"]

Seconds = Annotated[float, Field(gt=0, le=60)]
Gain = Annotated[float, Field(ge=0, le=500)]


@ROBOTS.register
class UnitreeG1Config(RobotConfig):
    """A Unitree G1 (29 DoF) standing on its own controller, its waist and arms driven over DDS ``arm_sdk``.

    ``joints`` are the commanded joints (any of the 17 arm_sdk joints, G1 URDF names); the others
    hold where they were. ``network_interface`` is this host's interface on the robot's network
    (192.168.123.0/24); ``lo`` dry-runs against a running
    :class:`~telerig.robots.unitree.fake.FakeG1`. ``velocity`` [rad/s] and ``acceleration``
    [rad/s^2] are the teleoperation limits the safety chain enforces (the motors allow 22-37 rad/s).
    ``kp`` / ``kd`` are the PD gains per commanded joint (one value for all, or one each); the
    held joints use the first. Needs ``pip install 'telerig[unitree]'`` (Cyclone DDS).
    """

    type: Literal["unitree_g1"] = "unitree_g1"
    network_interface: str = "eth0"
    domain_id: Annotated[int, Field(ge=0, le=230)] = 0
    joints: tuple[str, ...] = G1_UPPER_BODY_NAMES
    velocity: Annotated[float, Field(gt=0, le=22)] = 3.0
    acceleration: Annotated[float, Field(gt=0, le=500)] = 20.0
    kp: Gain | tuple[Gain, ...] = 60.0
    kd: Gain | tuple[Gain, ...] = 1.5
    weight_ramp_s: Seconds = 1.0
    keepalive_hz: Annotated[float, Field(ge=10, le=1000)] = 100.0
    timeout_s: Seconds = 2.0
    stale_timeout_s: Seconds = 0.2

    @model_validator(mode="after")
    def _joints_known(self) -> UnitreeG1Config:
        unknown = [j for j in self.joints if j not in G1_UPPER_BODY_NAMES]
        if unknown:
            valid = ", ".join(G1_UPPER_BODY_NAMES)
            raise ValueError(f"joints: {unknown[0]!r} is not an arm_sdk joint of the G1. Valid: {valid}")
        if not self.joints or len(set(self.joints)) != len(self.joints):
            raise ValueError("joints must list each joint once")
        for label in ("kp", "kd"):
            value = getattr(self, label)
            if isinstance(value, tuple) and len(value) != len(self.joints):
                raise ValueError(f"{label} has {len(value)} values for {len(self.joints)} joints")
        return self

    def joint_limits(self) -> JointLimits:
        """Position limits from the G1 URDF, the configured speed and acceleration limits."""
        import numpy as np

        from telerig.robots.base import JointLimits

        by_name = {j.name: j for j in G1_UPPER_BODY}
        n = len(self.joints)
        return JointLimits(
            names=self.joints,
            lower=np.array([by_name[j].lower for j in self.joints]),
            upper=np.array([by_name[j].upper for j in self.joints]),
            velocity=np.full(n, self.velocity),
            acceleration=np.full(n, self.acceleration),
        )

    def build(self) -> UnitreeG1:
        try:
            from telerig.robots.unitree.driver import UnitreeG1
        except ModuleNotFoundError as exc:
            from telerig.errors import DependencyError

            raise DependencyError(
                f"the Unitree driver needs {exc.name!r}: pip install 'telerig[unitree]'"
            ) from None
        import numpy as np

        return UnitreeG1(
            self.id,
            self.joint_limits(),
            network_interface=self.network_interface,
            domain_id=self.domain_id,
            kp=np.asarray(self.kp, dtype=np.float64),
            kd=np.asarray(self.kd, dtype=np.float64),
            weight_ramp_s=self.weight_ramp_s,
            keepalive_hz=self.keepalive_hz,
            timeout_s=self.timeout_s,
            stale_timeout_s=self.stale_timeout_s,
        )
