"""Arm retargeting: operator pose → end-effector target (absolute or clutched relative) → IK → joints."""

from __future__ import annotations

from typing import Literal

from telerig.ir.frames import quat_conjugate, quat_multiply
from telerig.ir.types import ControllerState, FloatArray, HandPose, JointCommand, Pose, Sample
from telerig.retarget.alignment import Alignment
from telerig.retarget.arm_ik import ArmIK, IKResult
from telerig.retarget.clutch import Clutch
from telerig.retarget.fixtures import FixtureSet
from telerig.retarget.scaling import ScaleKnob
from telerig.retarget.se3_filter import OneEuroPoseFilter

__all__ = ["AbsolutePoseRetargeter", "ArmMode", "ArmPoseRetargeter"]

#: ``absolute``: where your hand is, the end effector is. ``relative``: the end effector moves by
#: the hand's motion while the clutch is held, and holds still while it is not.
ArmMode = Literal["absolute", "relative"]


def _pose_of(sample: Sample) -> tuple[FloatArray, FloatArray]:
    if isinstance(sample, ControllerState | Pose):
        return sample.position, sample.orientation
    if isinstance(sample, HandPose):
        return sample.wrist_position, sample.wrist_orientation
    raise TypeError(
        f"an arm retargeter needs a Pose, ControllerState or HandPose, got {type(sample).__name__}"
    )


