"""Whole-body teleoperation: a SpaceMouse twist or a VR controller's motion → the 8-D WBC action → joints."""

from __future__ import annotations

import math
import time
from collections.abc import Mapping

import numpy as np
from pydantic import JsonValue

from telerig.ir.frames import quat_conjugate, quat_log, quat_multiply, quat_normalize, quat_rotate
from telerig.ir.types import ControllerState, FloatArray, GripperCommand, JointCommand, Sample, Twist
from telerig.retarget.clutch import button_held
from telerig.retarget.reach_plan import ReachPlanAid
from telerig.retarget.wbc import EE_MODE, WHOLE_BODY_MODE, WBCResult, WholeBodyController

__all__ = ["PoseTwist", "WholeBodyGripper", "WholeBodyResidual", "WholeBodyRetargeter", "WholeBodySwitches"]

_MODE_NAMES = {EE_MODE: "ee", WHOLE_BODY_MODE: "whole_body"}
#: Action components recorded with every residual, in action order.
ACTION_KEYS = ("a_vx", "a_vy", "a_vz", "a_wx", "a_wy", "a_wz", "a_gripper", "a_mode")
#: Operator input above either speed while a plan executes cancels it (a deliberate push of the
#: SpaceMouse or controller, above its noise) [m/s], [rad/s].
_TAKEOVER_M_S = 0.02
_TAKEOVER_RAD_S = 0.1


class WholeBodySwitches:
    """The operator's discrete inputs to the whole-body controller: the mode and the gripper closure.

    A live :class:`~telerig.retarget.binding.Aid`: it takes button samples from any device stream
    (a SpaceMouse's buttons come on their own stream, apart from its twist) and text commands, and
    its state is published for a UI. The mode toggles on each press of ``mode_button``; the
    gripper toggles between open (closure 0) and closed (1) on each press of ``gripper_button``
    (or follows a controller trigger through :meth:`set_gripper`). The switch itself is a step in
    the action; the controller's acceleration limits make the motion smooth.

    Args:
        mode_button: Button that toggles end-effector / whole-body mode (see
            :func:`~telerig.retarget.clutch.button_held`); None for bus commands only.
        gripper_button: Button that toggles the gripper; None for none.
        mode: Initial mode, :data:`~telerig.retarget.wbc.EE_MODE` or ``WHOLE_BODY_MODE``.
    """

    #: Stream the node publishes :meth:`state` on (retained JSON).
    stream = "wbc_mode"

    __slots__ = ("_gripper", "_gripper_held", "_mode", "_mode_held", "gripper_button", "mode_button")

    def __init__(
        self, *, mode_button: str | None = None, gripper_button: str | None = None, mode: int = EE_MODE
    ) -> None:
        if mode not in _MODE_NAMES:
            raise ValueError(f"mode must be {EE_MODE} (end effector) or {WHOLE_BODY_MODE} (whole body)")
        if mode_button is not None and mode_button == gripper_button:
            raise ValueError(f"mode_button and gripper_button must differ, both are {mode_button!r}")
        self.mode_button = mode_button
        self.gripper_button = gripper_button
        self._mode = mode
        self._gripper = 0.0
        self._mode_held = False
        self._gripper_held = False

    @property
    def mode(self) -> int:
        """Current mode: 0 end effector, 1 whole body."""
        return self._mode

    @property
    def gripper(self) -> float:
        """Gripper closure, 0 open .. 1 closed."""
        return self._gripper

    def set_mode(self, mode: int) -> bool:
        """Set the mode; returns whether it changed."""
        if mode not in _MODE_NAMES:
            raise ValueError(f"mode must be {EE_MODE} (end effector) or {WHOLE_BODY_MODE} (whole body)")
        changed = mode != self._mode
        self._mode = mode
        return changed

    def set_gripper(self, closure: float) -> bool:
        """Set the closure (clamped to [0, 1]; non-finite ignored); returns whether it changed."""
        if not math.isfinite(closure):
            return False
        value = min(1.0, max(0.0, float(closure)))
        changed = value != self._gripper
        self._gripper = value
        return changed

    def update(self, sample: Sample) -> bool:
        """Toggle on the press edges of the buttons in ``sample``; returns whether anything changed."""
        changed = False
        if self.mode_button is not None:
            held = button_held(sample, self.mode_button)
            if held and not self._mode_held:
                changed |= self.set_mode(WHOLE_BODY_MODE if self._mode == EE_MODE else EE_MODE)
            self._mode_held = held
        if self.gripper_button is not None:
            held = button_held(sample, self.gripper_button)
            if held and not self._gripper_held:
                changed |= self.set_gripper(0.0 if self._gripper >= 0.5 else 1.0)
            self._gripper_held = held
        return changed

    def command(self, text: str) -> bool:
        """Apply ``ee``, ``whole_body``, ``toggle``, ``open`` or ``close``; returns whether it changed.

        Raises:
            ValueError: ``text`` is none of those.
        """
        word = text.strip().lower()
        if word in ("ee", "whole_body"):
            return self.set_mode(EE_MODE if word == "ee" else WHOLE_BODY_MODE)
        if word == "toggle":
            return self.set_mode(WHOLE_BODY_MODE if self._mode == EE_MODE else EE_MODE)
        if word in ("open", "close"):
            return self.set_gripper(0.0 if word == "open" else 1.0)
        raise ValueError(f"wbc_mode command must be ee, whole_body, toggle, open or close, got {text!r}")

    def state(self) -> dict[str, JsonValue]:
        """What a UI shows: the mode name and the gripper closure."""
        return {"mode": _MODE_NAMES[self._mode], "gripper": self._gripper}


