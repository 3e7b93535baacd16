"""Mobile reach: IK over the arm plus virtual planar base joints, then base-first execution via the WBC."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import mink
import mujoco
import numpy as np
import numpy.typing as npt

from telerig.ir.types import FloatArray
from telerig.retarget.wbc import EE_MODE, WHOLE_BODY_MODE, WholeBodyController, _rotvec
from telerig.robots.models.tiago import TiagoScene, build_tiago_kinematics

__all__ = [
    "MobileReachExecutor",
    "MobileReachPlan",
    "MobileReachPlanner",
    "ReachOutcome",
    "manual_instructions",
]

_NB = 3
Phase = Literal["idle", "base", "arm", "done"]


def _wrap(angle: float) -> float:
    """Angle wrapped to [-pi, pi) [rad]."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def _capped(vector: FloatArray, cap: float) -> FloatArray:
    """``vector`` scaled down to norm ``cap`` when longer."""
    norm = float(np.linalg.norm(vector))
    return vector * (cap / norm) if norm > cap else vector


def _unit_quat(value: npt.ArrayLike, name: str) -> FloatArray:
    quat = np.asarray(value, dtype=np.float64)
    norm = float(np.linalg.norm(quat)) if quat.shape == (4,) else 0.0
    if not math.isfinite(norm) or norm < 1e-9:
        raise ValueError(f"{name} must be a non-zero quaternion (w, x, y, z), got {quat}")
    return quat / norm


def _position(value: npt.ArrayLike, name: str) -> FloatArray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite with shape (3,) [m], got {arr}")
    return arr


def manual_instructions(
    base_start: npt.ArrayLike, base_goal: npt.ArrayLike, *, tolerance: float = 0.02
) -> int:
    """Operator instructions the same reach takes without the planner, with the WBC's two modes.

    The operator drives one thing at a time: (1) translate the base to the goal, (2) turn it to
    the goal heading (both in whole-body mode), (3) switch to end-effector mode, (4) move the hand
    to the target. Steps (1)-(3) count only when the base has to move by more than ``tolerance``
    ([m] for the translation, [rad] for the heading); step (4) always counts.

    Args:
        base_start: Base pose (x [m], y [m], yaw [rad]) before the reach. Shape (3,).
        base_goal: Base pose at the planned solution. Shape (3,).
        tolerance: Smallest base motion that needs an instruction of its own.
    """
    start = np.asarray(base_start, dtype=np.float64)
    goal = np.asarray(base_goal, dtype=np.float64)
    translate = float(np.hypot(*(goal[:2] - start[:2]))) > tolerance
    turn = abs(_wrap(float(goal[2] - start[2]))) > tolerance
    return int(translate) + int(turn) + int(translate or turn) + 1


@dataclass(frozen=True, slots=True)
class MobileReachPlan:
    """Where the base goes and how the arm finishes, for one end-effector target.

    Attributes:
        target_position: Target grasp-site position [m], world frame. Shape (3,).
        target_orientation: Target hand orientation (w, x, y, z), world frame. Shape (4,).
        q_start: Configuration the plan starts from, order of ``TIAGO_JOINTS``. Shape (10,).
        q_goal: IK solution: base pose and arm configuration that reach the target. Shape (10,).
        base_moves: False when the arm reaches the target from where the base stands.
        position_error: Grasp-site distance to the target at ``q_goal`` [m].
        orientation_error: Hand rotation from the target at ``q_goal`` [rad].
        reachable: Both errors are within the planner's tolerances.
        manual_instructions: Instructions the reach takes without the planner
            (:func:`manual_instructions`).
    """

    target_position: FloatArray
    target_orientation: FloatArray
    q_start: FloatArray
    q_goal: FloatArray
    base_moves: bool
    position_error: float
    orientation_error: float
    reachable: bool
    manual_instructions: int

    @property
    def base_goal(self) -> FloatArray:
        """Base pose to drive to: x [m], y [m] (world), yaw [rad]. Shape (3,)."""
        return self.q_goal[:_NB]

    @property
    def arm_goal(self) -> FloatArray:
        """Torso [m] and arm [rad] configuration that finishes the reach. Shape (7,)."""
        return self.q_goal[_NB:]


