"""Variants of a shipped rig that the benchmarks compare with the rig as its file has it."""

from __future__ import annotations

from telerig.config import RigConfig
from telerig.config.schema import RuntimeConfig


def with_robot_processes(config: RigConfig, realtime_priority: int) -> RigConfig:
    """``config`` with each robot (its control loop, physics, devices and simulated cameras) in a
    process of its own under ``SCHED_RR`` at ``realtime_priority``: ``runtime: {isolation:
    processes, realtime_priority: N}`` (without root or CAP_SYS_NICE the robots warn and run at
    normal priority)."""
    runtime = RuntimeConfig.model_validate(
        {**config.runtime.model_dump(), "isolation": "processes", "realtime_priority": realtime_priority}
    )  # validated: a priority outside 1..99 is refused here, with the field's message
    return config.model_copy(update={"runtime": runtime})
