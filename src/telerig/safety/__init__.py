"""The safety chain between retargeting and every robot driver, and the filters it composes."""

from telerig.safety.chain import SafetyChain, SafetyOutput, SafetyStatus
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

__all__ = [
    "SAFETY_CODES",
    "AccelerationLimit",
    "Freshness",
    "InputCheck",
    "InputWatchdog",
    "Limit",
    "PositionClamp",
    "PositionRangeCheck",
    "SafetyChain",
    "SafetyCode",
    "SafetyEvent",
    "SafetyOutput",
    "SafetyStatus",
    "StartupRamp",
    "Tick",
    "VelocityLimit",
]