class MobileReachPlanner:
    """IK for an end-effector target over the extended chain: planar base (x, y, yaw) + torso + arm.

    The arm alone is tried first (base joints frozen). When the target is out of its reach the base
    joints are unlocked and the same IK runs again: a frame task on the grasp site, a posture
    task that keeps the torso and arm near their home posture (so the base, which costs nothing,
    does the travelling and the arm ends in a comfortable configuration), and joint limits. Solved
    with mink on the 10-joint kinematic model (``daqp``), iterated to convergence: planning happens
    once per instruction, not every tick.
    """

    def __init__(
        self,
        scene: TiagoScene | None = None,
        *,
        position_tolerance: float = 0.005,
        orientation_tolerance: float = 0.02,
        posture_cost: float = 0.02,
        max_iterations: int = 400,
    ) -> None:
        """Build the planner.

        Args:
            scene: TIAGo kinematic model; :func:`build_tiago_kinematics` when None.
            position_tolerance: Largest grasp-site error of a reachable plan [m].
            orientation_tolerance: Largest hand rotation error of a reachable plan [rad].
            posture_cost: Posture-task weight on the torso and arm [1/rad], relative to the frame
                task (1 [1/m], 1 [1/rad]).
            max_iterations: IK iterations per attempt. >= 1.

        Raises:
            ValueError: a tolerance or cost is not positive, or ``max_iterations < 1``.
        """
        if not position_tolerance > 0 or not orientation_tolerance > 0:
            raise ValueError("position_tolerance [m] and orientation_tolerance [rad] must be positive")
        if not posture_cost > 0:
            raise ValueError(f"posture_cost must be positive, got {posture_cost}")
        if max_iterations < 1:
            raise ValueError(f"max_iterations must be >= 1, got {max_iterations}")
        self._scene = scene if scene is not None else build_tiago_kinematics()
        model = self._scene.model
        self._model = model
        self._pos_tol = position_tolerance
        self._ori_tol = orientation_tolerance
        self._iterations = max_iterations
        self._config = mink.Configuration(model, self._scene.home.copy())
        self._frame = mink.FrameTask(
            self._scene.ee_site, "site", position_cost=1.0, orientation_cost=1.0, lm_damping=1e-3
        )
        costs = np.zeros(model.nv)
        costs[_NB:] = posture_cost
        self._posture = mink.PostureTask(model, cost=costs)
        self._posture.set_target(self._scene.home.copy())
        self._limits = [mink.ConfigurationLimit(model)]
        self._freeze_base = [mink.DofFreezingTask(model, dof_indices=list(range(_NB)))]

    @property
    def scene(self) -> TiagoScene:
        """The kinematic model the planner uses."""
        return self._scene

    def plan(
        self, target_position: npt.ArrayLike, target_orientation: npt.ArrayLike, q: npt.ArrayLike
    ) -> MobileReachPlan:
        """Plan a reach of the grasp site to a world-frame pose from configuration ``q``.

        Args:
            target_position: Target grasp-site position [m], world frame. Shape (3,).
            target_orientation: Target hand orientation (w, x, y, z), world frame. Shape (4,).
            q: Current configuration, order of ``TIAGO_JOINTS``. Shape (10,).

        Returns:
            The plan; check ``reachable`` (False: even with the base the target was not reached
            within the tolerances, e.g. too high or too low for the torso and arm).

        Raises:
            ValueError: an argument has the wrong shape or is not finite.
        """
        position = _position(target_position, "target_position")
        orientation = _unit_quat(target_orientation, "target_orientation")
        q0 = np.array(q, dtype=np.float64)
        if q0.shape != (len(self._scene.joints),) or not np.all(np.isfinite(q0)):
            raise ValueError(f"q must be finite with shape ({len(self._scene.joints)},), got {q0}")
        q0 = np.clip(q0, self._scene.limits.lower, self._scene.limits.upper)
        target = mink.SE3.from_rotation_and_translation(mink.SO3(orientation), position)
        self._frame.set_target(target)

        q_arm, pos_err, ori_err = self._solve(q0, freeze_base=True)
        base_moves = not (pos_err <= self._pos_tol and ori_err <= self._ori_tol)
        if base_moves:
            q_arm, pos_err, ori_err = self._solve(q0, freeze_base=False)
        q_goal = q_arm.copy()
        if base_moves:  # the nearest equivalent heading, so the base never turns the long way
            q_goal[2] = q0[2] + _wrap(float(q_goal[2] - q0[2]))
        else:  # frozen up to the QP's tolerance: make it exact
            q_goal[:_NB] = q0[:_NB]
        for arr in (position, orientation, q0, q_goal):
            arr.flags.writeable = False
        return MobileReachPlan(
            target_position=position,
            target_orientation=orientation,
            q_start=q0,
            q_goal=q_goal,
            base_moves=base_moves,
            position_error=pos_err,
            orientation_error=ori_err,
            reachable=pos_err <= self._pos_tol and ori_err <= self._ori_tol,
            manual_instructions=manual_instructions(q0[:_NB], q_goal[:_NB]),
        )

    def _solve(self, q0: FloatArray, *, freeze_base: bool) -> tuple[FloatArray, float, float]:
        config = self._config
        config.update(q0)
        constraints = self._freeze_base if freeze_base else []
        pos_err = ori_err = math.inf
        for _ in range(self._iterations):
            velocity = mink.solve_ik(
                config,
                [self._frame, self._posture],
                1.0,
                "daqp",
                limits=self._limits,
                constraints=constraints,
            )
            config.integrate_inplace(velocity, 1.0)
            error = self._frame.compute_error(config)
            pos_err = float(np.linalg.norm(error[:3]))
            ori_err = float(np.linalg.norm(error[3:]))
            if float(np.linalg.norm(velocity)) < 1e-6:
                break
        return config.q.copy(), pos_err, ori_err


