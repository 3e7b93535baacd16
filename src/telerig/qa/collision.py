"""Self-collision gate: the recorded joint states replayed through the robot model's collision geometry."""

from __future__ import annotations

import numpy as np

from telerig.bus.catalogue import JOINT_STATE
from telerig.config.qa import QaThresholds
from telerig.qa.episode import EpisodeData, RobotData
from telerig.qa.motion import MAX_EVENTS
from telerig.qa.report import GateVerdict
from telerig.qa.robots import collision_model, match_joints

__all__ = ["replay_indices", "self_collision"]


def replay_indices(time_ns: np.ndarray, rate_hz: float) -> np.ndarray:
    """Indices of the samples to replay: the first sample at or after each tick of a ``rate_hz``
    grid over the stream (every sample when the stream is slower). Shape (k,), increasing."""
    if time_ns.size == 0:
        return np.zeros(0, dtype=np.intp)
    step = round(1e9 / rate_hz)
    grid = np.arange(int(time_ns[0]), int(time_ns[-1]) + 1, step, dtype=np.int64)
    idx = np.searchsorted(time_ns, grid, side="left")
    out: np.ndarray = np.unique(np.clip(idx, 0, time_ns.size - 1))
    return out


def self_collision(episode: EpisodeData, thresholds: QaThresholds) -> GateVerdict:
    """Fail when two non-adjacent bodies of a robot touch in any replayed recorded configuration.

    Each robot's measured joint positions are replayed at ``collision_rate_hz`` through its
    kinematic MuJoCo model (``mj_kinematics`` + ``mj_collision`` on the robot's own collision geoms,
    :class:`telerig.safety.collision.SelfCollision`): parent/child pairs are never checked, and pairs
    already touching at the model's home pose (meshes overlapping by design) are allowed.
    ``value`` is the deepest penetration [m].
    """
    from telerig.safety.collision import SelfCollision  # MuJoCo: the sim extra
    from telerig.safety.kinematics import KinematicsModel

    rate = thresholds.collision_rate_hz
    skipped: list[str] = []
    deepest = 0.0
    worst_text = ""
    events: list[float] = []
    frames_hit = 0
    replayed = 0
    for robot in episode.robots.values():
        state = robot.streams.get(JOINT_STATE)
        reason = _cannot_replay(robot)
        if reason or state is None:
            skipped.append(f"{robot.robot} ({reason or 'no joint_state'})")
            continue
        model = collision_model(str(robot.info.model))
        if model is None:
            skipped.append(f"{robot.robot} (model {robot.info.model} has no collision geometry)")
            continue
        names = robot.names.get(JOINT_STATE, ())
        index = match_joints(names, model.joints)
        columns = [i for i, j in enumerate(index) if j >= 0]
        if not columns:
            skipped.append(f"{robot.robot} (none of its joints is in model {robot.info.model})")
            continue
        joints = [model.joints[index[i]] for i in columns]
        kin = KinematicsModel(model.model, joints, base_body=model.base_body)
        home = np.array([model.home[index[i]] for i in columns])
        check = SelfCollision(kin, allowed=[home])
        q = state.fields["positions"][:, columns]
        previous = False
        for i in replay_indices(state.time_ns, rate):
            replayed += 1
            violation = check.violation(np.ascontiguousarray(q[i]))
            hit = violation is not None
            if violation is not None:
                frames_hit += 1
                t = episode.at(int(state.time_ns[i]))
                if not previous and len(events) < MAX_EVENTS:
                    events.append(round(t, 4))
                if violation.depth_m > deepest or not worst_text:
                    deepest = max(deepest, violation.depth_m)
                    worst_text = f"{robot.robot}: {violation.reason} at t={t:.2f} s"
            previous = hit
    if replayed == 0:
        why = "; ".join(skipped) or "no robot recorded joint states"
        return GateVerdict("self_collision", None, None, 0.0, "m", f"nothing replayed: {why}")
    if frames_hit:
        detail = f"{worst_text} ({frames_hit} of {replayed} replayed states in contact)"
    else:
        detail = f"no contact in {replayed} replayed states ({rate:g} Hz)"
    if skipped:
        detail += f"; not checked: {', '.join(skipped)}"
    return GateVerdict("self_collision", frames_hit == 0, deepest, 0.0, "m", detail, tuple(events))


def _cannot_replay(robot: RobotData) -> str:
    if robot.info.model is None:
        return "robot model unknown"
    return ""
