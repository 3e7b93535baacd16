"""Body skeleton → humanoid upper body: anatomical keypoints, segment-length scaling and mink IK.

Correspondence. From a :class:`~telerig.ir.types.BodySkeleton` the retargeter reads six required
keypoints, the shoulder, elbow and wrist of each arm, and optionally both hips. Producers name
them differently; a :class:`SkeletonProfile` maps each keypoint to the producer's joint names
(MediaPipe pose, CMU-style BVH / NatNet, OptiTrack Motive; see :data:`SKELETON_PROFILES`).

Frames. The skeleton's frame must have z up (telerig's operator axes, x forward, y left, z up,
which the BVH/NatNet mounts and the MediaPipe conversion produce). Arm segments are expressed in
the chest heading frame (z up, x the direction the shoulder line faces), so the operator may
stand anywhere and face any way. Each segment keeps its direction and takes the robot's length
(the per-frame ratio of robot to human segment length scales it), and the chain is rebuilt from
the robot's shoulder: robot elbow = shoulder + L_upper * u/|u|, robot wrist = elbow +
L_fore * f/|f|. Targets are in the robot's torso frame, so they turn with the waist, whose yaw
follows the chest's yaw relative to the hips (held at home without hips).

IK. mink's tasks over one QP per sub-step: a relative position task per wrist (torso frame), elbow
position tasks at a lower weight, a posture task (the waist yaw target; home for the arms,
weakly), joint position limits and joint speed limits as bounds on the step (DAQP directly, as
the arm IK does; the tests hold it to ``mink.solve_ik``). The wrist position error left after
each solve is the residual; a result is flagged when either wrist misses by more than the
threshold (5 cm default).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass
from functools import cached_property
from types import MappingProxyType

import mink
import mujoco
import numpy as np
import numpy.typing as npt

from telerig.errors import RobotError
from telerig.ir.types import BodySkeleton, FloatArray, JointCommand, Sample
from telerig.retarget.arm_ik import DAMPING, BoxStep, check_ik_settings, require_names
from telerig.retarget.keypoint_filter import OneEuroPointFilter
from telerig.robots.models.g1 import (
    HUMANOID_VELOCITY_LIMIT,
    WAIST_JOINTS,
    WAIST_YAW_JOINT,
    HumanoidScene,
    build_humanoid_kinematics,
)

__all__ = [
    "KEYPOINTS",
    "REQUIRED_KEYPOINTS",
    "SKELETON_PROFILES",
    "HumanoidBodyRetargeter",
    "HumanoidIK",
    "HumanoidIKResult",
    "HumanoidMinkReference",
    "HumanoidRetargeter",
    "HumanoidGeometry",
    "HumanoidTargets",
    "SkeletonProfile",
    "humanoid_targets",
    "KeypointMap",
]

_log = logging.getLogger(__name__)

#: Keypoints the retargeter reads, in the order of :meth:`SkeletonProfile.extract`'s rows.
KEYPOINTS = (
    "right_shoulder",
    "right_elbow",
    "right_wrist",
    "left_shoulder",
    "left_elbow",
    "left_wrist",
    "right_hip",
    "left_hip",
)
#: Keypoints a skeleton must have; the hips are optional (without them the waist holds home).
REQUIRED_KEYPOINTS = KEYPOINTS[:6]
_RS, _RE, _RW, _LS, _LE, _LW, _RH, _LH = range(8)
_MIN_SEGMENT_M = 0.01  # shorter human segments have no usable direction [m]


@dataclass(frozen=True, slots=True)
class SkeletonProfile:
    """How one producer names the keypoints.

    Attributes:
        name: Profile name, e.g. ``"mediapipe"``.
        joints: Keypoint (one of :data:`KEYPOINTS`) → producer joint name. A skeleton joint
            matches a name exactly or, for NatNet streams that prefix bones with the skeleton's
            name, as ``"<prefix>_<name>"``.
    """

    name: str
    joints: Mapping[str, str]

    def resolve(self, joint_names: tuple[str, ...]) -> tuple[npt.NDArray[np.intp], list[str]]:
        """Row of each keypoint in ``joint_names`` (-1 when absent) and the missing required keypoints."""
        exact = {n: i for i, n in enumerate(joint_names)}
        rows = np.full(len(KEYPOINTS), -1, dtype=np.intp)
        missing = []
        for k, keypoint in enumerate(KEYPOINTS):
            name = self.joints.get(keypoint)
            row = exact.get(name, -1) if name is not None else -1
            if row < 0 and name is not None:
                suffixed = [i for i, n in enumerate(joint_names) if n.endswith("_" + name)]
                row = suffixed[0] if len(suffixed) == 1 else -1
            rows[k] = row
            if row < 0 and keypoint in REQUIRED_KEYPOINTS:
                missing.append(name or keypoint)
        return rows, missing


def _profile(name: str, names: tuple[str, ...]) -> SkeletonProfile:
    return SkeletonProfile(name, MappingProxyType(dict(zip(KEYPOINTS, names, strict=True))))


#: Built-in profiles: MediaPipe pose landmarks (markerless), CMU-style names (BVH files and the
#: NatNet fake's skeleton: ``LeftArm`` is the shoulder joint, ``LeftForeArm`` the elbow,
#: ``LeftHand`` the wrist, ``LeftUpLeg`` the hip) and OptiTrack Motive's default skeleton. The BVH
#: player finds these joints by the skeleton's structure and gives them their CMU names whatever the
#: file calls them (``LeftShoulder/LeftElbow/LeftWrist`` too; see
#: :func:`telerig.devices.mocap.bvh.body_keypoints`), so every BVH file reads through ``cmu``.
SKELETON_PROFILES: Mapping[str, SkeletonProfile] = MappingProxyType(
    {
        "mediapipe": _profile("mediapipe", KEYPOINTS),
        "cmu": _profile(
            "cmu",
            (
                "RightArm",
                "RightForeArm",
                "RightHand",
                "LeftArm",
                "LeftForeArm",
                "LeftHand",
                "RightUpLeg",
                "LeftUpLeg",
            ),
        ),
        "motive": _profile(
            "motive", ("RUArm", "RFArm", "RHand", "LUArm", "LFArm", "LHand", "RThigh", "LThigh")
        ),
    }
)


class KeypointMap:
    """Extract :data:`KEYPOINTS` from skeletons, finding the profile from the first skeleton's names.

    Call it with a skeleton: returns the keypoint positions [m], skeleton frame, shape (8, 3),
    with NaN rows for absent optional keypoints.
    """

    def __init__(self, profile: str | SkeletonProfile | None = None) -> None:
        """Args:
        profile: A name in :data:`SKELETON_PROFILES`, a custom profile, or None to detect.

        Raises:
            ValueError: unknown profile name.
        """
        if isinstance(profile, str):
            if profile not in SKELETON_PROFILES:
                raise ValueError(
                    f"unknown skeleton profile {profile!r}. Valid: {', '.join(SKELETON_PROFILES)}"
                )
            profile = SKELETON_PROFILES[profile]
        self._fixed = profile
        self._layout: tuple[str, ...] | None = None
        self._rows = np.zeros(0, dtype=np.intp)
        self.profile: SkeletonProfile | None = profile

    def __call__(self, skeleton: BodySkeleton) -> FloatArray:
        """Keypoint positions of ``skeleton`` [m], shape (8, 3), NaN rows where absent.

        Raises:
            ValueError: a required keypoint is missing (one line naming the missing joints).
        """
        if skeleton.joint_names != self._layout:
            self._resolve(skeleton.joint_names)
        out = np.full((len(KEYPOINTS), 3), np.nan)
        present = self._rows >= 0
        out[present] = skeleton.positions[self._rows[present]]
        return out

    def _resolve(self, names: tuple[str, ...]) -> None:
        candidates = [self._fixed] if self._fixed is not None else list(SKELETON_PROFILES.values())
        best: tuple[SkeletonProfile, list[str]] | None = None
        for profile in candidates:
            rows, missing = profile.resolve(names)
            if not missing:
                self._layout, self._rows, self.profile = names, rows, profile
                return
            if best is None or len(missing) < len(best[1]):
                best = (profile, missing)
        assert best is not None
        profile, missing = best
        raise ValueError(
            f"body skeleton lacks joints the humanoid retargeter needs: {', '.join(missing)} "
            f"(profile '{profile.name}'; required: shoulders, elbows and wrists of both arms)"
        )


@dataclass(frozen=True, slots=True)
class HumanoidTargets:
    """Upper-body targets for one skeleton frame.

    Attributes:
        wrists: Right and left wrist targets [m], robot torso frame. Shape (2, 3).
        elbows: Right and left elbow targets [m], robot torso frame. Shape (2, 3).
        waist_yaw: Waist yaw target [rad] (chest yaw relative to the hips; 0 without hips).
        scale: Robot-to-human length ratio of the right and left upper arm and forearm, in that
            order. Shape (4,).
    """

    wrists: FloatArray
    elbows: FloatArray
    waist_yaw: float
    scale: FloatArray


@dataclass(frozen=True, slots=True)
class HumanoidGeometry:
    """The robot's arm geometry the targets are built on, measured at home.

    Attributes:
        shoulders: Right and left shoulder centre [m], torso-site frame. Shape (2, 3).
        upper: Right and left upper-arm length, shoulder to elbow [m]. Shape (2,).
        fore: Right and left forearm length, elbow to wrist [m]. Shape (2,).
    """

    shoulders: FloatArray
    upper: FloatArray
    fore: FloatArray


def _heading(v: FloatArray) -> float | None:
    """Yaw [rad] of the forward direction of a left-pointing horizontal line ``v``; None if vertical."""
    if math.hypot(v[0], v[1]) < _MIN_SEGMENT_M:
        return None
    return math.atan2(v[1], v[0]) - math.pi / 2


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2 * math.pi) - math.pi


def humanoid_targets(
    keypoints: FloatArray,
    geometry: HumanoidGeometry,
    *,
    waist_range: tuple[float, float] = (-math.pi, math.pi),
    previous: HumanoidTargets | None = None,
) -> HumanoidTargets:
    """Robot targets from keypoints (shape (8, 3), :data:`KEYPOINTS` order, skeleton frame, z up).

    A degenerate human segment (shorter than 1 cm) keeps the previous frame's robot target.

    Raises:
        ValueError: a required keypoint is not finite, or the shoulders coincide.
    """
    if not np.all(np.isfinite(keypoints[:6])):
        raise ValueError("required skeleton keypoints (shoulders, elbows, wrists) must be finite")
    chest = _heading(keypoints[_LS] - keypoints[_RS])
    if chest is None:
        raise ValueError("shoulders coincide in the horizontal plane: cannot tell which way the chest faces")
    waist = 0.0
    if np.all(np.isfinite(keypoints[_RH:])):
        hips = _heading(keypoints[_LH] - keypoints[_RH])
        if hips is not None:
            waist = float(np.clip(_wrap(chest - hips), *waist_range))
    c, s = math.cos(chest), math.sin(chest)
    to_chest = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])  # world → chest heading
    wrists = np.empty((2, 3))
    elbows = np.empty((2, 3))
    scale = np.empty(4)
    for side, (sh, el, wr) in enumerate(((_RS, _RE, _RW), (_LS, _LE, _LW))):
        upper = to_chest @ (keypoints[el] - keypoints[sh])
        fore = to_chest @ (keypoints[wr] - keypoints[el])
        lu, lf = float(np.linalg.norm(upper)), float(np.linalg.norm(fore))
        if lu < _MIN_SEGMENT_M or lf < _MIN_SEGMENT_M:
            if previous is None:
                raise ValueError("an arm segment is shorter than 1 cm in the first frame: check the skeleton")
            wrists[side], elbows[side] = previous.wrists[side], previous.elbows[side]
            scale[2 * side : 2 * side + 2] = previous.scale[2 * side : 2 * side + 2]
            continue
        ru, rf = geometry.upper[side], geometry.fore[side]
        elbows[side] = geometry.shoulders[side] + upper * (ru / lu)
        wrists[side] = elbows[side] + fore * (rf / lf)
        scale[2 * side], scale[2 * side + 1] = ru / lu, rf / lf
    for arr in (wrists, elbows, scale):
        arr.flags.writeable = False
    return HumanoidTargets(wrists=wrists, elbows=elbows, waist_yaw=waist, scale=scale)


@dataclass(frozen=True, slots=True)
class HumanoidIKResult:
    """One IK step.

    Attributes:
        q: Upper-body joint positions to command [rad], IK joint order. Shape (n,).
        wrist_errors: Right and left wrist distance to its target [m]. Shape (2,).
        elbow_errors: Right and left elbow distance to its target [m]. Shape (2,).
        flagged: True when a wrist error exceeds the residual threshold: the target is out of
            reach (joint limits), or too far to cover in one step at the speed limit.
        solve_time_s: Wall time the solve took [s] (QPs and error evaluation).
    """

    q: FloatArray
    wrist_errors: FloatArray
    elbow_errors: FloatArray
    flagged: bool
    solve_time_s: float = math.nan

    @property
    def max_wrist_error(self) -> float:
        """The larger wrist error [m]."""
        return float(np.max(self.wrist_errors))

    def metrics(self) -> dict[str, float]:
        """Per-task errors [m] and the solve time [s], as the control node records them every tick."""
        return {
            "right_wrist_error_m": float(self.wrist_errors[0]),
            "left_wrist_error_m": float(self.wrist_errors[1]),
            "right_elbow_error_m": float(self.elbow_errors[0]),
            "left_elbow_error_m": float(self.elbow_errors[1]),
            "ik_time_s": self.solve_time_s,
        }


class HumanoidIK:
    """Track wrist and elbow targets (robot torso frame) and a waist yaw, one speed-limited step per call.

    Each :meth:`solve` runs ``iterations`` QPs over sub-steps of ``dt``, so the joint step over
    one call is at most ``velocity_limit * dt`` per joint. Each is the QP ``mink.solve_ik`` builds
    from the same tasks, a ``ConfigurationLimit`` and a ``VelocityLimit``, with the limits as
    bounds (:class:`~telerig.retarget.arm_ik.BoxStep`): 0.8x the time of a solve through mink
    (``benchmarks/humanoid_ik.py``; the four frame tasks' Jacobians are most of what is left),
    once per tick of the G1's control loop; :class:`HumanoidMinkReference` solves it through mink.
    The solver owns its ``MjModel``/``MjData`` (the kinematic G1, pelvis fixed) and never touches
    a simulation.
    """

    def __init__(
        self,
        scene: HumanoidScene | None = None,
        *,
        velocity_limit: npt.ArrayLike = HUMANOID_VELOCITY_LIMIT,
        wrist_cost: float = 1.0,
        elbow_cost: float = 0.3,
        waist_cost: float = 1.0,
        posture_cost: float = 1e-2,
        lm_damping: float = 1e-3,
        iterations: int = 1,
        residual_threshold_m: float = 0.05,
    ) -> None:
        """Build the IK problem.

        Args:
            scene: Kinematic humanoid; ``build_humanoid_kinematics()`` when None.
            velocity_limit: Joint speed limit [rad/s], scalar or shape (n,).
            wrist_cost: Wrist position task weight [1/m].
            elbow_cost: Elbow position task weight [1/m]; lower than the wrists' so the hands win.
            waist_cost: Posture weight of the waist toward its yaw target [1/rad].
            posture_cost: Posture weight of the arm joints toward home [1/rad]; small, it only picks
                the forearm roll and settles redundancy.
            lm_damping: Levenberg-Marquardt damping of the position tasks.
            iterations: QP sub-steps per :meth:`solve`. >= 1; one tracks 60 Hz mocap as well as three.
            residual_threshold_m: Wrist error above which a result is flagged [m]. > 0.

        Raises:
            RobotError: the scene's model lacks a joint or site the IK needs.
            ValueError: a numeric argument is out of range.
        """
        self._scene = scene if scene is not None else build_humanoid_kinematics()
        model = self._scene.model
        joints = self._scene.joints
        n = len(joints)
        if model.nq != n or model.nv != n:
            raise RobotError(
                f"the IK needs a kinematic model with exactly the {n} upper-body joints "
                f"(got nq={model.nq}); use build_humanoid_kinematics()"
            )
        require_names(model, mujoco.mjtObj.mjOBJ_JOINT, joints)
        require_names(model, mujoco.mjtObj.mjOBJ_SITE, tuple(self._scene.sites.values()))
        vmax = check_ik_settings(iterations, residual_threshold_m, velocity_limit, n)

        self._n = n
        self._iterations = iterations
        self._threshold = residual_threshold_m
        self._vmax = vmax
        self._qadr = np.array([model.joint(j).qposadr[0] for j in joints])
        sites = self._scene.sites
        self._torso = sites["torso"]
        self._wrist_sites = (sites["right_wrist"], sites["left_wrist"])
        self._elbow_sites = (sites["right_elbow"], sites["left_elbow"])
        self._config = mink.Configuration(model, np.array(self._scene.home))

        def relative(site: str, cost: float) -> mink.RelativeFrameTask:
            return mink.RelativeFrameTask(site, "site", self._torso, "site", cost, 0.0, lm_damping=lm_damping)

        self._wrist_tasks = [relative(s, wrist_cost) for s in self._wrist_sites]
        self._elbow_tasks = [relative(s, elbow_cost) for s in self._elbow_sites]
        # Every waist joint is held by the waist cost; the skeleton's heading steers the yaw only
        # (roll and pitch stay at home, as the real G1's waist does under arm_sdk).
        costs = np.full(model.nv, posture_cost)
        costs[[int(model.joint(j).dofadr[0]) for j in WAIST_JOINTS]] = waist_cost
        self._waist = int(model.joint(WAIST_YAW_JOINT).dofadr[0])
        self._posture = mink.PostureTask(model, cost=costs)
        self._posture_target = np.array(self._scene.home)
        self._tasks = [*self._wrist_tasks, *self._elbow_tasks, self._posture]
        jids = [model.joint(j).id for j in joints]
        self._box = BoxStep(model, jids, vmax, "humanoid IK")
        self._lower: FloatArray = self._box.lower
        self._upper: FloatArray = self._box.upper
        yaw = model.joint(WAIST_YAW_JOINT).id
        self._waist_range = (float(model.jnt_range[yaw, 0]), float(model.jnt_range[yaw, 1]))
        self.geometry = self._measure()

    @property
    def joint_names(self) -> tuple[str, ...]:
        """Upper-body joints, in the order of ``q``."""
        return self._scene.joints

    @property
    def home(self) -> FloatArray:
        """Home configuration [rad]. Shape (n,)."""
        return self._scene.home

    @property
    def lower(self) -> FloatArray:
        """Lower joint limits [rad]. Shape (n,)."""
        return self._lower

    @property
    def upper(self) -> FloatArray:
        """Upper joint limits [rad]. Shape (n,)."""
        return self._upper

    @property
    def residual_threshold_m(self) -> float:
        """Wrist error above which a result is flagged [m]."""
        return self._threshold

    @property
    def waist_range(self) -> tuple[float, float]:
        """Waist yaw range [rad]."""
        return self._waist_range

    def points(self, q: npt.ArrayLike) -> dict[str, FloatArray]:
        """Anatomical site positions at ``q`` [rad] (shape (n,)), world frame [m], by role (shape (3,) each).

        The kinematic model's world frame has its origin on the floor under the pelvis, x forward,
        y left, z up; the pelvis is 0.795 m up.
        """
        self._config.update(self._checked_q(q))
        data = self._config.data
        return {
            role: data.site_xpos[self._config.model.site(site).id].copy()
            for role, site in self._scene.sites.items()
        }

    def solve(
        self, targets: HumanoidTargets, q_current: npt.ArrayLike, dt: float, *, iterations: int | None = None
    ) -> HumanoidIKResult:
        """One IK step from ``q_current`` toward ``targets``.

        Args:
            targets: Wrist/elbow targets (robot torso frame) and waist yaw.
            q_current: Current upper-body joint positions [rad]. Shape (n,).
            dt: Control period [s]; bounds the step to ``velocity_limit * dt``.
            iterations: QP sub-steps for this call; the constructor's when None.

        Raises:
            ValueError: ``q_current`` has the wrong shape or is not finite, or ``dt <= 0``.
        """
        if not dt > 0:
            raise ValueError(f"dt must be positive [s], got {dt}")
        t0 = time.perf_counter()
        steps = self._iterations if iterations is None else iterations
        if steps < 1:
            raise ValueError(f"iterations must be >= 1, got {steps}")
        # Clamp into the limits: mink's QP is infeasible from outside them.
        q = np.clip(self._checked_q(q_current), self._lower, self._upper)
        config = self._config
        config.update(q)
        self._posture_target[:] = self._scene.home
        self._posture_target[self._waist] = np.clip(targets.waist_yaw, *self._waist_range)
        self._posture.set_target(self._posture_target)
        for task, target in (
            *zip(self._wrist_tasks, targets.wrists, strict=True),
            *zip(self._elbow_tasks, targets.elbows, strict=True),
        ):
            task.set_target(mink.SE3.from_translation(np.asarray(target)))
        sub_dt = dt / steps
        for _ in range(steps):
            self._step(sub_dt)
        wrist_errors = self._errors(self._wrist_sites, targets.wrists)
        elbow_errors = self._errors(self._elbow_sites, targets.elbows)
        q_next = np.clip(config.q.copy(), self._lower, self._upper)
        for arr in (q_next, wrist_errors, elbow_errors):
            arr.flags.writeable = False
        return HumanoidIKResult(
            q=q_next,
            wrist_errors=wrist_errors,
            elbow_errors=elbow_errors,
            flagged=bool(np.max(wrist_errors) > self._threshold),
            solve_time_s=time.perf_counter() - t0,
        )

    def _step(self, dt: float) -> None:
        """One QP from the configuration's joints over ``dt``, and the step taken.

        Minimises ``|W dq + e|^2 + (mu + damping) |dq|^2`` with every task's weighted residual
        stacked in ``W`` and ``e`` (mink's fusion of the tasks), within the step's bounds."""
        config = self._config
        jacobians, errors, mu = [], [], DAMPING
        for task in self._tasks:
            residual = task.compute_qp_residual(config)
            assert residual is not None  # position and posture tasks are least-squares residuals
            jacobians.append(residual[0])
            errors.append(residual[1])
            mu += residual[2]
        weighted = np.vstack(jacobians)
        hessian = weighted.T @ weighted
        hessian.flat[:: self._n + 1] += mu
        gradient = -(np.concatenate(errors) @ weighted)
        q = config.q  # nq == nv == n: every coordinate is one of the joints
        config.update(q + self._box.solve(hessian, gradient, q, dt))

    def _errors(self, sites: tuple[str, str], targets: FloatArray) -> FloatArray:
        root = self._config.get_transform_frame_to_world(self._torso, "site").inverse()
        out = np.empty(2)
        for i, site in enumerate(sites):
            p = (root @ self._config.get_transform_frame_to_world(site, "site")).translation()
            out[i] = float(np.linalg.norm(p - targets[i]))
        return out

    def _checked_q(self, q: npt.ArrayLike) -> FloatArray:
        arr = np.array(q, dtype=np.float64)
        if arr.shape != (self._n,) or not np.all(np.isfinite(arr)):
            raise ValueError(f"q must be finite with shape ({self._n},), got {arr}")
        return arr

    def _measure(self) -> HumanoidGeometry:
        """Robot shoulder positions (torso frame) and arm segment lengths, at home."""
        model = self._config.model
        data = mujoco.MjData(model)
        data.qpos[:] = self._scene.home
        mujoco.mj_kinematics(model, data)

        def site(role: str) -> FloatArray:
            sid = model.site(self._scene.sites[role]).id
            return np.array(data.site_xpos[sid], dtype=np.float64)

        torso_id = model.site(self._torso).id
        torso_rot = data.site_xmat[torso_id].reshape(3, 3)
        torso_pos = data.site_xpos[torso_id]
        sides = ("right", "left")
        shoulders = np.array([torso_rot.T @ (site(f"{s}_shoulder") - torso_pos) for s in sides])
        upper = np.array([np.linalg.norm(site(f"{s}_elbow") - site(f"{s}_shoulder")) for s in sides])
        fore = np.array([np.linalg.norm(site(f"{s}_wrist") - site(f"{s}_elbow")) for s in sides])
        return HumanoidGeometry(shoulders=shoulders, upper=upper, fore=fore)


class HumanoidMinkReference(HumanoidIK):
    """:class:`HumanoidIK` with each sub-step's QP built from mink's own limits and solved by
    ``mink.solve_ik`` (through qpsolvers): what HumanoidIK is held to (tests) and timed against
    (``benchmarks/humanoid_ik.py``). Not for the control loop: ~1.25x slower."""

    @cached_property
    def _limits(self) -> list[mink.Limit]:
        model = self._scene.model
        return [
            mink.ConfigurationLimit(model),  # mink's defaults, not ours: the test holds ours to them
            mink.VelocityLimit(model, dict(zip(self._scene.joints, self._vmax, strict=True))),
        ]

    def _step(self, dt: float) -> None:
        velocity = mink.solve_ik(self._config, self._tasks, dt, "daqp", limits=self._limits)
        self._config.integrate_inplace(velocity, dt)


class HumanoidRetargeter:
    """Body skeleton → upper-body joint targets: keypoints, anatomical scaling, then :class:`HumanoidIK`."""

    def __init__(
        self,
        ik: HumanoidIK | None = None,
        *,
        profile: str | SkeletonProfile | None = None,
        keypoint_filter: OneEuroPointFilter | None = None,
    ) -> None:
        """Args:
        ik: The IK; a default :class:`HumanoidIK` when None.
        profile: Skeleton naming (see :data:`SKELETON_PROFILES`); detected from the first skeleton when None.
        keypoint_filter: Low-pass of the keypoints (skeleton frame, capture time) before the targets
            are built; None passes them through.
        """
        self.ik = ik if ik is not None else HumanoidIK()
        self.keypoints = KeypointMap(profile)
        self.keypoint_filter = keypoint_filter
        self._previous: HumanoidTargets | None = None

    @property
    def joint_names(self) -> tuple[str, ...]:
        """Upper-body joints the commands name."""
        return self.ik.joint_names

    def reset(self) -> None:
        """Forget the previous targets and the filter state."""
        self._previous = None
        if self.keypoint_filter is not None:
            self.keypoint_filter.reset()

    def targets(self, skeleton: BodySkeleton) -> HumanoidTargets:
        """Robot targets for ``skeleton`` (see :func:`humanoid_targets`).

        Raises:
            ValueError: the skeleton lacks a required joint (one line naming them) or is degenerate.
        """
        points = self.keypoints(skeleton)
        if self.keypoint_filter is not None:
            points = self.keypoint_filter(points, skeleton.stamp.capture_ns / 1e9)
        targets = humanoid_targets(
            points,
            self.ik.geometry,
            waist_range=self.ik.waist_range,
            previous=self._previous,
        )
        self._previous = targets
        return targets

    def __call__(
        self, skeleton: BodySkeleton, q_current: FloatArray, dt: float
    ) -> tuple[JointCommand, HumanoidIKResult]:
        """Joint targets for ``skeleton`` (stamped with its stamp) and the IK residual.

        Raises:
            ValueError: the skeleton lacks a required joint (one line naming them) or is degenerate.
        """
        result = self.ik.solve(self.targets(skeleton), q_current, dt)
        return JointCommand(skeleton.stamp, self.joint_names, result.q), result


class HumanoidBodyRetargeter:
    """The control loop's humanoid retargeter (:class:`~telerig.retarget.binding.Retargeter` protocol).

    Wraps a :class:`HumanoidRetargeter` for a driver: joints in the driver's order, one IK step per
    fresh skeleton over the time since the previous one (a 60 Hz mocap stream driven by a 100 Hz
    node moves the joints as far per sample as the speed limit allows in 16.7 ms, not in 10 ms),
    and skeletons it cannot use (a missing joint, a degenerate pose) skipped with a warning, so
    the safety chain holds the last command and its watchdog stops the robot if they persist.
    """

    def __init__(
        self, retargeter: HumanoidRetargeter, joint_names: tuple[str, ...], *, max_step_s: float = 0.1
    ) -> None:
        """Args:
        retargeter: Skeleton → IK joint targets.
        joint_names: The driver's commanded joints; the same set as ``retargeter.joint_names``.
        max_step_s: Longest interval one IK step may cover [s]; after a pause the joints then move
            at most ``velocity_limit * max_step_s`` per sample. > 0.

        Raises:
            ValueError: the joint sets differ, or ``max_step_s <= 0``.
        """
        ik_names = retargeter.joint_names
        if sorted(joint_names) != sorted(ik_names):
            raise ValueError(
                f"driver joints {', '.join(joint_names)} are not the IK's upper-body joints "
                f"{', '.join(ik_names)}"
            )
        if not max_step_s > 0:
            raise ValueError(f"max_step_s must be positive [s], got {max_step_s}")
        self.retargeter = retargeter
        self._names = tuple(joint_names)
        self._to_ik = np.array([joint_names.index(n) for n in ik_names], dtype=np.intp)
        self._to_driver = np.array([ik_names.index(n) for n in joint_names], dtype=np.intp)
        self._max_step = max_step_s
        self._last_ns: int | None = None
        self._warned: set[str] = set()
        #: Skeletons skipped because the retargeter could not use them.
        self.rejected = 0

    @property
    def accepts(self) -> tuple[type, ...]:
        """Body skeletons only."""
        return (BodySkeleton,)

    @property
    def joint_names(self) -> tuple[str, ...]:
        """The driver's joints, the order of the commands."""
        return self._names

    def __call__(
        self, sample: Sample, q_current: FloatArray, dt: float
    ) -> tuple[JointCommand | None, HumanoidIKResult | None]:
        """Joint targets for one skeleton (driver order, the skeleton's stamp) and the IK residual.

        Args:
            sample: A :class:`~telerig.ir.types.BodySkeleton`; anything else returns (None, None).
            q_current: Last command sent [rad], driver order. Shape (n,).
            dt: Control period [s]; the lower bound of the step interval.
        """
        if not isinstance(sample, BodySkeleton):
            return None, None
        capture = sample.stamp.capture_ns
        step = dt
        if self._last_ns is not None and capture > self._last_ns:
            step = min(max((capture - self._last_ns) / 1e9, dt), max(self._max_step, dt))
        self._last_ns = capture
        try:
            _, result = self.retargeter(sample, np.asarray(q_current)[self._to_ik], step)
        except ValueError as exc:
            self.rejected += 1
            message = str(exc)
            if message not in self._warned:  # once per reason: a bad stream repeats it every frame
                self._warned.add(message)
                _log.warning("%s: skipped skeleton: %s", sample.stamp.source_id, message)
            return None, None
        positions = result.q[self._to_driver]
        return JointCommand(sample.stamp, self._names, positions), result

    def reset(self) -> None:
        """Forget the step clock, the previous targets and the filter state (called while homing)."""
        self._last_ns = None
        self.retargeter.reset()