@dataclass(frozen=True, slots=True)
class ReachOutcome:
    """Result of :meth:`MobileReachExecutor.run`.

    Attributes:
        q: Final configuration. Shape (10,).
        reached: The executor finished (phase ``done``) within the time limit.
        duration: Simulated time taken [s].
        position_error: Final grasp-site distance to the target [m].
        orientation_error: Final hand rotation from the target [rad].
        instructions: Operator instructions given (1 per :meth:`MobileReachExecutor.instruct`).
        manual_instructions: Instructions the same reach takes without the planner.
        efficiency: ``manual_instructions / instructions``: the seed's eta.
    """

    q: FloatArray
    reached: bool
    duration: float
    position_error: float
    orientation_error: float
    instructions: int
    manual_instructions: int
    efficiency: float


class MobileReachExecutor:
    """Carry out a mobile reach from one operator instruction: drive the base, then finish with the arm.

    :meth:`instruct` takes the target (one instruction) and plans it; :meth:`action` then returns,
    every tick, the 8-D action for the :class:`~telerig.retarget.wbc.WholeBodyController`:

    * ``base`` phase (whole-body mode, hand held on the base): a saturated proportional base twist
      toward the planned base pose, until it is within ``base_tolerance``;
    * ``arm`` phase (EE mode, base still): a saturated proportional hand twist toward the target,
      with the controller's posture set to the plan's arm configuration, until the hand is within
      the planner's tolerances (times ``finish_margin``);
    * ``done``: zero twist in EE mode.

    It counts instructions; :attr:`efficiency` is the seed's eta, instructions needed without the
    planner over instructions given.
    """

    def __init__(
        self,
        controller: WholeBodyController,
        planner: MobileReachPlanner | None = None,
        *,
        base_gain: float = 1.5,
        arm_gain: float = 2.0,
        max_base_speed: float = 0.5,
        max_base_turn: float = 1.0,
        max_hand_speed: float = 0.25,
        max_hand_turn: float = 1.0,
        base_tolerance: float = 0.01,
        hand_tolerance: float = 0.002,
        hand_turn_tolerance: float = 0.02,
    ) -> None:
        """Build the executor around ``controller``.

        Args:
            controller: The whole-body controller the actions are for.
            planner: Planner on the same robot; one on ``controller.scene`` when None.
            base_gain: Base approach gain [1/s].
            arm_gain: Hand approach gain [1/s].
            max_base_speed: Base speed cap [m/s].
            max_base_turn: Base yaw-rate cap [rad/s].
            max_hand_speed: Hand speed cap [m/s].
            max_hand_turn: Hand angular speed cap [rad/s].
            base_tolerance: Base position [m] and yaw [rad] error that ends the base phase.
            hand_tolerance: Hand position error that ends the arm phase [m].
            hand_turn_tolerance: Hand rotation error that ends the arm phase [rad].

        Raises:
            ValueError: a gain, cap or tolerance is not positive.
        """
        values = (base_gain, arm_gain, max_base_speed, max_base_turn, max_hand_speed, max_hand_turn)
        tolerances = (base_tolerance, hand_tolerance, hand_turn_tolerance)
        if not all(v > 0 for v in values + tolerances):
            raise ValueError("gains, speed caps and tolerances must all be positive")
        self._wbc = controller
        self._planner = planner if planner is not None else MobileReachPlanner(controller.scene)
        self._base_gain = base_gain
        self._arm_gain = arm_gain
        self._base_caps = (max_base_speed, max_base_turn)
        self._hand_caps = (max_hand_speed, max_hand_turn)
        self._base_tol = base_tolerance
        self._hand_tol = (hand_tolerance, hand_turn_tolerance)
        self._plan: MobileReachPlan | None = None
        self._phase: Phase = "idle"
        self._instructions = 0
        self._manual = 0
        self._target_r = np.eye(3)

    @property
    def phase(self) -> Phase:
        """``idle`` before an instruction, then ``base``, ``arm`` and ``done``."""
        return self._phase

    @property
    def plan(self) -> MobileReachPlan | None:
        """Plan of the current instruction; None before the first."""
        return self._plan

    @property
    def instructions(self) -> int:
        """Operator instructions given so far."""
        return self._instructions

    @property
    def efficiency(self) -> float:
        """eta: instructions the reaches need without the planner / instructions given (0 before any)."""
        return self._manual / self._instructions if self._instructions else 0.0

    def instruct(
        self, target_position: npt.ArrayLike, target_orientation: npt.ArrayLike, q: npt.ArrayLike
    ) -> MobileReachPlan:
        """One operator instruction: reach the grasp site to a world-frame pose, starting from ``q``.

        Args:
            target_position: Target grasp-site position [m], world frame. Shape (3,).
            target_orientation: Target hand orientation (w, x, y, z), world frame. Shape (4,).
            q: Current configuration. Shape (10,).

        Returns:
            The plan being executed.

        Raises:
            ValueError: an argument has the wrong shape or is not finite.
        """
        return self.execute(self._planner.plan(target_position, target_orientation, q))

    def execute(self, plan: MobileReachPlan) -> MobileReachPlan:
        """One operator instruction: carry out a plan made beforehand (e.g. previewed, then confirmed).

        The plan must be for this executor's robot model; it is not re-planned, so check that the
        robot is still at ``plan.q_start`` before calling this.

        Returns:
            ``plan``, now being executed.
        """
        self._plan = plan
        self._instructions += 1
        self._manual += plan.manual_instructions
        rotation = np.empty(9)
        mujoco.mju_quat2Mat(rotation, plan.target_orientation)
        self._target_r = rotation.reshape(3, 3)
        self._phase = "base" if plan.base_moves else "arm"
        if not plan.base_moves:
            self._wbc.posture = plan.arm_goal
        return plan

    def action(self, q: npt.ArrayLike) -> FloatArray:
        """Action for the controller's next tick at configuration ``q`` (shape (10,)). Shape (8,)."""
        qc = np.asarray(q, dtype=np.float64)
        out = np.zeros(8)
        plan = self._plan
        if plan is None or self._phase in ("idle", "done"):
            out[7] = EE_MODE
            return out
        if self._phase == "base":
            goal = plan.base_goal
            c, s = math.cos(qc[2]), math.sin(qc[2])
            dx, dy = goal[0] - qc[0], goal[1] - qc[1]
            ex, ey = c * dx + s * dy, -s * dx + c * dy  # base-frame position error
            eyaw = _wrap(float(goal[2] - qc[2]))
            if math.hypot(ex, ey) < self._base_tol and abs(eyaw) < self._base_tol:
                self._phase = "arm"
                self._wbc.posture = plan.arm_goal
            else:
                out[:2] = _capped(self._base_gain * np.array([ex, ey]), self._base_caps[0])
                out[5] = float(np.clip(self._base_gain * eyaw, -self._base_caps[1], self._base_caps[1]))
                out[7] = WHOLE_BODY_MODE
                return out
        pos_err, rot_err = self._hand_error(qc)
        if (
            float(np.linalg.norm(pos_err)) < self._hand_tol[0]
            and float(np.linalg.norm(rot_err)) < self._hand_tol[1]
        ):
            self._phase = "done"
            out[7] = EE_MODE
            return out
        out[:3] = _capped(self._arm_gain * pos_err, self._hand_caps[0])
        out[3:6] = _capped(self._arm_gain * rot_err, self._hand_caps[1])
        out[7] = EE_MODE
        return out

    def run(self, q: npt.ArrayLike, dt: float = 0.002, max_time: float = 20.0) -> ReachOutcome:
        """Execute the current instruction kinematically (``q`` ← the controller's output), for tests.

        Args:
            q: Start configuration. Shape (10,).
            dt: Tick period [s].
            max_time: Simulated time limit [s].

        Raises:
            ValueError: no instruction was given, or ``dt``/``max_time`` is not positive.
        """
        if self._plan is None:
            raise ValueError(
                "no target to reach: call instruct(target_position, target_orientation, q) first"
            )
        if not dt > 0 or not max_time > 0:
            raise ValueError(f"dt and max_time must be positive [s], got {dt} and {max_time}")
        qc = np.array(q, dtype=np.float64)
        t = 0.0
        while t < max_time and self._phase != "done":
            qc = np.array(self._wbc.step(self.action(qc), qc, dt).q)
            t += dt
        # Let the last commanded velocity brake to zero within the acceleration limit.
        while float(np.abs(self._wbc.velocity).max()) > 1e-4 and t < max_time + 1.0:
            qc = np.array(self._wbc.step(np.zeros(8), qc, dt).q)
            t += dt
        pos_err, rot_err = self._hand_error(qc)
        final = qc.copy()
        final.flags.writeable = False
        return ReachOutcome(
            q=final,
            reached=self._phase == "done",
            duration=t,
            position_error=float(np.linalg.norm(pos_err)),
            orientation_error=float(np.linalg.norm(rot_err)),
            instructions=self._instructions,
            manual_instructions=self._manual,
            efficiency=self.efficiency,
        )

    def _hand_error(self, q: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Target minus hand, position [m] and rotation vector [rad], in base-frame axes."""
        assert self._plan is not None
        p, r = self._wbc.hand_in_base(q)
        c, s = math.cos(q[2]), math.sin(q[2])
        rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        target_p = rz.T @ (self._plan.target_position - np.array([q[0], q[1], 0.0]))
        target_r = rz.T @ self._target_r
        return target_p - p, _rotvec(target_r @ r.T)
