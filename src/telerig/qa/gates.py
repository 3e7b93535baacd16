"""Run the quality gates on one committed episode: :func:`evaluate`."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path

from telerig.config.qa import GATES, GateName, QaThresholds
from telerig.qa.collision import self_collision
from telerig.qa.episode import EpisodeData, load_episode
from telerig.qa.motion import (
    IdleTime,
    calibration_drift,
    fall,
    force_spike,
    idle_gate,
    idle_time,
    joint_limits,
)
from telerig.qa.report import GateVerdict, QaReport
from telerig.qa.timing import sync, teleop_faults

__all__ = ["GATE_FUNCTIONS", "evaluate", "evaluate_loaded"]

Gate = Callable[[EpisodeData, QaThresholds], GateVerdict]

#: Each gate's function, by name (the idle gate is judged from :func:`~telerig.qa.motion.idle_time`).
GATE_FUNCTIONS: Mapping[GateName, Gate] = {
    "fall": fall,
    "self_collision": self_collision,
    "joint_limits": joint_limits,
    "force_spike": force_spike,
    "sync": sync,
    "teleop_faults": teleop_faults,
    "calibration_drift": calibration_drift,
}


def evaluate(episode_dir: Path, thresholds: QaThresholds) -> QaReport:
    """Run the enabled gates (``thresholds.gates``) on the episode in ``episode_dir``.

    Reads ``manifest.json`` and ``episode.mcap`` (never the videos) and the robot models the
    manifest names; writes nothing.

    Raises:
        RecordingError: the episode cannot be read (one line with the path).
        DependencyError: a robot model's package or MuJoCo is missing.
    """
    return evaluate_loaded(load_episode(Path(episode_dir)), thresholds)


def evaluate_loaded(episode: EpisodeData, thresholds: QaThresholds) -> QaReport:
    """:func:`evaluate` on an episode already read with :func:`~telerig.qa.episode.load_episode`."""
    idle: IdleTime = idle_time(episode, thresholds)
    verdicts: list[GateVerdict] = []
    for gate in thresholds.gates:
        if gate == "idle":
            verdicts.append(idle_gate(idle, thresholds))
        else:
            verdicts.append(GATE_FUNCTIONS[gate](episode, thresholds))
    order: dict[str, int] = {g: i for i, g in enumerate(GATES)}
    verdicts.sort(key=lambda v: order[v.gate])
    return QaReport(episode.manifest.id, tuple(verdicts), idle.fraction, idle.segments)
