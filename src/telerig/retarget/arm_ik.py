"""Differential inverse kinematics for an arm's end-effector pose: mink's frame task, one box QP (DAQP)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import daqp
import mink
import mujoco
import numpy as np
import numpy.typing as npt

from telerig.errors import RobotError
from telerig.ir.types import FloatArray
from telerig.robots.models.arm import ArmScene, build_arm_kinematics

__all__ = ["ArmIK", "BoxStep", "IKResult", "MinkReference", "check_ik_settings", "require_names"]

#: mink's ``ConfigurationLimit`` gain: a step closes at most this share of the distance to a limit.
LIMIT_GAIN = 0.95
#: mink's ``solve_ik`` default damping on every joint [1/rad^2]: keeps the QP strictly convex.
DAMPING = 1e-12


@dataclass(frozen=True, slots=True)
class IKResult:
    """One IK step.

    Attributes:
        q: Arm joint positions to command [rad], in the IK's joint order. Shape (n,).
        position_error: Distance from the reached to the target ee position [m].
        orientation_error: Rotation angle from the reached to the target ee orientation [rad].
        flagged: True when ``position_error`` exceeds the IK's ``residual_threshold_m``: the target is
            out of reach, or too far to cover in one step at the velocity limit.
    """

    q: FloatArray
    position_error: float
    orientation_error: float
    flagged: bool

    def metrics(self) -> dict[str, float]:
        """The errors recorded every tick: ``position_error_m``, ``orientation_error_rad``."""
        return {"position_error_m": self.position_error, "orientation_error_rad": self.orientation_error}


class ArmIK:
    """Track an end-effector pose target, one velocity-limited step per call.

    Each :meth:`solve` runs ``iterations`` QPs over sub-steps of ``dt``: a frame task on the ee
    site (mink's, with Levenberg-Marquardt damping that grows with the error, which keeps steps
    sane near singularities and for unreachable targets), a weak posture task toward home for a
    well-defined solution, joint position limits and joint speed limits. The joint step over one
    call is therefore at most ``velocity_limit * dt`` per joint.

    This is the QP ``mink.solve_ik`` builds from a ``FrameTask``, a ``PostureTask``, a
    ``ConfigurationLimit``, a ``VelocityLimit`` and a ``DofFreezingTask`` for the other joints
    (the tests hold it to mink's solution), written as what it is: a box-constrained QP over the
    arm joints (:class:`BoxStep`). mink also freezes the other joints with equalities.

    The solver owns its own ``MjModel``/``MjData`` and never touches a simulation's data.
    Targets are in the robot base frame; the model may place the base anywhere in its world.
    """

    def __init__(
        self,
        scene: ArmScene | None = None,
        *,
        velocity_limit: npt.ArrayLike = np.pi,
        position_cost: float = 1.0,
        orientation_cost: float = 0.5,
        posture_cost: float = 1e-3,
        lm_damping: float = 1e-2,
        iterations: int = 3,
        residual_threshold_m: float = 0.05,
    ) -> None:
        """Build the IK problem.

        Args:
            scene: Arm model; :func:`~telerig.robots.models.arm.build_arm_kinematics` when None.
                Joints other than ``scene.arm_joints`` are held at their ``qpos0``; the
                kinematic model (arm joints only) solves about twice as fast as a full scene.
            velocity_limit: Joint speed limit [rad/s], scalar or shape (n,).
            position_cost: Frame-task weight on position error [1/m].
            orientation_cost: Frame-task weight on orientation error [1/rad].
            posture_cost: Posture-task weight toward ``scene.home`` [1/rad]; keep small, the
                6-DoF arm has no null space so it trades against tracking accuracy.
            lm_damping: Frame-task Levenberg-Marquardt damping (scaled by the squared error).
            iterations: QP sub-steps per :meth:`solve`. >= 1.
            residual_threshold_m: Position error above which a result is flagged [m].

        Raises:
            RobotError: a joint, site or body the scene names is not in its model.
            ValueError: a numeric argument is out of range.
        """
        self._scene = scene if scene is not None else build_arm_kinematics()
        model = self._scene.model
        joints = self._scene.arm_joints
        n = len(joints)
        require_names(model, mujoco.mjtObj.mjOBJ_JOINT, joints)
        require_names(model, mujoco.mjtObj.mjOBJ_SITE, (self._scene.ee_site,))
        require_names(model, mujoco.mjtObj.mjOBJ_BODY, (self._scene.base_body,))
        vmax = check_ik_settings(iterations, residual_threshold_m, velocity_limit, n)

        jids = [model.joint(j).id for j in joints]
        kinds = {int(model.jnt_type[i]) for i in jids}
        if not kinds <= {mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE}:
            raise RobotError(
                f"arm IK needs hinge or slide joints; {', '.join(joints)} include a ball or free joint"
            )

        self._n = n
        self._iterations = iterations
        self._threshold = residual_threshold_m
        self._qadr = np.array([model.joint(j).qposadr[0] for j in joints])
        self._dofs = np.array([int(model.joint(j).dofadr[0]) for j in joints])
        # Other joints (fingers, free objects) stay at their model defaults.
        self._q_full = model.qpos0.copy()
        self._q_full[self._qadr] = self._scene.home
        self._config = mink.Configuration(model, self._q_full)
        self._frame_task = mink.FrameTask(
            frame_name=self._scene.ee_site,
            frame_type="site",
            position_cost=position_cost,
            orientation_cost=orientation_cost,
            lm_damping=lm_damping,
        )
        if not posture_cost >= 0:
            raise ValueError(f"posture_cost must be >= 0 [1/rad], got {posture_cost}")
        self._posture_weight = posture_cost**2
        self._settings = (position_cost, orientation_cost, posture_cost, lm_damping)
        self._home = self._scene.home.astype(np.float64)
        self._vmax = vmax
        self._box = BoxStep(model, jids, vmax, "arm IK")
        self._lower, self._upper = self._box.lower, self._box.upper
        # The base is welded to the world: its pose is constant, read once.
        data = mujoco.MjData(model)
        mujoco.mj_kinematics(model, data)
        base = model.body(self._scene.base_body).id
        self._world_base = mink.SE3.from_rotation_and_translation(
            mink.SO3(data.xquat[base].copy()), data.xpos[base].copy()
        )

    @property
    def joint_names(self) -> tuple[str, ...]:
        """Arm joints, in the order of ``q``."""
        return self._scene.arm_joints

    @property
    def home(self) -> FloatArray:
        """Home configuration the posture task pulls toward [rad]. Shape (n,)."""
        return self._scene.home

    def forward(self, q: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
        """End-effector pose at joint positions ``q`` [rad] (shape (n,)).

        Returns:
            Position [m] (shape (3,)) and orientation (w, x, y, z) (shape (4,)), base frame.
        """
        self._q_full[self._qadr] = self._checked_q(q)
        self._config.update(self._q_full)
        pose = self._ee_in_base()
        return pose.translation(), pose.rotation().wxyz.copy()

    def solve(
        self,
        target_position: npt.ArrayLike,
        target_orientation: npt.ArrayLike,
        q_current: npt.ArrayLike,
        dt: float,
    ) -> IKResult:
        """One IK step from ``q_current`` toward the target pose.

        Args:
            target_position: Target ee position [m] in the robot base frame. Shape (3,).
            target_orientation: Target ee orientation (w, x, y, z) in the base frame. Shape (4,).
            q_current: Current arm joint positions [rad]. Shape (n,).
            dt: Control period [s]; bounds the step to ``velocity_limit * dt``.

        Returns:
            The next joint positions and the ee error they leave.

        Raises:
            ValueError: an argument has the wrong shape, is not finite, or ``dt <= 0``.
        """
        position = np.asarray(target_position, dtype=np.float64)
        orientation = np.asarray(target_orientation, dtype=np.float64)
        if position.shape != (3,) or not np.all(np.isfinite(position)):
            raise ValueError(f"target_position must be finite with shape (3,), got {position}")
        norm = float(np.linalg.norm(orientation)) if orientation.shape == (4,) else 0.0
        if not np.isfinite(norm) or norm < 1e-9:
            raise ValueError(f"target_orientation must be a non-zero quaternion (w,x,y,z), got {orientation}")
        if not dt > 0:
            raise ValueError(f"dt must be positive [s], got {dt}")
        # Clamp into the limits: from outside them the step's bounds are an empty box.
        q = np.clip(self._checked_q(q_current), self._lower, self._upper)

        target_base = mink.SE3.from_rotation_and_translation(mink.SO3(orientation / norm), position)
        self._frame_task.set_target(self._world_base @ target_base)
        config = self._config
        self._q_full[self._qadr] = q
        config.update(self._q_full)
        sub_dt = dt / self._iterations
        for _ in range(self._iterations):
            self._q_full[self._qadr] += self._step(sub_dt)
            config.update(self._q_full)

        return self._result(config, target_base)

    def _result(self, config: mink.Configuration, target_base: mink.SE3) -> IKResult:
        """The joints ``config`` holds and the ee error they leave against ``target_base``."""
        error = self._ee_in_base(config).inverse() @ target_base
        position_error = float(np.linalg.norm(error.translation()))
        orientation_error = float(np.linalg.norm(error.rotation().log()))
        q_next = config.q[self._qadr]
        q_next.flags.writeable = False
        return IKResult(
            q=q_next,
            position_error=position_error,
            orientation_error=orientation_error,
            flagged=position_error > self._threshold,
        )

    def _step(self, dt: float) -> FloatArray:
        """One QP from the configuration's current joints: the joint step [rad] over ``dt``.

        Minimises ``|J dq + e|_W^2 + mu |dq|^2 + w_p |q + dq - home|^2`` (mink's frame-task
        residual: cost-weighted Jacobian ``J``, error ``e`` and its Levenberg-Marquardt ``mu``)
        subject to ``max(-v dt, g (lower - q)) <= dq <= min(v dt, g (upper - q))``.
        """
        jac, err, mu = self._frame_task.compute_qp_residual(self._config)
        jac = jac[:, self._dofs]
        q = self._q_full[self._qadr]
        hessian = jac.T @ jac
        hessian.flat[:: self._n + 1] += self._posture_weight + mu + DAMPING
        gradient = self._posture_weight * (q - self._home) - err @ jac
        return self._box.solve(hessian, gradient, q, dt)

    def _checked_q(self, q: npt.ArrayLike) -> FloatArray:
        arr = np.array(q, dtype=np.float64)
        if arr.shape != (self._n,) or not np.all(np.isfinite(arr)):
            raise ValueError(f"q must be finite with shape ({self._n},), got {arr}")
        return arr

    def _ee_in_base(self, config: mink.Configuration | None = None) -> mink.SE3:
        world_ee = (config or self._config).get_transform_frame_to_world(self._scene.ee_site, "site")
        return self._world_base.inverse() @ world_ee


class BoxStep:
    """The constraints of one differential-IK QP as what they are, bounds on the joint step, and
    the QP handed to DAQP directly.

    mink's ``ConfigurationLimit`` (gain :data:`LIMIT_GAIN`) and ``VelocityLimit`` bound each joint's
    step ``dq`` over ``dt``: ``max(-v dt, g (lower - q)) <= dq <= min(v dt, g (upper - q))``.
    ``mink.solve_ik`` stacks them as 4n general inequalities and goes through qpsolvers' checks and
    conversions; as n bounds DAQP solves the same problem in a fraction of the time
    (``benchmarks/arm_ik.py``), which every control tick of an IK-driven robot pays.

    Args:
        model: The IK's model.
        joints: Ids of the hinge or slide joints the QP moves, in the order of ``q``.
        velocity_limit: Their speed limits [rad/s]. Shape (n,).
        what: Who solves, for the error message (``"arm IK"``).
    """

    def __init__(
        self, model: mujoco.MjModel, joints: Sequence[int], velocity_limit: FloatArray, what: str
    ) -> None:
        n = len(joints)
        # An unlimited joint's range reads [0, 0]: its bounds are the speed limit's alone.
        limited = model.jnt_limited[joints].astype(bool)
        self.lower: FloatArray = np.where(limited, model.jnt_range[joints, 0], -np.inf)
        self.upper: FloatArray = np.where(limited, model.jnt_range[joints, 1], np.inf)
        self._vmax = velocity_limit
        self._what = what
        # Bounds only: an empty constraint matrix, every row a simple bound.
        self._no_rows = np.zeros((0, n))
        self._sense = np.zeros(n, dtype=np.intc)
        self._lb = np.empty(n)
        self._ub = np.empty(n)

    def solve(self, hessian: FloatArray, gradient: FloatArray, q: FloatArray, dt: float) -> FloatArray:
        """The step ``dq`` [rad] minimising ``dq' H dq / 2 + c' dq`` within the bounds at ``q`` over ``dt``.

        Raises:
            RobotError: DAQP found no solution (with a strictly convex ``H`` and ``q`` within the
                limits, only a numerical failure).
        """
        reach = self._vmax * dt
        np.maximum(-reach, LIMIT_GAIN * (self.lower - q), out=self._lb)
        np.minimum(reach, LIMIT_GAIN * (self.upper - q), out=self._ub)
        step, _, exitflag, _ = daqp.solve(hessian, gradient, self._no_rows, self._ub, self._lb, self._sense)
        if exitflag <= 0:
            raise RobotError(f"{self._what}: the QP found no step (DAQP exit flag {exitflag}); q={q}")
        return np.asarray(step)


class MinkReference:
    """The QP one :class:`ArmIK` step solves, built from mink's own tasks and limits and solved by
    ``mink.solve_ik`` (through qpsolvers): what ArmIK is held to (tests) and timed against
    (``benchmarks/arm_ik.py``). Not for the control loop: ~3x slower."""

    def __init__(self, ik: ArmIK) -> None:
        """The same model, costs, damping and limits as ``ik``."""
        scene = ik._scene
        model = scene.model
        position_cost, orientation_cost, posture_cost, lm_damping = ik._settings
        self._ik = ik
        self._qadr = ik._qadr
        self._q_full = model.qpos0.copy()
        self._q_full[self._qadr] = scene.home
        self._config = mink.Configuration(model, self._q_full)
        self._frame = mink.FrameTask(
            scene.ee_site,
            "site",
            position_cost=position_cost,
            orientation_cost=orientation_cost,
            lm_damping=lm_damping,
        )
        costs = np.zeros(model.nv)
        costs[ik._dofs] = posture_cost
        posture = mink.PostureTask(model, cost=costs)
        posture.set_target(self._q_full.copy())
        self._tasks = [self._frame, posture]
        self._limits = [
            mink.ConfigurationLimit(model),  # mink's defaults, not ours: the test holds ours to them
            mink.VelocityLimit(model, dict(zip(scene.arm_joints, ik._vmax, strict=True))),
        ]
        frozen = [i for i in range(model.nv) if i not in set(ik._dofs.tolist())]
        self._constraints = [mink.DofFreezingTask(model, dof_indices=frozen)] if frozen else []

    def solve(
        self, target_position: npt.ArrayLike, target_orientation: npt.ArrayLike, q: npt.ArrayLike, dt: float
    ) -> IKResult:
        """:meth:`ArmIK.solve` with one sub-step, through mink: the joints after one QP step of
        ``dt`` from ``q`` (within the limits) toward the target, and the error they leave."""
        orientation = np.asarray(target_orientation, dtype=np.float64)
        target = mink.SE3.from_rotation_and_translation(
            mink.SO3(orientation / np.linalg.norm(orientation)), np.asarray(target_position, dtype=np.float64)
        )
        self._frame.set_target(self._ik._world_base @ target)
        self._q_full[self._qadr] = q
        self._config.update(self._q_full)
        velocity = mink.solve_ik(
            self._config,
            self._tasks,
            dt,
            "daqp",
            limits=self._limits,
            constraints=self._constraints,
            safety_break=False,
        )
        self._config.integrate_inplace(velocity, dt)
        return self._ik._result(self._config, target)


def require_names(model: mujoco.MjModel, kind: mujoco.mjtObj, names: Sequence[str]) -> None:
    """Raise a one-line RobotError naming the first of ``names`` the model lacks and what it has."""
    have = [mujoco.mj_id2name(model, kind, i) for i in range(_count(model, kind))]
    for name in names:
        if name not in have:
            what = kind.name.removeprefix("mjOBJ_").lower()
            raise RobotError(f"{what} '{name}' not found. Available: {', '.join(h for h in have if h)}")


def check_ik_settings(
    iterations: int, residual_threshold_m: float, velocity_limit: npt.ArrayLike, n: int
) -> FloatArray:
    """Validate the settings every differential IK here takes; the speed limits as shape (n,) [rad/s].

    Raises:
        ValueError: a setting is out of range (one line naming it).
    """
    if iterations < 1:
        raise ValueError(f"iterations must be >= 1, got {iterations}")
    if residual_threshold_m <= 0:
        raise ValueError(f"residual_threshold_m must be positive [m], got {residual_threshold_m}")
    vmax = np.broadcast_to(np.asarray(velocity_limit, dtype=np.float64), (n,)).copy()
    if not np.all((vmax > 0) & np.isfinite(vmax)):
        raise ValueError(f"velocity_limit must be positive and finite [rad/s], got {vmax}")
    return vmax


def _count(model: mujoco.MjModel, kind: mujoco.mjtObj) -> int:
    counts = {
        mujoco.mjtObj.mjOBJ_JOINT: model.njnt,
        mujoco.mjtObj.mjOBJ_SITE: model.nsite,
        mujoco.mjtObj.mjOBJ_BODY: model.nbody,
    }
    return int(counts[kind])
