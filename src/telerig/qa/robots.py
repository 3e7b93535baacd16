"""What the gates know of each recorded robot: its model, joint limits, standing height, collision model.

The manifest's ``robot_joints`` (the driver's own joints and limits, recorded with the episode) is
the first source; an episode without it falls back to the robot model its fingerprint names
(``robot arm0 -> mujoco_arm ur5e_robotiq85``), read from :mod:`telerig.robots.models`.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from telerig.ir.types import FloatArray
from telerig.robots.models import ARM_MODELS
from telerig.store.manifest_extra import EpisodeExtra

if TYPE_CHECKING:
    import mujoco

__all__ = ["CollisionModel", "RobotInfo", "collision_model", "match_joints", "robot_info"]

#: Models of robots that stand on a pelvis or a mobile base (the fall gate applies).
_STANDING_MODELS = frozenset({"g1", "tiago_robotiq85"})
_STANDING_TYPES = frozenset({"mujoco_humanoid", "mujoco_tiago", "unitree_g1"})


@dataclass(frozen=True, slots=True)
class RobotInfo:
    """One robot's model and limits as the gates use them.

    Attributes:
        robot: Robot id (the topic's node).
        type: Driver config type (``mujoco_arm``...), ``None`` when unknown.
        model: Robot model name (``ur5e_robotiq85``, ``g1``...), ``None`` when unknown.
        joints: Joint names the limits are given for. Length n (0 when no limits are known).
        lower: Lower position limits [rad] or [m]; NaN where unbounded. Shape (n,).
        upper: Upper position limits; NaN where unbounded. Shape (n,).
        velocity: Speed limits [rad/s] or [m/s]; NaN where unknown. Shape (n,).
        standing_height_m: Pelvis or base height when standing [m]; ``None`` when not known.
        standing: The robot stands on a pelvis or a mobile base (humanoid, mobile manipulator).
        source: Where the limits come from, for details: ``the manifest``, ``model g1``, or ``""``.
    """

    robot: str
    type: str | None
    model: str | None
    joints: tuple[str, ...]
    lower: FloatArray
    upper: FloatArray
    velocity: FloatArray
    standing_height_m: float | None
    standing: bool
    source: str

    def limits_for(self, names: Sequence[str]) -> tuple[FloatArray, FloatArray, FloatArray]:
        """``(lower, upper, velocity)`` for joints ``names`` (recorded order); NaN where unknown."""
        index = match_joints(names, self.joints)
        out = [np.full(len(names), np.nan) for _ in range(3)]
        for i, j in enumerate(index):
            if j >= 0:
                out[0][i], out[1][i], out[2][i] = self.lower[j], self.upper[j], self.velocity[j]
        return out[0], out[1], out[2]


def match_joints(names: Sequence[str], model_joints: Sequence[str]) -> list[int]:
    """Index into ``model_joints`` of each of ``names`` (-1 where none fits).

    A name matches exactly, or with a side prefix (``left_shoulder_pan_joint`` is the model's
    ``shoulder_pan_joint`` on a bimanual station).
    """
    exact = {n: i for i, n in enumerate(model_joints)}
    out = []
    for name in names:
        i = exact.get(name, -1)
        if i < 0:
            i = next((k for k, j in enumerate(model_joints) if name.endswith("_" + j)), -1)
        out.append(i)
    return out


def robot_info(robot: str, extra: EpisodeExtra) -> RobotInfo:
    """The model and limits of ``robot`` (a robot id) in an episode with manifest ``extra``.

    Raises:
        DependencyError: the model's package (robosuite, example-robot-data) or MuJoCo is missing.
        RobotError: the model file does not load.
    """
    record = extra.robot_joints.get(robot)
    if record is not None:
        standing = record.standing_height_m is not None or _stands(record.type, record.model)
        return RobotInfo(
            robot=robot,
            type=record.type,
            model=record.model,
            joints=tuple(record.joints),
            lower=_array(record.lower),
            upper=_array(record.upper),
            velocity=_array(record.velocity),
            standing_height_m=record.standing_height_m,
            standing=standing,
            source="the manifest",
        )
    kind, model = _from_fingerprint(robot, extra)
    joints, lower, upper, velocity, height = _model_limits(model) if model is not None else _NO_LIMITS
    return RobotInfo(
        robot=robot,
        type=kind,
        model=model,
        joints=joints,
        lower=lower,
        upper=upper,
        velocity=velocity,
        standing_height_m=height,
        standing=_stands(kind, model),
        source=f"model {model}" if joints else "",
    )


def _stands(kind: str | None, model: str | None) -> bool:
    return model in _STANDING_MODELS or kind in _STANDING_TYPES


def _array(values: Sequence[float | None]) -> FloatArray:
    return np.array([math.nan if v is None else v for v in values], dtype=np.float64)


def _from_fingerprint(robot: str, extra: EpisodeExtra) -> tuple[str | None, str | None]:
    """``(type, model)`` from the fingerprint's ``robot <id>`` component (``"mujoco_arm ur5e_robotiq85"``)."""
    text = extra.fingerprint.components.get(f"robot {robot}") if extra.fingerprint is not None else None
    if text is None:
        # A one-robot rig's model is the manifest's only robot model.
        return None, extra.robots[0] if len(extra.robots) == 1 else None
    words = text.split()
    model = words[1] if len(words) > 1 and words[1] != "joints" else None
    return words[0], model


_Limits = tuple[tuple[str, ...], FloatArray, FloatArray, FloatArray, float | None]
_NO_LIMITS: _Limits = ((), np.zeros(0), np.zeros(0), np.zeros(0), None)


@functools.lru_cache(maxsize=8)
def _model_limits(model: str) -> _Limits:
    """Joints, position range (NaN unbounded), speed limit and standing height of a model by name."""
    if model in ARM_MODELS:
        from telerig.robots.models.arm import build_arm_kinematics

        arm = build_arm_kinematics(model)
        rng = _ranges(arm.model, arm.arm_joints)
        velocity = np.asarray(arm.velocity_limit, dtype=np.float64)
        return arm.arm_joints, rng[:, 0], rng[:, 1], velocity, None
    if model == "g1":
        from telerig.robots.models.g1 import (
            G1_PELVIS_HEIGHT,
            HUMANOID_VELOCITY_LIMIT,
            UPPER_BODY_JOINTS,
            build_humanoid_kinematics,
        )

        g1 = build_humanoid_kinematics()
        rng = _ranges(g1.model, UPPER_BODY_JOINTS)
        velocity = np.full(len(UPPER_BODY_JOINTS), HUMANOID_VELOCITY_LIMIT)
        return UPPER_BODY_JOINTS, rng[:, 0], rng[:, 1], velocity, G1_PELVIS_HEIGHT
    if model == "tiago_robotiq85":
        from telerig.robots.models.tiago import build_tiago_kinematics

        limits = build_tiago_kinematics().limits
        lower = np.where(np.isfinite(limits.lower), limits.lower, np.nan)
        upper = np.where(np.isfinite(limits.upper), limits.upper, np.nan)
        return limits.names, lower, upper, np.array(limits.velocity), None
    return _NO_LIMITS


def _ranges(model: mujoco.MjModel, joints: Sequence[str]) -> FloatArray:
    out = np.full((len(joints), 2), np.nan)
    for i, name in enumerate(joints):
        jid = model.joint(name).id
        if model.jnt_limited[jid]:
            out[i] = model.jnt_range[jid]
    return out


@dataclass(frozen=True, slots=True)
class CollisionModel:
    """A robot's kinematic MuJoCo model with its own collision geometry.

    Attributes:
        model: The compiled model (``mujoco.MjModel``; copied before use, never changed).
        joints: Its joints the recorded joint states drive, model names. Length n.
        base_body: The robot's root body (contacts with bodies outside its subtree are ignored).
        home: A configuration of ``joints`` whose contacts are by design (meshes overlapping at
            the joints). Shape (n,).
    """

    model: mujoco.MjModel
    joints: tuple[str, ...]
    base_body: str
    home: FloatArray


@functools.lru_cache(maxsize=8)
def collision_model(model: str) -> CollisionModel | None:
    """The collision model of a robot model by name; ``None`` for a model without one (hands).

    Raises:
        DependencyError: the model's package or MuJoCo is missing.
        RobotError: the model file does not load.
    """
    if model in ARM_MODELS:
        from telerig.robots.models.arm import build_arm_kinematics

        arm = build_arm_kinematics(model)
        return CollisionModel(arm.model, arm.arm_joints, arm.base_body, np.array(arm.home))
    if model == "g1":
        from telerig.robots.models.g1 import HUMANOID_HOME, UPPER_BODY_JOINTS, build_humanoid_kinematics

        g1 = build_humanoid_kinematics()
        return CollisionModel(g1.model, UPPER_BODY_JOINTS, g1.pelvis_body, np.array(HUMANOID_HOME))
    if model == "tiago_robotiq85":
        from telerig.robots.models.tiago import build_tiago_kinematics

        tiago = build_tiago_kinematics()
        return CollisionModel(tiago.model, tiago.joints, tiago.base_body, np.array(tiago.home))
    return None
