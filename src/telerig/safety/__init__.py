"""The safety chain between retargeting and every robot driver, its filters and the fleet supervisor."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from telerig.safety.alerts import SEVERITY, SafetyAlert, SafetyAlerts, Severity
from telerig.safety.chain import FAULT_CODES, SafetyChain, SafetyOutput, SafetyStatus
from telerig.safety.deadman import Deadman
from telerig.safety.filters import (
    SAFETY_CODES,
    AccelerationLimit,
    Freshness,
    InputCheck,
    InputWatchdog,
    Limit,
    PositionClamp,
    PositionRangeCheck,
    SafetyCode,
    SafetyEvent,
    StartupRamp,
    Tick,
    VelocityLimit,
)
from telerig.safety.guard import ConfigurationCheck, ConfigurationGuard, Violation
from telerig.safety.settings import RobotSafetyConfig, arm_guard
from telerig.safety.supervisor import POLICIES, FaultPolicy, RobotSafety, SafetySupervisor
from telerig.safety.workspace import Box, Sphere, WorkspaceBounds

if TYPE_CHECKING:  # MuJoCo-backed (sim extra): imported on first use
    from telerig.safety.collision import SelfCollision
    from telerig.safety.kinematics import KinematicsModel

__all__ = [
    "FAULT_CODES",
    "POLICIES",
    "SAFETY_CODES",
    "SEVERITY",
    "AccelerationLimit",
    "Box",
    "ConfigurationCheck",
    "ConfigurationGuard",
    "Deadman",
    "FaultPolicy",
    "Freshness",
    "InputCheck",
    "InputWatchdog",
    "KinematicsModel",
    "Limit",
    "PositionClamp",
    "PositionRangeCheck",
    "RobotSafety",
    "RobotSafetyConfig",
    "SafetyAlert",
    "SafetyAlerts",
    "SafetyChain",
    "SafetyCode",
    "SafetyEvent",
    "SafetyOutput",
    "SafetyStatus",
    "SafetySupervisor",
    "SelfCollision",
    "Severity",
    "Sphere",
    "StartupRamp",
    "Tick",
    "VelocityLimit",
    "Violation",
    "WorkspaceBounds",
    "arm_guard",
]

_LAZY = {"KinematicsModel": "telerig.safety.kinematics", "SelfCollision": "telerig.safety.collision"}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'telerig.safety' has no attribute {name!r}")
