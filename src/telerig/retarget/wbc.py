"""Whole-body QP velocity controller for the TIAGo mobile manipulator (holonomic base + torso + arm)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import daqp
import mujoco
import numpy as np
import numpy.typing as npt

from telerig.errors import RobotError
from telerig.ir.types import FloatArray
from telerig.robots.models.tiago import TiagoScene, build_tiago_kinematics

__all__ = ["EE_MODE", "WHOLE_BODY_MODE", "TaskErrors", "WBCResult", "WholeBodyController"]

#: ``action[7]`` value of end-effector mode: the twist moves the hand, the base stands still.
EE_MODE = 0
#: ``action[7]`` value of whole-body mode: the twist drives the base, the hand holds its pose on it.
WHOLE_BODY_MODE = 1

_NB = 3  # base joints (x, y, yaw), first in q
_N = 10  # base + torso + 6 arm joints
# Most the hand reference may run ahead of the hand [m], [rad] (anti-windup, see _advance_reference).
_MAX_LAG_M = 0.02
_MAX_LAG_RAD = 0.1


@dataclass(frozen=True, slots=True)
class TaskErrors:
    """Per-task tracking errors of one tick, for recording.

    Velocity residuals are ``‖J q̇ - v_target‖`` of each task after the QP (what the limits or a
    higher-weight task kept from being tracked); a task that is not active in the mode reports 0.

    Attributes:
        ee_linear: Hand linear velocity residual [m/s]: the commanded twist (EE mode) or the
            hand-hold velocity relative to the base (whole-body mode).
        ee_angular: Hand angular velocity residual [rad/s], same targets.
        base_linear: Base planar velocity residual [m/s] (EE mode: against standing still).
        base_angular: Base yaw-rate residual [rad/s].
        elbow: Elbow planar velocity residual relative to the base [m/s]; whole-body mode only.
        hand_position: Hand position error against its reference [m]: in EE mode the pose the
            commanded twist integrates to; in whole-body mode the pose held on the base since the
            mode was entered (horizontal part only: the height follows ``a[2]``).
        hand_orientation: Hand rotation error against the same reference [rad].
    """

    ee_linear: float
    ee_angular: float
    base_linear: float
    base_angular: float
    elbow: float
    hand_position: float
    hand_orientation: float

    def as_dict(self) -> dict[str, float]:
        """The errors by field name, for a recorder."""
        return {name: getattr(self, name) for name in self.__slots__}


@dataclass(frozen=True, slots=True)
class WBCResult:
    """One controller tick.

    Attributes:
        q: Joint positions to command at the end of the tick, order of
            :attr:`WholeBodyController.joint_names` ([m] for base x/y and torso, [rad] otherwise).
            Shape (10,).
        qdot: Joint velocities over the tick: base x/y in the world frame [m/s], yaw rate
            [rad/s], torso [m/s], arm [rad/s]. Shape (10,). Feed ``qdot[:3]`` to base velocity servos.
        gripper: Gripper closure from the action, 0 open .. 1 closed (``GripperCommand.opening``
            is ``1 - gripper``).
        mode: :data:`EE_MODE` or :data:`WHOLE_BODY_MODE`.
        errors: Per-task tracking errors.
        solved: False when the QP solver failed and ``qdot`` is the clipped unconstrained optimum.
    """

    q: FloatArray
    qdot: FloatArray
    gripper: float
    mode: int
    errors: TaskErrors
    solved: bool


def _rotation(rotvec: FloatArray) -> FloatArray:
    """Rotation matrix of a rotation vector (axis * angle [rad]). Shape (3, 3)."""
    angle = math.sqrt(float(rotvec @ rotvec))
    quat = np.array([1.0, 0.0, 0.0, 0.0])
    if angle > 0.0:
        mujoco.mju_axisAngle2Quat(quat, rotvec / angle, angle)
    out = np.empty(9)
    mujoco.mju_quat2Mat(out, quat)
    return out.reshape(3, 3)


def _rotvec(rotation: FloatArray) -> FloatArray:
    """Rotation vector (axis * angle [rad]) of a 3x3 rotation matrix."""
    quat = np.empty(4)
    mujoco.mju_mat2Quat(quat, rotation.ravel())
    out = np.empty(3)
    mujoco.mju_quat2Vel(out, quat, 1.0)
    return out


class WholeBodyController:
    """Turn an 8-D teleoperation action into joint velocities for the 10 TIAGo joints, one QP a tick.

    The action is ``a = (vx, vy, vz, wx, wy, wz, gripper, mode)``, expressed in the mobile base
    frame (body ``base``: x forward, y left, z up):

    * **EE mode** (``mode = 0``): ``a[:6]`` is the hand twist: the linear velocity of the grasp
      site [m/s] and the angular velocity of the hand [rad/s], both in base-frame axes. It is the
      highest-weight task. The twist is fed forward, and a reference pose that integrates it is fed
      back (gain ``hold_gain``), so the hand does not drift while the twist is zero; motion the
      limits block is dropped, not caught up later (the reference never leads the hand by more
      than 2 cm / 0.1 rad). The base is held still as a hard constraint (after braking within its
      acceleration limit when coming from whole-body mode); a low-weight posture task damps the
      arm's null space toward :attr:`posture`.
    * **Whole-body mode** (``mode = 1``): ``(a[0], a[1], a[5])`` is the base twist in SE(2)
      (forward and leftward velocity [m/s], yaw rate [rad/s], base frame); ``a[2]`` moves the hand
      up or down relative to the base [m/s]; ``a[3]`` and ``a[4]`` are ignored. With the same
      weight as the base task, the hand keeps its pose relative to the base ("don't spill the
      cup": no horizontal or angular motion relative to the base; drift is pulled back to the pose
      held when the mode was entered); at a lower weight the elbow keeps its horizontal position
      relative to the base, i.e. it follows the same planar twist.

    Hard constraints in both modes, as bounds on ``q̇``: joint position limits (as a velocity bound
    that leaves room to brake at the acceleration limit, so position and acceleration limits are
    always jointly feasible), velocity limits and acceleration limits relative to the previous
    tick's ``q̇`` (base limits are per joint: world x, world y, yaw). The acceleration limit is
    what makes a mode switch smooth: velocities change by at most ``acceleration * dt`` per tick,
    whatever the action does. The previous ``q̇`` is the controller's own last output; call
    :meth:`reset` after a stop or when taking over a moving robot. References re-anchor to the
    current hand pose at every mode change.

    The QP is small and box-constrained: ``min ‖A q̇ - b‖²_W + λ‖q̇‖²`` over 10 variables, solved
    with DAQP's Python API directly (a few µs; qpsolvers' conversions cost more than the solve).
    Kinematics use one ``mj_kinematics`` + ``mj_comPos`` and two ``mj_jacSite`` calls on the
    10-joint kinematic model. Construct once; call :meth:`step` every tick.
    """

    def __init__(
        self,
        scene: TiagoScene | None = None,
        *,
        ee_weight: float = 1.0,
        orientation_weight: float = 0.5,
        base_weight: float = 1.0,
        elbow_weight: float = 0.05,
        posture_weight: float = 1e-3,
        posture_gain: float = 2.0,
        hold_gain: float = 5.0,
        damping: float = 1e-6,
    ) -> None:
        """Build the controller.

        Args:
            scene: TIAGo kinematic model; :func:`~telerig.robots.models.tiago.build_tiago_kinematics`
                when None. Its ``limits`` are the hard constraints.
            ee_weight: Weight of the hand task [1/(m/s)^2] (twist in EE mode, hold in whole-body mode).
            orientation_weight: Weight of the hand's angular rows relative to its linear rows.
            base_weight: Weight of the base twist task in whole-body mode (equal priority: 1.0).
            elbow_weight: Weight of the elbow-follows-base task in whole-body mode (lower priority).
            posture_weight: Weight of the posture task on the torso and arm (null-space damping).
            posture_gain: Posture task velocity gain [1/s]: target ``gain * (posture - q)``.
            hold_gain: Gain pulling the hand to its reference (the integrated twist in EE mode, the
                held pose in whole-body mode) and the elbow to its held place [1/s].
            damping: Tikhonov damping λ on all joint velocities (keeps the QP strictly convex).

        Raises:
            RobotError: the scene lacks a joint, site or body the controller needs.
            ValueError: a weight or gain is not positive (``damping`` must be > 0 too).
        """
        self._scene = scene if scene is not None else build_tiago_kinematics()
        model = self._scene.model
        for name, value in (
            ("ee_weight", ee_weight),
            ("orientation_weight", orientation_weight),
            ("base_weight", base_weight),
            ("elbow_weight", elbow_weight),
            ("posture_weight", posture_weight),
            ("posture_gain", posture_gain),
            ("hold_gain", hold_gain),
            ("damping", damping),
        ):
            if not value > 0:
                raise ValueError(f"{name} must be positive, got {value}")
        joints = [model.joint(i).name for i in range(model.njnt)]
        if tuple(joints) != self._scene.joints or model.nq != _N or model.nv != _N:
            raise RobotError(
                f"the whole-body controller needs the kinematic model with exactly the joints "
                f"{', '.join(self._scene.joints)} (build_tiago_kinematics()); got {', '.join(joints)}"
            )
        sites = [model.site(i).name for i in range(model.nsite)]
        for site in (self._scene.ee_site, self._scene.elbow_site):
            if site not in sites:
                raise RobotError(f"site '{site}' not found. Available: {', '.join(sites)}")
        self._model = model
        self._data = mujoco.MjData(model)
        self._ee = model.site(self._scene.ee_site).id
        self._elbow = model.site(self._scene.elbow_site).id
        self._base = model.body(self._scene.base_body).id
        limits = self._scene.limits
        self._lower = limits.lower.copy()
        self._upper = limits.upper.copy()
        self._vmax = limits.velocity.copy()
        self._amax = limits.acceleration.copy()

        self._w_ee = ee_weight * np.array(
            [1.0, 1.0, 1.0, orientation_weight, orientation_weight, orientation_weight]
        )
        self._w_base = base_weight
        self._w_elbow = elbow_weight
        self._w_posture = posture_weight
        self._posture_gain = posture_gain
        self._hold_gain = hold_gain
        self._posture = self._scene.home[_NB:].copy()
        self._base_diag = base_weight * np.eye(_NB)
        self._posture_diag = posture_weight * np.eye(_N - _NB)
        self._damping_diag = damping * np.eye(_N)

        self._jp = np.zeros((3, _N))
        self._jr = np.zeros((3, _N))
        self._je = np.zeros((3, _N))
        self._empty = np.zeros((0, _N))
        self._sense = np.zeros(_N, dtype=np.int32)
        self._qdot = np.zeros(_N)
        self._mode = EE_MODE
        self._has_reference = False
        self._ref_p = np.zeros(3)
        self._ref_r = np.eye(3)
        self._ref_elbow = np.zeros(2)

    @property
    def joint_names(self) -> tuple[str, ...]:
        """Controlled joints, the order of ``q``: base x, y, yaw, torso, six arm joints."""
        return self._scene.joints

    @property
    def scene(self) -> TiagoScene:
        """The kinematic model the controller uses."""
        return self._scene

    @property
    def mode(self) -> int:
        """Mode of the last tick (:data:`EE_MODE` before the first)."""
        return self._mode

    @property
    def velocity(self) -> FloatArray:
        """Joint velocities of the last tick (zero before the first). Shape (10,)."""
        out = self._qdot.copy()
        out.flags.writeable = False
        return out

    @property
    def posture(self) -> FloatArray:
        """Torso and arm posture the null-space task pulls toward [m, rad]. Shape (7,)."""
        out = self._posture.copy()
        out.flags.writeable = False
        return out

    @posture.setter
    def posture(self, value: npt.ArrayLike) -> None:
        arr = np.array(value, dtype=np.float64)
        if arr.shape != (_N - _NB,) or not np.all(np.isfinite(arr)):
            raise ValueError(f"posture must be finite with shape ({_N - _NB},) [m, rad], got {arr}")
        self._posture = np.clip(arr, self._lower[_NB:], self._upper[_NB:])

    def reset(self, velocity: npt.ArrayLike | None = None) -> None:
        """Forget the last tick: set the velocity the acceleration limit starts from (zero by default).

        Args:
            velocity: Current joint velocities, order of :attr:`joint_names`. Shape (10,).
        """
        qdot = np.zeros(_N) if velocity is None else np.array(velocity, dtype=np.float64)
        if qdot.shape != (_N,) or not np.all(np.isfinite(qdot)):
            raise ValueError(f"velocity must be finite with shape ({_N},), got {qdot}")
        self._qdot = np.clip(qdot, -self._vmax, self._vmax)
        self._mode = EE_MODE
        self._has_reference = False

    def sync_velocity(self, velocity: npt.ArrayLike) -> None:
        """Take ``velocity`` as the last tick's joint velocities without re-anchoring the references.

        For a caller whose commands were changed downstream (a safety chain clipped or held them):
        the acceleration limit then starts from what the robot was actually commanded.

        Args:
            velocity: Joint velocities actually commanded, order of :attr:`joint_names`. Shape (10,).
        """
        qdot = np.array(velocity, dtype=np.float64)
        if qdot.shape != (_N,) or not np.all(np.isfinite(qdot)):
            raise ValueError(f"velocity must be finite with shape ({_N},), got {qdot}")
        self._qdot = np.clip(qdot, -self._vmax, self._vmax)

    def hand_in_base(self, q: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Pose of the grasp site relative to the mobile base at joint positions ``q`` (shape (10,)).

        Returns:
            Position [m] (shape (3,)) and rotation matrix (shape (3, 3)), base frame.
        """
        self._forward(self._checked_q(q))
        return self._hand_in_base()

    def step(self, action: npt.ArrayLike, q: npt.ArrayLike, dt: float) -> WBCResult:
        """One control tick from joint positions ``q`` under ``action``.

        Args:
            action: ``(vx, vy, vz, wx, wy, wz, gripper, mode)``: a twist in the base frame [m/s,
                rad/s], gripper closure in [0, 1], mode 0 (EE) or 1 (whole body); see the class
                docstring for what drives what in each mode. Shape (8,).
            q: Current joint positions, order of :attr:`joint_names`. Shape (10,).
            dt: Tick period [s], > 0.

        Returns:
            Next joint positions and velocities, the gripper closure and per-task errors.

        Raises:
            ValueError: the action has the wrong shape, is not finite, has the gripper outside
                [0, 1] or a mode other than 0 or 1; ``q`` has the wrong shape or is not finite;
                ``dt`` is not positive.
        """
        a = np.asarray(action, dtype=np.float64)
        if a.shape != (8,):
            raise ValueError(
                f"action must have shape (8,): (vx, vy, vz, wx, wy, wz, gripper, mode), got {a.shape}"
            )
        if not np.all(np.isfinite(a)):
            raise ValueError(f"action must be finite, got {a.tolist()}")
        if not 0.0 <= a[6] <= 1.0:
            raise ValueError(f"action[6] (gripper closure) must be in [0, 1], got {a[6]}")
        if a[7] != EE_MODE and a[7] != WHOLE_BODY_MODE:
            raise ValueError(f"action[7] (mode) must be 0 (end effector) or 1 (whole body), got {a[7]}")
        if not dt > 0:
            raise ValueError(f"dt must be positive [s], got {dt}")
        qc = self._checked_q(q)
        mode = int(a[7])
        self._forward(qc)
        jp, jr = self._jp, self._jr
        rb = self._data.xmat[self._base].reshape(3, 3)
        mujoco.mj_jacSite(self._model, self._data, jp, jr, self._ee)
        # Hand Jacobian in base-frame axes; its arm columns are also the Jacobian of the hand
        # relative to the base (the base columns are what the base's own motion adds).
        j_ee = np.vstack((rb.T @ jp, rb.T @ jr))
        if mode != self._mode or not self._has_reference:
            self._anchor(rb)
        self._mode = mode

        lo, hi = self._bounds(qc, dt)
        w_ee = self._w_ee
        k = self._hold_gain
        p, r = self._hand_in_base()
        dp = self._ref_p - p
        rot_err = _rotvec(self._ref_r @ r.T)
        elbow_rows = None
        if mode == EE_MODE:
            brake = np.clip(
                0.0, self._qdot[:_NB] - self._amax[:_NB] * dt, self._qdot[:_NB] + self._amax[:_NB] * dt
            )
            lo[:_NB] = brake
            hi[:_NB] = brake
            hand_p = math.sqrt(float(dp @ dp))
            ee_target = a[:6] + k * np.concatenate((dp, rot_err))
            ee_rows = j_ee
            base_target = np.zeros(3)
            h = ee_rows.T @ (w_ee[:, None] * ee_rows)
            f = -ee_rows.T @ (w_ee * ee_target)
            self._advance_reference(p, r, a[:3] * dt, a[3:6] * dt)
        else:
            c, s = np.cos(qc[2]), np.sin(qc[2])
            base_target = np.array([c * a[0] - s * a[1], s * a[0] + c * a[1], a[5]])
            hand_p = math.hypot(dp[0], dp[1])
            ee_target = np.array([k * dp[0], k * dp[1], a[2] + k * dp[2], *(k * rot_err)])
            ee_rows = j_ee.copy()
            ee_rows[:, :_NB] = 0.0
            mujoco.mj_jacSite(self._model, self._data, self._je, None, self._elbow)
            elbow_rows = (rb.T @ self._je)[:2]
            elbow_rows[:, :_NB] = 0.0
            elbow_now = (rb.T @ (self._data.site_xpos[self._elbow] - self._data.xpos[self._base]))[:2]
            elbow_target = k * (self._ref_elbow - elbow_now)
            h = ee_rows.T @ (w_ee[:, None] * ee_rows) + self._w_elbow * (elbow_rows.T @ elbow_rows)
            f = -ee_rows.T @ (w_ee * ee_target) - self._w_elbow * (elbow_rows.T @ elbow_target)
            h[:_NB, :_NB] += self._base_diag
            f[:_NB] -= self._w_base * base_target
            self._advance_reference(p, r, np.array([0.0, 0.0, a[2] * dt]), None)
        hand_r = math.sqrt(float(rot_err @ rot_err))
        posture_target = self._posture_gain * (self._posture - qc[_NB:])
        h[_NB:, _NB:] += self._posture_diag
        f[_NB:] -= self._w_posture * posture_target
        h += self._damping_diag

        x, _, exitflag, _ = daqp.solve(h, f, self._empty, hi, lo, self._sense)
        solved = exitflag == 1
        if not solved:  # cannot happen for a convex box QP with lo <= hi; stay safe if it does
            x = np.linalg.solve(h, -f)
        # The solver meets bounds to its tolerance; clipping makes the hard limits exact.
        qdot = np.clip(x, lo, hi)
        self._qdot = qdot

        ee_res = ee_rows @ qdot - ee_target
        base_res = qdot[:_NB] - base_target
        elbow_res = None if elbow_rows is None else elbow_rows @ qdot - elbow_target
        elbow_err = 0.0 if elbow_res is None else math.hypot(elbow_res[0], elbow_res[1])
        errors = TaskErrors(
            ee_linear=math.hypot(ee_res[0], ee_res[1], ee_res[2]),
            ee_angular=math.hypot(ee_res[3], ee_res[4], ee_res[5]),
            base_linear=math.hypot(base_res[0], base_res[1]),
            base_angular=float(abs(base_res[2])),
            elbow=elbow_err,
            hand_position=hand_p,
            hand_orientation=hand_r,
        )
        q_next = qc + qdot * dt
        out_qdot = qdot.copy()
        q_next.flags.writeable = False
        out_qdot.flags.writeable = False
        return WBCResult(
            q=q_next, qdot=out_qdot, gripper=float(a[6]), mode=mode, errors=errors, solved=solved
        )

    def _bounds(self, q: FloatArray, dt: float) -> tuple[FloatArray, FloatArray]:
        """Box on q̇ from position (with braking room), velocity and acceleration limits."""
        amax = self._amax
        # Fastest speed from which braking at amax, starting after this tick, stops at the limit:
        # v dt + v^2 / (2 a) <= d. Staying under it keeps the next tick feasible too.
        ad = amax * dt
        up = np.maximum(self._upper - q, 0.0)
        down = np.maximum(q - self._lower, 0.0)
        v_up = -ad + np.sqrt(ad * ad + 2.0 * amax * up)
        v_down = -ad + np.sqrt(ad * ad + 2.0 * amax * down)
        hi_pv = np.minimum(self._vmax, v_up)
        lo_pv = np.maximum(-self._vmax, -v_down)
        acc_lo = self._qdot - ad
        acc_hi = self._qdot + ad
        lo = np.maximum(lo_pv, acc_lo)
        hi = np.minimum(hi_pv, acc_hi)
        conflict = lo > hi
        if np.any(conflict):
            # Only when q jumped (e.g. measured, not integrated): brake as hard as allowed.
            pinned = np.where(acc_lo > hi_pv, acc_lo, acc_hi)
            lo = np.where(conflict, pinned, lo)
            hi = np.where(conflict, pinned, hi)
        return lo, hi

    def _anchor(self, rb: FloatArray) -> None:
        """Take the current hand pose and elbow position relative to the base as the references."""
        p, r = self._hand_in_base()
        self._ref_p = p.copy()
        self._ref_r = r.copy()
        elbow = rb.T @ (self._data.site_xpos[self._elbow] - self._data.xpos[self._base])
        self._ref_elbow = elbow[:2].copy()
        self._has_reference = True

    def _advance_reference(self, p: FloatArray, r: FloatArray, dp: FloatArray, dw: FloatArray | None) -> None:
        """Move the hand reference by ``dp`` [m] and rotate it by ``dw`` [rad] (base frame).

        The reference stays within ``_MAX_LAG_M`` / ``_MAX_LAG_RAD`` of the hand, so motion a limit
        blocks is dropped instead of piling up and being caught up later (anti-windup).
        """
        ref_p = self._ref_p + dp
        lag = ref_p - p
        dist = math.sqrt(float(lag @ lag))
        if dist > _MAX_LAG_M:
            ref_p = p + lag * (_MAX_LAG_M / dist)
        self._ref_p = ref_p
        ref_r = self._ref_r if dw is None or not np.any(dw) else _rotation(dw) @ self._ref_r
        err = _rotvec(ref_r @ r.T)
        angle = math.sqrt(float(err @ err))
        if angle > _MAX_LAG_RAD:
            ref_r = _rotation(err * (_MAX_LAG_RAD / angle)) @ r
        self._ref_r = ref_r

    def _forward(self, q: FloatArray) -> None:
        self._data.qpos[:] = q
        mujoco.mj_kinematics(self._model, self._data)
        mujoco.mj_comPos(self._model, self._data)

    def _hand_in_base(self) -> tuple[FloatArray, FloatArray]:
        rb = self._data.xmat[self._base].reshape(3, 3)
        p = rb.T @ (self._data.site_xpos[self._ee] - self._data.xpos[self._base])
        r = rb.T @ self._data.site_xmat[self._ee].reshape(3, 3)
        return p, r

    def _checked_q(self, q: npt.ArrayLike) -> FloatArray:
        arr = np.array(q, dtype=np.float64)
        if arr.shape != (_N,) or not np.all(np.isfinite(arr)):
            raise ValueError(
                f"q must be finite with shape ({_N},) in the order {', '.join(self.joint_names)}, got {arr}"
            )
        return arr
