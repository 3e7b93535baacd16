"""Dexterous hand retargeting: bounded least squares over keypoint vectors by projected Levenberg-Marquardt.

Problem, per frame, over the actuated joints ``q`` (mimic joints follow as ``q_full = A q + b``)::

    minimize  sum_i w_i || alpha_i v_i - f_i(q) ||^2  +  beta || q - q_prev ||^2
    subject to  lower <= q <= upper

with ``v_i`` a human keypoint vector in the hand frame, ``alpha_i`` its finger's scale and
``f_i(q) = p_task_i(q) - p_origin_i(q)`` the matching robot vector.

Why this solver: the problem is small (6-16 variables, 4-6 vectors, 3 residuals each), smooth,
and warm-started from the previous frame, where it is nearly quadratic. Gauss-Newton with
Levenberg-Marquardt damping converges in 2-3 steps from a warm start, and each step costs one
forward kinematics pass plus a tiny dense solve. A general NLP solver (dex-retargeting runs NLopt
SLSQP with autograd) spends most of its time in per-call overhead. The Jacobian is analytic: one
``mujoco.mj_jacSite`` per keypoint site of the mesh-free model, folded into d f / d q through the
selection (task minus origin) and the coupling ``A`` in one matrix product. (Computing the columns
``axis_j x (p - anchor_j)`` for every site-joint pair in NumPy instead, as this did until
2026-11-27, took two to three times as long: 33-36 against 11-16 us on the Inspire hand, the
``mj_comPos`` that ``mj_jacSite`` needs included; 8-17 % less time per frame.) Each
step is the box-constrained quadratic model, solved exactly by ``daqp`` (a dual active-set QP
solver in C, already the whole-body controller's and mink's) and clipped into the box, so the
output never leaves the joint limits. (Solving unconstrained first and calling ``daqp`` only when
the step leaves the box was slower: a bound is active in 75-80 % of the steps of
benchmarks/hand_retarget.py's motion.)

Most of a solve's cost on a CPU is Python and NumPy's per-call overhead on arrays of 5-16 entries,
not arithmetic: the step went from a hand-written projected active set (each pass in NumPy,
``np.ix_`` sub-matrices and ``np.linalg.solve``: ~0.1 ms of overhead per step, and on strongly
coupled models not even a descent step) to one ``daqp`` call (~8 us), and the residual / cost
bookkeeping works on flat vectors with ufuncs instead of ``np.clip``'s and ``einsum``'s Python
wrappers (benchmarks/hand_retarget.py).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import daqp
import mujoco
import numpy as np
import numpy.typing as npt

from telerig.ir.types import FloatArray, HandPose, JointCommand, Sample
from telerig.retarget.hand.vectors import HandFrameSource, KeypointVectors, default_vectors, human_vectors
from telerig.robots.models.hands import HandKinematics

__all__ = ["HandRetargetResult", "HandRetargeter", "OptimizerResult", "VectorOptimizer"]


@dataclass(frozen=True, slots=True)
class OptimizerResult:
    """One solve.

    Attributes:
        q: Actuated joint positions [rad], within the bounds. Shape (na,).
        residuals: ``|| alpha_i v_i - f_i(q) ||`` per vector [m]. Shape (m,).
        iterations: Levenberg-Marquardt steps taken.
    """

    q: FloatArray
    residuals: FloatArray
    iterations: int


class VectorOptimizer:
    """Solve the vector-matching problem (see the module docstring) for one robot hand.

    The optimizer owns its own ``MjData``; one instance per control loop (not thread-safe).

    Args:
        hand: Robot hand model; targets are in its hand frame.
        vectors: Keypoint pairs; each keypoint must have a robot site in ``hand.keypoints``.
        beta: Weight of the change from the previous solution [m^2/rad^2]; smooths and regularizes.
        iterations: Maximum Levenberg-Marquardt steps per solve, >= 1. Three: two were a quarter
            faster per frame at the same mean vector error on benchmarks/hand_retarget.py's motion
            (+0.003 mm of 10-14 mm), but a held pose far from the start still drifted 1e-3 rad per
            frame after 20 frames and chattered (tests/retarget/hand/test_optimizer.py).
        damping: Initial Levenberg-Marquardt damping [m^2/rad^2], > 0.
        tolerance: Stop when a step is shorter than this [rad]. 1e-3 rad (0.06 deg) is ten times
            below what tracking noise alone moves a finger joint (1.5 mm at a fingertip ~10 cm out:
            ~0.015 rad); at 1e-4 nearly every frame took all ``iterations`` steps, for solutions
            within 3e-4 rad and the same vector error (benchmarks/hand_retarget.py's motion).

    Raises:
        ValueError: a keypoint has no robot site, or an argument is out of range.
    """

    def __init__(
        self,
        hand: HandKinematics,
        vectors: KeypointVectors,
        *,
        beta: float = 1e-3,
        iterations: int = 3,
        damping: float = 1e-6,
        tolerance: float = 1e-3,
    ) -> None:
        missing = sorted({int(i) for i in (*vectors.origins, *vectors.tasks)} - set(hand.keypoints))
        if missing:
            raise ValueError(
                f"{hand.name} has no point for keypoint(s) {missing}. Available: {sorted(hand.keypoints)}"
            )
        if not (math.isfinite(beta) and beta >= 0.0):
            raise ValueError(f"beta must be >= 0, got {beta}")
        if iterations < 1:
            raise ValueError(f"iterations must be >= 1, got {iterations}")
        if not (math.isfinite(damping) and damping > 0.0):
            raise ValueError(f"damping must be > 0, got {damping}")
        self.hand = hand
        self.vectors = vectors
        self.beta = float(beta)
        self.iterations = int(iterations)
        self.damping = float(damping)
        self.tolerance = float(tolerance)
        model = hand.model
        self._model = model
        self._data = mujoco.MjData(model)
        used = sorted({int(i) for i in (*vectors.origins, *vectors.tasks)})
        self._site_ids = np.array([model.site(hand.keypoints[i]).id for i in used], dtype=np.intp)
        col = {k: s for s, k in enumerate(used)}
        m = len(vectors)
        # Row i of `sel` picks task minus origin site: f = sel @ P.
        self._sel = np.zeros((m, len(used)))
        for i, (o, t) in enumerate(vectors.pairs):
            self._sel[i, col[t]] += 1.0
            self._sel[i, col[o]] -= 1.0
        na = len(hand.actuated)
        # d f / d q_act = (S kron I3) J_sites A: J_sites stacks each used site's 3 x nv Jacobian
        # (nv == nq: a hand model has hinge joints only).
        self._sites = [int(sid) for sid in self._site_ids]
        self._site_jac = np.zeros((len(used), 3, model.nv))
        self._site_jac_rows = self._site_jac.reshape(3 * len(used), model.nv)  # a view: filled in place
        self._sel3 = np.kron(self._sel, np.eye(3))
        self._a = np.ascontiguousarray(hand.coupling, dtype=np.float64)
        self._b = np.array(hand.offset)
        self._lo = np.array(hand.lower)
        self._hi = np.array(hand.upper)
        self._diag = np.arange(na) * (na + 1)  # flat indices of the diagonal of an (na, na) matrix
        self._no_rows = np.zeros((0, na))  # daqp: no general constraints, the bounds are simple
        self._sense = np.zeros(na, dtype=np.int32)

    def forward(self, q: FloatArray) -> FloatArray:
        """Robot vectors ``f_i(q)`` [m] in the hand frame. Shape (na,) -> (m, 3)."""
        self._fk(np.asarray(q, dtype=np.float64))
        out: FloatArray = self._sel @ self._data.site_xpos[self._site_ids]
        return out

    def _fk(self, q: FloatArray) -> None:
        self._data.qpos[:] = self._a @ q + self._b
        mujoco.mj_kinematics(self._model, self._data)

    def _evaluate(self, q: FloatArray, target: FloatArray) -> FloatArray:
        """Residuals ``target - f(q)`` (m, 3) at ``q``; leaves the kinematics of ``q`` in the data."""
        self._fk(q)
        out: FloatArray = target - self._sel @ self._data.site_xpos[self._site_ids]
        return out

    def _jacobian(self) -> FloatArray:
        """d f / d q_act at the last evaluated ``q``. Shape (3m, na)."""
        model, data, site_jac = self._model, self._data, self._site_jac
        mujoco.mj_comPos(model, data)  # the joint axes mj_jacSite reads (mj_kinematics leaves them)
        for k, site in enumerate(self._sites):
            mujoco.mj_jacSite(model, data, site_jac[k], None, site)
        jac: FloatArray = self._sel3 @ (self._site_jac_rows @ self._a)
        return jac

    def _step(self, q: FloatArray, h: FloatArray, g: FloatArray) -> FloatArray:
        """``q + dq`` for the quadratic model ``min 1/2 dq'H dq - g'dq`` within the bounds."""
        dq, _, exitflag, _ = daqp.solve(h, -g, self._no_rows, self._hi - q, self._lo - q, self._sense)
        if exitflag != 1:  # a convex box QP with lo <= hi is always solved; if not, hold this frame
            return q
        # The solver meets the bounds to its tolerance; clipping makes the joint limits exact.
        out: FloatArray = np.minimum(np.maximum(q + dq, self._lo), self._hi)
        return out

    def solve(self, targets: FloatArray, weights: FloatArray, q_prev: FloatArray) -> OptimizerResult:
        """Minimize the weighted vector error near ``q_prev``.

        Args:
            targets: Scaled human vectors ``alpha_i v_i`` [m] in the hand frame. Shape (m, 3).
            weights: Vector weights ``w_i`` >= 0 (0 ignores a vector). Shape (m,).
            q_prev: Previous solution [rad], the warm start and the smoothing anchor. Shape (na,).
        """
        beta = self.beta
        anchor = np.minimum(np.maximum(q_prev, self._lo), self._hi)
        q = anchor.copy()
        w3 = np.repeat(weights, 3)
        r = self._evaluate(q, targets).ravel()
        total = float(w3 @ (r * r))  # q starts at the anchor: no beta term
        lam = self.damping
        steps = 0
        for _ in range(self.iterations):
            steps += 1
            jac = self._jacobian()
            jw = jac.T * w3
            h = jw @ jac
            h.flat[self._diag] += beta + lam
            g = jw @ r - beta * (q - anchor)
            q_new = self._step(q, h, g)
            r_new = self._evaluate(q_new, targets).ravel()
            dqa = q_new - anchor
            total_new = float(w3 @ (r_new * r_new)) + beta * float(dqa @ dqa)
            if total_new <= total:
                step = float(abs(q_new - q).max())
                q, r, total = q_new, r_new, total_new
                lam = max(lam * 0.1, 1e-12)
                if step < self.tolerance:
                    break
            else:
                lam *= 10.0
                r = self._evaluate(q, targets).ravel()  # restore the kinematics of q for the next Jacobian
        q.flags.writeable = False
        res = np.sqrt((r * r).reshape(-1, 3).sum(axis=1))
        return OptimizerResult(q=q, residuals=res, iterations=steps)


@dataclass(frozen=True, slots=True)
class HandRetargetResult:
    """One retargeted hand sample.

    Attributes:
        command: Hand joint targets [rad] stamped with the sample's stamp.
        error_m: Mean vector error ``|| alpha_i v_i - f_i(q) ||`` over the valid vectors [m].
        vector_errors: Error per vector [m]; NaN for vectors skipped for low confidence. Shape (m,).
        valid: Vectors used in this solve. Shape (m,).
    """

    command: JointCommand
    error_m: float
    vector_errors: FloatArray
    valid: npt.NDArray[np.bool_]


class HandRetargeter:
    """A tracked hand (:class:`~telerig.ir.types.HandPose`) → robot hand joint command, warm-started.

    Vectors whose keypoints are below ``min_confidence`` (or non-finite) are skipped for that frame,
    so their joints hold their last value (the ``beta`` term keeps them there); when no vector is
    valid, or the hand frame cannot be found, the sample yields ``None`` and the robot keeps its
    last command.

    Args:
        hand: Robot hand model.
        vectors: Keypoint pairs; :func:`~telerig.retarget.hand.vectors.default_vectors` when None.
        scale: Global human-to-robot scale; ``hand.default_scale`` when None.
        finger_scales: Per-finger factor on ``scale``, thumb..little: alpha_i = scale * finger_scales[f].
            Shape (5,).
        weights: Per-vector weight; all 1 when None. Shape (m,).
        beta: Smoothing weight [m^2/rad^2] (see :class:`VectorOptimizer`).
        iterations: Maximum solver steps per sample.
        min_confidence: Keypoint confidence below which a vector is skipped, in [0, 1].
        frame: How the human hand frame is found (see :func:`~telerig.retarget.hand.vectors.hand_rotation`).
        command: ``"actuated"`` joints only (the hand's motors) or ``"all"`` joints, mimic ones included.

    Raises:
        ValueError: an argument is out of range or names a keypoint the hand has no point for.
    """

    def __init__(
        self,
        hand: HandKinematics,
        vectors: KeypointVectors | None = None,
        *,
        scale: float | None = None,
        finger_scales: Sequence[float] = (1.0, 1.0, 1.0, 1.0, 1.0),
        weights: Sequence[float] | None = None,
        beta: float = 1e-3,
        iterations: int = 3,
        min_confidence: float = 0.5,
        frame: HandFrameSource = "keypoints",
        command: Literal["actuated", "all"] = "actuated",
    ) -> None:
        vectors = default_vectors(sorted(hand.keypoints)) if vectors is None else vectors
        s = hand.default_scale if scale is None else float(scale)
        fs = np.asarray(finger_scales, dtype=np.float64)
        if not (math.isfinite(s) and s > 0.0):
            raise ValueError(f"scale must be > 0, got {scale}")
        if fs.shape != (5,) or not np.all(np.isfinite(fs) & (fs > 0.0)):
            raise ValueError(
                f"finger_scales must be 5 positive numbers (thumb..little), got {list(finger_scales)}"
            )
        w = np.ones(len(vectors)) if weights is None else np.asarray(weights, dtype=np.float64)
        if w.shape != (len(vectors),) or not np.all(np.isfinite(w) & (w >= 0.0)):
            raise ValueError(f"weights must be {len(vectors)} numbers >= 0 (one per vector), got {list(w)}")
        if not 0.0 <= min_confidence <= 1.0:
            raise ValueError(f"min_confidence must be in [0, 1], got {min_confidence}")
        self.hand = hand
        self.vectors = vectors
        self.optimizer = VectorOptimizer(hand, vectors, beta=beta, iterations=iterations)
        self.alpha: FloatArray = s * fs[vectors.fingers]
        self.weights: FloatArray = w
        self.min_confidence = float(min_confidence)
        self.frame: HandFrameSource = frame
        self._all = command == "all"
        self.joint_names = hand.joint_names if self._all else hand.actuated
        self._q = hand.neutral()

    @property
    def q(self) -> FloatArray:
        """Last actuated solution [rad], the next warm start. Shape (na,)."""
        return self._q

    def reset(self, q: FloatArray | None = None) -> None:
        """Restart from ``q`` (actuated joints [rad], clipped into the bounds) or the open hand."""
        self._q = self.hand.neutral() if q is None else np.clip(q, self.hand.lower, self.hand.upper)

    def __call__(self, sample: Sample) -> HandRetargetResult | None:
        """Retarget one sample; ``None`` for a non-hand sample, the other hand, or no usable vector."""
        if not isinstance(sample, HandPose) or sample.handedness != self.hand.handedness:
            return None
        found = human_vectors(sample, self.vectors, source=self.frame, min_confidence=self.min_confidence)
        if found is None:
            return None
        v, valid = found
        weights = np.where(valid, self.weights, 0.0)
        if not (weights > 0.0).any():
            return None
        result = self.optimizer.solve(v * self.alpha[:, None], weights, self._q)
        self._q = result.q
        errors = np.where(valid, result.residuals, np.nan)
        positions = self.hand.full(result.q) if self._all else result.q
        return HandRetargetResult(
            command=JointCommand(sample.stamp, self.joint_names, positions),
            error_m=float(result.residuals[valid].mean()),
            vector_errors=errors,
            valid=valid,
        )