class PoseTwist:
    """Velocity of a controller estimated from successive poses, while a clutch button is held.

    The linear velocity is the position difference over the capture-time difference; the angular
    velocity is the rotation vector of ``q_k q_{k-1}^-1`` over the same time (both operator frame).
    Released, or across a gap longer than ``max_gap_s``, the twist is zero and the next held sample
    only re-anchors: the robot never jumps on a clutch press or a dropout.

    Args:
        clutch_button: Button that engages the motion (see
            :func:`~telerig.retarget.clutch.button_held`); None: always engaged.
        max_gap_s: Longest capture interval [s] still differentiated, > 0.
    """

    __slots__ = ("_prev", "clutch_button", "max_gap_s")

    def __init__(self, clutch_button: str | None = None, *, max_gap_s: float = 0.1) -> None:
        if not (math.isfinite(max_gap_s) and max_gap_s > 0):
            raise ValueError(f"max_gap_s must be > 0 s, got {max_gap_s}")
        self.clutch_button = clutch_button
        self.max_gap_s = float(max_gap_s)
        self._prev: tuple[int, FloatArray, FloatArray] | None = None

    def __call__(self, sample: ControllerState) -> tuple[FloatArray, FloatArray]:
        """Linear [m/s] and angular [rad/s] velocity of the controller, operator frame. Shapes (3,)."""
        zero = np.zeros(3)
        held = self.clutch_button is None or button_held(sample, self.clutch_button)
        finite = bool(np.all(np.isfinite(sample.position)) and np.all(np.isfinite(sample.orientation)))
        if not held or not finite:
            self._prev = None
            return zero, zero.copy()
        t, p, q = sample.stamp.capture_ns, sample.position, quat_normalize(sample.orientation)
        prev, self._prev = self._prev, (t, p, q)
        if prev is None:
            return zero, zero.copy()
        dt = (t - prev[0]) * 1e-9
        if not 0.0 < dt <= self.max_gap_s:
            return zero, zero.copy()
        linear = (p - prev[1]) / dt
        angular = quat_log(quat_multiply(q, quat_conjugate(prev[2]))) / dt
        return linear, angular

    def reset(self) -> None:
        """Forget the last pose; the next engaged sample re-anchors."""
        self._prev = None