class ArmPoseRetargeter:
    """Operator pose → end-effector target → virtual fixture → SE(3) filter → one IK step.

    Absolute mode maps the pose through ``alignment`` (origins, rotation, calibration scale).
    Relative mode anchors on the clutch press: with ``(p_e0, q_e0)`` the end-effector pose at
    ``q_current`` at the press and ``(p_h0, q_h0)`` the hand pose then, the target is
    ``p = p_e0 + k s R (p_h - p_h0)`` and ``q = (R (q_h q_h0^-1) R^-1) q_e0``, with ``R`` the
    alignment rotation (operator → robot base frame), ``s`` its calibration scale and ``k`` the live
    motion scale (translation only; rotations stay 1:1). While the clutch is up the command is
    ``q_current``: the robot holds, and the input stays fresh for the safety chain's watchdog.
    A change of the motion scale or of the fixture re-anchors at the current target, so neither
    makes the target jump. Targets are in the robot base frame.

    Args:
        alignment: Operator frame → robot base frame.
        ik: The arm's IK (its joints are the command's joints).
        joint_names: Names of the commanded joints, in the IK's order.
        mode: See :data:`ArmMode`.
        clutch: The clutch button; required in relative mode, not allowed in absolute mode.
        pose_filter: SE(3) filter on the target; None bypasses filtering.
        scale: Live motion scale (relative mode only); None means 1.
        fixtures: Live virtual fixtures; None means unconstrained.
    """

    #: Sample types this retargeter takes (the control node counts others as wrong-type input).
    accepts: tuple[type, ...] = (ControllerState, Pose, HandPose)

    __slots__ = (
        "_alignment",
        "_clutch",
        "_ee0",
        "_filter",
        "_fixtures",
        "_hand0",
        "_ik",
        "_scale",
        "_target",
        "_version",
        "joint_names",
        "mode",
    )

    def __init__(
        self,
        alignment: Alignment,
        ik: ArmIK,
        joint_names: tuple[str, ...],
        *,
        mode: ArmMode = "absolute",
        clutch: Clutch | None = None,
        pose_filter: OneEuroPoseFilter | None = None,
        scale: ScaleKnob | None = None,
        fixtures: FixtureSet | None = None,
    ) -> None:
        if mode == "relative" and clutch is None:
            raise ValueError("relative mode needs a clutch button")
        if mode == "absolute" and (clutch is not None or scale is not None):
            raise ValueError("a clutch and a motion scale need relative mode")
        self._alignment = alignment
        self._ik = ik
        self.joint_names = joint_names
        self.mode = mode
        self._clutch = clutch
        self._filter = pose_filter
        self._scale = scale
        self._fixtures = fixtures
        self._hand0: tuple[FloatArray, FloatArray] | None = None
        self._ee0: tuple[FloatArray, FloatArray] | None = None
        self._target: tuple[FloatArray, FloatArray] | None = None
        self._version = self._aid_version()

    @property
    def engaged(self) -> bool:
        """Whether the arm follows the hand now (always in absolute mode; clutch held in relative)."""
        return self._clutch is None or self._clutch.engaged

    @property
    def motion_scale(self) -> ScaleKnob | None:
        """The live motion scale knob, if any (an :class:`~telerig.runtime.control_node.Aid`)."""
        return self._scale

    @property
    def fixtures(self) -> FixtureSet | None:
        """The live virtual fixtures, if any (an :class:`~telerig.runtime.control_node.Aid`)."""
        return self._fixtures

    @property
    def target(self) -> tuple[FloatArray, FloatArray] | None:
        """Last end-effector target before filtering: position [m] (3,), orientation (w, x, y, z) (4,)."""
        return self._target

    def reset(self) -> None:
        """Forget anchors and filter state (after homing): relative mode waits for a new press."""
        if self._clutch is not None:
            self._clutch.reset()
        if self._filter is not None:
            self._filter.reset()
        self._hand0 = self._ee0 = self._target = None

    def _from_anchor(
        self, anchor: tuple[FloatArray, FloatArray] | None, dp: FloatArray, dq: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """Anchor pose moved by ``dp`` [m] and left-rotated by ``dq``, after the active fixture."""
        assert anchor is not None
        if self._fixtures is not None:
            dp, dq = self._fixtures.active.constrain(dp, dq)
        return anchor[0] + dp, quat_multiply(dq, anchor[1])

    def _aid_version(self) -> tuple[int, int]:
        return (
            0 if self._scale is None else self._scale.version,
            0 if self._fixtures is None else self._fixtures.version,
        )

    def __call__(
        self, sample: Sample, q_current: FloatArray, dt: float
    ) -> tuple[JointCommand | None, IKResult | None]:
        """Joint targets for ``sample`` (stamped with its stamp) and the IK residual (None while holding).

        Args:
            sample: Operator pose (controller, pose or hand wrist) in the operator frame.
            q_current: Current commanded joint positions [rad]. Shape (n,).
            dt: Control period [s].

        Raises:
            TypeError: ``sample`` carries no pose (see :attr:`accepts`).
        """
        p_h, q_h = _pose_of(sample)
        version = self._aid_version()
        reanchor = version != self._version
        self._version = version
        if self._clutch is not None:
            event = self._clutch.update(sample)
            if event in ("release", "idle"):
                self._hand0 = None
                return JointCommand(sample.stamp, self.joint_names, q_current), None
            if event == "press" or self._hand0 is None:
                self._ee0 = self._ik.forward(q_current)
                self._hand0 = (p_h, q_h)
                if self._filter is not None:
                    self._filter.reset()
            elif reanchor and self._target is not None:
                self._ee0 = self._target
                self._hand0 = (p_h, q_h)
            k = 1.0 if self._scale is None else self._scale.scale
            dp = k * self._alignment.displacement(p_h - self._hand0[0])
            dq = self._alignment.rotation_delta(quat_multiply(q_h, quat_conjugate(self._hand0[1])))
            p, q = self._from_anchor(self._ee0, dp, dq)
        else:
            p, q = self._alignment.apply(p_h, q_h)
            if self._fixtures is not None:
                # The fixture constrains motion from where the target was when it was switched on.
                if self._ee0 is None or reanchor:
                    self._ee0 = (p, q)
                dq = quat_multiply(q, quat_conjugate(self._ee0[1]))
                p, q = self._from_anchor(self._ee0, p - self._ee0[0], dq)
        self._target = (p, q)
        if self._filter is not None:
            p, q = self._filter(p, q, sample.stamp.capture_ns * 1e-9)
        result = self._ik.solve(p, q, q_current, dt)
        return JointCommand(sample.stamp, self.joint_names, result.q), result


class AbsolutePoseRetargeter(ArmPoseRetargeter):
    """ "Where your hand is, the end effector is": absolute mode without filter or fixtures."""

    __slots__ = ()

    def __init__(self, alignment: Alignment, ik: ArmIK, joint_names: tuple[str, ...]) -> None:
        super().__init__(alignment, ik, joint_names)