class WholeBodyResidual:
    """One whole-body tick for the recorder: per-task errors, the mode, the action and the solve time.

    ``flagged`` when the hand is more than ``threshold_m`` from its reference or the QP failed.
    """

    __slots__ = ("action", "result", "solve_s", "threshold_m")

    def __init__(self, result: WBCResult, action: FloatArray, threshold_m: float, solve_s: float) -> None:
        self.result = result
        self.action = action
        self.threshold_m = threshold_m
        self.solve_s = solve_s

    @property
    def flagged(self) -> bool:
        """True when the hand is off its reference by more than the threshold, or the QP failed."""
        return self.result.errors.hand_position > self.threshold_m or not self.result.solved

    def metrics(self) -> Mapping[str, float]:
        """:class:`~telerig.retarget.wbc.TaskErrors` fields [m, m/s, rad, rad/s], ``mode`` (0 EE,
        1 whole body), the action: ``a_vx`` .. ``a_wz`` [m/s, rad/s], ``a_gripper``, ``a_mode``, and
        ``solve_s``: the controller's tick (kinematics, Jacobians, the QP) [s], as the hand
        retargeter records its own."""
        out: dict[str, float] = self.result.errors.as_dict()
        out["mode"] = float(self.result.mode)
        out.update(zip(ACTION_KEYS, (float(v) for v in self.action), strict=True))
        out["solve_s"] = self.solve_s
        return out


class WholeBodyRetargeter:
    """Retargeter over :class:`~telerig.retarget.wbc.WholeBodyController` (8-D action from a twist).

    Each fresh sample becomes the action ``a = (v, w, gripper, mode)``:

    * a ``Twist`` (SpaceMouse): its linear and angular velocity;
    * a ``ControllerState`` (VR controller): its velocity from successive poses while
      ``clutch_button`` is held (relative, clutched: see :class:`PoseTwist`).

    The operator-frame twist is rotated into the robot base frame by ``rotation`` (w, x, y, z;
    operator → base), multiplied by ``linear_scale`` / ``angular_scale`` and limited in norm to
    ``max_linear_m_s`` / ``max_angular_rad_s``. Gripper and mode come from ``switches``. The
    controller integrates the QP velocities over the control period ``dt`` into joint targets
    (velocities ride along as feed-forward). When the safety chain changed the previous command
    (start-up ramp, clipping, hold), the controller's acceleration limit restarts from the
    velocity actually commanded, so the chain's changes never cause a velocity step.

    Args:
        controller: The whole-body QP.
        switches: Mode and gripper state (also bound as an aid to the buttons' stream).
        joint_names: The driver's joints; must equal the controller's, in order.
        rotation: Operator → base rotation (w, x, y, z). Shape (4,).
        linear_scale: Factor on linear velocity (dimensionless), > 0.
        angular_scale: Factor on angular velocity, > 0.
        max_linear_m_s: Norm limit of the linear velocity [m/s], > 0.
        max_angular_rad_s: Norm limit of the angular velocity [rad/s], > 0.
        clutch_button: Controller button that engages pose-velocity input; None: always.
        trigger_gripper: A controller's trigger sets the gripper closure.
        residual_threshold_m: Hand distance from its reference flagged in the residual [m], > 0.

    Raises:
        ValueError: ``joint_names`` differ from the controller's, or a number is out of range.
    """

    accepts: tuple[type, ...] = (Twist, ControllerState)

    def __init__(
        self,
        controller: WholeBodyController,
        switches: WholeBodySwitches,
        joint_names: tuple[str, ...],
        *,
        rotation: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0),
        linear_scale: float = 1.0,
        angular_scale: float = 1.0,
        max_linear_m_s: float = 0.5,
        max_angular_rad_s: float = 1.0,
        clutch_button: str | None = None,
        trigger_gripper: bool = False,
        residual_threshold_m: float = 0.05,
    ) -> None:
        if tuple(joint_names) != controller.joint_names:
            raise ValueError(
                f"the robot's joints ({', '.join(joint_names)}) must be the whole-body controller's "
                f"({', '.join(controller.joint_names)}), in order"
            )
        for name, value in (
            ("linear_scale", linear_scale),
            ("angular_scale", angular_scale),
            ("max_linear_m_s", max_linear_m_s),
            ("max_angular_rad_s", max_angular_rad_s),
            ("residual_threshold_m", residual_threshold_m),
        ):
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be > 0, got {value}")
        self.controller = controller
        self.switches = switches
        self.joint_names = tuple(joint_names)
        self._rotation = quat_normalize(np.array(rotation, dtype=np.float64))
        self._linear_scale = float(linear_scale)
        self._angular_scale = float(angular_scale)
        self._max_linear = float(max_linear_m_s)
        self._max_angular = float(max_angular_rad_s)
        self._pose_twist = PoseTwist(clutch_button)
        self._trigger_gripper = trigger_gripper
        self._threshold = float(residual_threshold_m)
        self._q_in: FloatArray | None = None  # q the last call started from
        self._q_out: FloatArray | None = None  # q it returned
        self.last: WBCResult | None = None
        #: Plan-preview-execute of mobile reaches (its ``action`` replaces the operator's while a
        #: confirmed plan executes); None: not offered.
        self.plan: ReachPlanAid | None = None

    def __call__(
        self, sample: Sample, q_current: FloatArray, dt: float
    ) -> tuple[JointCommand | None, WholeBodyResidual | None]:
        """Joint targets for the driver (stamped with the sample's stamp) and the tick's residual.

        Args:
            sample: A ``Twist`` or ``ControllerState``; other samples give ``(None, None)``.
            q_current: Last command sent to the driver, order of ``joint_names``. Shape (10,).
            dt: Control period [s].
        """
        if isinstance(sample, Twist):
            linear, angular = sample.linear, sample.angular
        elif isinstance(sample, ControllerState):
            linear, angular = self._pose_twist(sample)
            if self._trigger_gripper:
                self.switches.set_gripper(sample.trigger)
        else:
            return None, None
        q = np.asarray(q_current, dtype=np.float64)
        self._sync(q, dt)
        v = self._limit(
            quat_rotate(self._rotation, np.asarray(linear)) * self._linear_scale, self._max_linear
        )
        w = self._limit(
            quat_rotate(self._rotation, np.asarray(angular)) * self._angular_scale, self._max_angular
        )
        action = np.array([*v, *w, self.switches.gripper, float(self.switches.mode)])
        if self.plan is not None:
            self.plan.observe(q)
            if self.plan.executing and (
                np.linalg.norm(v) > _TAKEOVER_M_S or np.linalg.norm(w) > _TAKEOVER_RAD_S
            ):
                self.plan.cancel("the operator took over")  # the operator's input wins, at once
            planned = self.plan.action(q, self.switches.gripper)
            if planned is not None:
                action = planned  # a confirmed plan drives; the safety chain still checks it
        t0 = time.perf_counter()
        result = self.controller.step(action, q, dt)
        solve_s = time.perf_counter() - t0
        self.last = result
        self._q_in, self._q_out = q.copy(), result.q
        command = JointCommand(sample.stamp, self.joint_names, result.q, result.qdot)
        return command, WholeBodyResidual(result, action, self._threshold, solve_s)

    def reset(self) -> None:
        """Forget velocities, references and the controller pose (the robot is driven home); an
        executing plan is cancelled (homing, a pause, a fault or a handover took the robot)."""
        if self.plan is not None:
            self.plan.cancel("control was reset (homing, pause, fault or handover)")
        self.controller.reset()
        self._pose_twist.reset()
        self._q_in = self._q_out = None

    def _sync(self, q: FloatArray, dt: float) -> None:
        """Restart the acceleration limit from the commanded velocity when the chain changed our output."""
        if self._q_out is None or self._q_in is None:
            self.controller.reset()
            return
        if np.array_equal(q, self._q_out):
            return
        velocity = (q - self._q_in) / dt
        if np.all(np.isfinite(velocity)):
            self.controller.sync_velocity(velocity)

    @staticmethod
    def _limit(vector: FloatArray, norm: float) -> FloatArray:
        if not np.all(np.isfinite(vector)):
            return np.zeros(3)
        size = float(np.linalg.norm(vector))
        return vector * (norm / size) if size > norm else vector


class WholeBodyGripper:
    """The gripper part of the whole-body action: opening ``1 - switches.gripper`` on each sample of
    the bound stream (a :class:`~telerig.retarget.binding.GripperRetargeter`)."""

    __slots__ = ("switches",)

    def __init__(self, switches: WholeBodySwitches) -> None:
        self.switches = switches

    def __call__(self, sample: Sample) -> GripperCommand | None:
        """Opening for ``sample``'s stamp; None for samples that are not twists or controllers."""
        if not isinstance(sample, (Twist, ControllerState)):
            return None
        return GripperCommand(sample.stamp, opening=1.0 - self.switches.gripper)
