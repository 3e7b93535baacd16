"""Configs of the built-in retargeters (registered by ``type``)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, ClassVar, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from telerig.config.schema import AlignmentConfig, RetargeterConfig
from telerig.registry import RETARGETERS

if TYPE_CHECKING:  # heavy (mink, MuJoCo): imported when a retargeter is built, not when a rig is parsed
    from telerig.retarget.arm import ArmPoseRetargeter
    from telerig.retarget.arm_ik import ArmIK
    from telerig.retarget.base_drive import BaseDrive
    from telerig.retarget.binding import Aid, BindContext, Bound
    from telerig.retarget.fixtures import FixtureSet
    from telerig.retarget.keypoint_filter import OneEuroPointFilter
    from telerig.retarget.reach_plan import PlanMarker
    from telerig.retarget.scaling import ScaleKnob
    from telerig.retarget.se3_filter import OneEuroPoseFilter
    from telerig.robots.models.arm import ArmScene

__all__ = [
    "AbsolutePoseConfig",
    "ArmPoseConfig",
    "BaseDriveConfig",
    "FixtureConfig",
    "FixturesConfig",
    "HumanoidBodyConfig",
    "KeypointFilterConfig",
    "MotionScaleConfig",
    "PinchGripperConfig",
    "PlanMarkerConfig",
    "PoseFilterConfig",
    "TriggerGripperConfig",
    "WholeBodyConfig",
]

#: A ``ControllerState.buttons`` name (see :func:`telerig.retarget.clutch.button_held` for each family's).
ButtonName = Annotated[str, Field(pattern=r"^[A-Za-z0-9_.\-]+$", min_length=1, max_length=32)]
_Id = Annotated[str, Field(pattern=r"^[A-Za-z0-9_.\-]+$", min_length=1, max_length=64)]


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class _InputSource(_Section):
    """Where a live control's buttons come from: the binding's own device part unless named."""

    device: _Id | None = None
    part: _Id | None = None


class PoseFilterConfig(_Section):
    """One-Euro SE(3) filter on the EE target (:class:`~telerig.retarget.se3_filter.OneEuroPoseFilter`).

    Lag at speed v is ``1 / (2 pi (min_cutoff_hz + beta v))`` s: lower ``min_cutoff_hz`` for less
    jitter at rest, higher ``beta`` for less lag in fast motion.
    """

    min_cutoff_hz: Annotated[float, Field(gt=0, le=100)] = 2.0
    #: Cutoff increase per linear speed [Hz per m/s].
    beta: Annotated[float, Field(ge=0, le=10_000)] = 40.0
    #: Cutoff increase per angular speed [Hz per rad/s].
    beta_rotation: Annotated[float, Field(ge=0, le=10_000)] = 4.0
    derivative_cutoff_hz: Annotated[float, Field(gt=0, le=100)] = 1.0

    def build(self) -> OneEuroPoseFilter:
        from telerig.retarget.se3_filter import OneEuroPoseFilter

        return OneEuroPoseFilter(self.min_cutoff_hz, self.beta, self.beta_rotation, self.derivative_cutoff_hz)


class MotionScaleConfig(_InputSource):
    """Live logarithmic motion scale on relative motion, stepped by buttons (and bus commands)."""

    initial: Annotated[float, Field(gt=0)] = 1.0
    min: Annotated[float, Field(gt=0)] = 0.001
    max: Annotated[float, Field(gt=0)] = 100.0
    step_factor: Annotated[float, Field(gt=1, le=100)] = 2.0
    up_button: ButtonName | None = None
    down_button: ButtonName | None = None

    @model_validator(mode="after")
    def _range(self) -> MotionScaleConfig:
        if not self.min <= self.initial <= self.max:
            raise ValueError(f"need min <= initial <= max, got {self.min}, {self.initial}, {self.max}")
        if self.up_button is not None and self.up_button == self.down_button:
            raise ValueError(f"up_button and down_button must differ, both are {self.up_button!r}")
        return self

    def build(self) -> ScaleKnob:
        from telerig.retarget.scaling import ScaleKnob

        return ScaleKnob(
            self.initial,
            minimum=self.min,
            maximum=self.max,
            step_factor=self.step_factor,
            up_button=self.up_button,
            down_button=self.down_button,
        )


class FixtureConfig(_Section):
    """One virtual fixture; ``axis``: direction (``axis``) or plane normal (``plane``), robot base frame."""

    name: _Id
    kind: Literal["free", "orientation", "axis", "plane"]
    axis: tuple[float, float, float] = (0.0, 0.0, 0.0)
    keep_orientation: bool = False

    @model_validator(mode="after")
    def _axis(self) -> FixtureConfig:
        if self.kind in ("axis", "plane") and sum(c * c for c in self.axis) < 1e-12:
            raise ValueError(
                f"fixture {self.name!r}: kind {self.kind!r} needs a non-zero axis, e.g. [0, 0, 1]"
            )
        return self


class FixturesConfig(_InputSource):
    """Virtual fixtures the operator switches live (``cycle_button`` or the ``fixture_command`` stream)."""

    options: Annotated[list[FixtureConfig], Field(min_length=1)] = Field(
        default_factory=lambda: [FixtureConfig(name="free", kind="free")]
    )
    cycle_button: ButtonName | None = None

    @model_validator(mode="after")
    def _unique(self) -> FixturesConfig:
        names = [f.name for f in self.options]
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise ValueError(f"fixture names must be unique, repeated: {', '.join(dupes)}")
        return self

    def build(self, frame: str = "base") -> FixtureSet:
        from telerig.retarget.fixtures import Fixture, FixtureSet

        fixtures = [Fixture(f.name, f.kind, f.axis, f.keep_orientation) for f in self.options]
        return FixtureSet(fixtures, cycle_button=self.cycle_button, frame=frame)


@RETARGETERS.register
class ArmPoseConfig(RetargeterConfig):
    """Operator pose → end-effector target → IK: absolute alignment or clutched relative motion.

    ``mode: relative`` needs ``clutch_button``; the arm then moves by the hand's motion (rotated by
    ``alignment.rotation``, scaled by ``alignment.scale`` times the live ``scale``) only while it is
    held. ``filter`` smooths the target on SE(3); ``fixtures`` constrain it (both modes).
    """

    type: Literal["arm_pose"] = "arm_pose"
    targets: ClassVar[tuple[str, ...]] = ("arm",)
    mode: Literal["absolute", "relative"] = "absolute"
    clutch_button: ButtonName | None = None
    alignment: AlignmentConfig = Field(default_factory=AlignmentConfig)
    residual_threshold_m: Annotated[float, Field(gt=0, le=1)] = 0.05
    #: QP sub-steps per control tick; 1 tracks smooth 100 Hz input to 0.01 mm (benchmarks/arm_ik.py).
    ik_substeps: Annotated[int, Field(ge=1, le=20)] = 1
    filter: PoseFilterConfig | None = None
    scale: MotionScaleConfig | None = None
    fixtures: FixturesConfig | None = None

    @model_validator(mode="after")
    def _mode(self) -> ArmPoseConfig:
        if self.mode == "relative" and self.clutch_button is None:
            raise ValueError("mode 'relative' needs clutch_button, e.g. clutch_button: grip")
        if self.mode == "absolute" and self.clutch_button is not None:
            raise ValueError("clutch_button needs mode: relative")
        if self.mode == "absolute" and self.scale is not None:
            raise ValueError("scale applies to relative motion; set mode: relative or remove scale")
        return self

    def build(self, ik: ArmIK, joint_names: tuple[str, ...], *, frame: str = "base") -> ArmPoseRetargeter:
        """The retargeter for ``ik``'s arm; its live aids are its ``scale`` and ``fixtures`` attributes."""
        from telerig.retarget.alignment import Alignment
        from telerig.retarget.arm import ArmPoseRetargeter
        from telerig.retarget.clutch import Clutch

        return ArmPoseRetargeter(
            Alignment.from_config(self.alignment),
            ik,
            joint_names,
            mode=self.mode,
            clutch=None if self.clutch_button is None else Clutch(self.clutch_button),
            pose_filter=None if self.filter is None else self.filter.build(),
            scale=None if self.scale is None else self.scale.build(),
            fixtures=None if self.fixtures is None else self.fixtures.build(frame),
        )

    def bind(self, context: BindContext) -> Bound:
        """IK on the robot's kinematic model drives its arm joints; the scale and fixtures become aids."""
        from telerig.retarget.arm_ik import ArmIK
        from telerig.retarget.binding import Bound

        context.require_target(self.type, *self.targets)
        ik = ArmIK(
            _arm_kinematics(context),
            iterations=self.ik_substeps,
            residual_threshold_m=self.residual_threshold_m,
        )
        retargeter = self.build(ik, context.robot.joint_names, frame=f"{context.robot_id}/base")
        bound = Bound(joints=retargeter)
        if retargeter.motion_scale is not None and self.scale is not None:
            topic = context.topic_of(self.scale.device, self.scale.part, what="scale")
            bound.aids.append((topic, retargeter.motion_scale))
        if retargeter.fixtures is not None and self.fixtures is not None:
            topic = context.topic_of(self.fixtures.device, self.fixtures.part, what="fixtures")
            bound.aids.append((topic, retargeter.fixtures))
        return bound


@RETARGETERS.register
class AbsolutePoseConfig(RetargeterConfig):
    """Absolute alignment: the operator's hand pose, mapped into the robot base frame, is the EE target."""

    type: Literal["absolute_pose"] = "absolute_pose"
    targets: ClassVar[tuple[str, ...]] = ("arm",)
    alignment: AlignmentConfig = Field(default_factory=AlignmentConfig)
    residual_threshold_m: Annotated[float, Field(gt=0, le=1)] = 0.05
    #: QP sub-steps per control tick; 1 tracks smooth 100 Hz input to 0.01 mm (benchmarks/arm_ik.py).
    ik_substeps: Annotated[int, Field(ge=1, le=20)] = 1

    def as_arm_pose(self) -> ArmPoseConfig:
        """The equivalent ``arm_pose`` config (absolute mode, no filter, no fixtures)."""
        return ArmPoseConfig(
            alignment=self.alignment,
            residual_threshold_m=self.residual_threshold_m,
            ik_substeps=self.ik_substeps,
        )

    def bind(self, context: BindContext) -> Bound:
        context.require_target(self.type, *self.targets)  # before arm_pose's check names arm_pose
        return self.as_arm_pose().bind(context)


@RETARGETERS.register
class TriggerGripperConfig(RetargeterConfig):
    """Controller trigger (or grip) → gripper opening: pressed closes."""

    type: Literal["trigger_gripper"] = "trigger_gripper"
    targets: ClassVar[tuple[str, ...]] = ("gripper",)
    source: Literal["trigger", "grip"] = "trigger"

    def bind(self, context: BindContext) -> Bound:
        from telerig.retarget.binding import Bound
        from telerig.retarget.gripper import TriggerGripper

        context.require_target(self.type, *self.targets)
        return Bound(gripper=TriggerGripper(self.source))


@RETARGETERS.register
class PinchGripperConfig(RetargeterConfig):
    """A tracked hand's thumb-index pinch distance → gripper opening (glove, camera, XR hands)."""

    type: Literal["pinch_gripper"] = "pinch_gripper"
    targets: ClassVar[tuple[str, ...]] = ("gripper",)
    closed_at_m: Annotated[float, Field(ge=0, le=0.2)] = 0.02
    open_at_m: Annotated[float, Field(gt=0, le=0.3)] = 0.08

    @model_validator(mode="after")
    def _ordered(self) -> PinchGripperConfig:
        if self.closed_at_m >= self.open_at_m:
            raise ValueError(f"closed_at_m ({self.closed_at_m}) must be below open_at_m ({self.open_at_m})")
        return self

    def bind(self, context: BindContext) -> Bound:
        from telerig.retarget.binding import Bound
        from telerig.retarget.gripper import PinchGripper

        context.require_target(self.type, *self.targets)
        return Bound(gripper=PinchGripper(self.closed_at_m, self.open_at_m))


@RETARGETERS.register
class BaseDriveConfig(RetargeterConfig):
    """Controller mode for a wheeled base: held buttons drive forward/backward, the thumbstick x turns.

    Bind it with ``target: base`` to a robot whose driver implements
    :class:`~telerig.robots.base.MobileBase`. Input older than ``input_timeout_ms`` stops the base;
    devices that send only on change (gamepad, keyboard) need a timeout longer than a held press.
    """

    type: Literal["base_drive"] = "base_drive"
    targets: ClassVar[tuple[str, ...]] = ("base",)
    forward_button: ButtonName = "b"
    backward_button: ButtonName = "a"
    max_linear_m_s: Annotated[float, Field(gt=0, le=5)] = 0.3
    max_angular_rad_s: Annotated[float, Field(gt=0, le=6)] = 0.8
    deadzone: Annotated[float, Field(ge=0, lt=1)] = 0.15
    input_timeout_ms: Annotated[float, Field(gt=0, le=10_000)] = 250.0

    @model_validator(mode="after")
    def _buttons(self) -> BaseDriveConfig:
        if self.forward_button == self.backward_button:
            raise ValueError(
                f"forward_button and backward_button must differ, both are {self.forward_button!r}"
            )
        return self

    def build(self, source_id: str = "base_drive") -> BaseDrive:
        from telerig.retarget.base_drive import BaseDrive

        return BaseDrive(
            forward_button=self.forward_button,
            backward_button=self.backward_button,
            max_linear_m_s=self.max_linear_m_s,
            max_angular_rad_s=self.max_angular_rad_s,
            deadzone=self.deadzone,
            input_timeout_s=self.input_timeout_ms / 1e3,
            source_id=source_id,
        )

    def bind(self, context: BindContext) -> Bound:
        from telerig.errors import ConfigError
        from telerig.retarget.binding import Bound
        from telerig.robots.base import MobileBase

        context.require_target(self.type, *self.targets)
        if not isinstance(context.robot, MobileBase):
            raise ConfigError(
                f"{context.where}: robot {context.robot_id!r} has no mobile base; bind base_drive to one"
            )
        return Bound(base=self.build(f"{context.robot_id}/base_drive"))


def _arm_kinematics(context: BindContext) -> ArmScene:
    """The kinematic model IK solves on for the bound robot (arm joints only: twice as fast as the scene)."""
    from telerig.errors import ConfigError
    from telerig.robots.models import arm_kinematics_of

    kinematics = arm_kinematics_of(context.robot)
    if kinematics is None:
        raise ConfigError(
            f"{context.where}: arm IK needs an arm model; robot {context.robot_id!r} names none (a "
            "mujoco_arm, or a real arm whose config names its model, e.g. `model: ur5e_robotiq85` on a "
            "ur_rtde robot; a humanoid binds humanoid_body to body, TIAGo wbc to whole_body, a hand "
            "hand_vector to hand)"
        )
    return kinematics


class KeypointFilterConfig(_Section):
    """One-Euro filter on the skeleton keypoints before IK (see :mod:`telerig.retarget.keypoint_filter`).

    Each keypoint lags ``1 / (2 pi (min_cutoff_hz + beta v))`` s at speed v [m/s]: with the defaults
    80 ms at rest, 23 ms at 0.5 m/s, 13 ms at 1 m/s. Worth it for jittery markerless tracking;
    optical mocap is clean enough to run without it.
    """

    min_cutoff_hz: Annotated[float, Field(gt=0, le=100)] = 2.0
    #: Cutoff increase per keypoint speed [Hz per m/s].
    beta: Annotated[float, Field(ge=0, le=10_000)] = 10.0
    derivative_cutoff_hz: Annotated[float, Field(gt=0, le=100)] = 1.0

    def build(self) -> OneEuroPointFilter:
        from telerig.retarget.keypoint_filter import OneEuroPointFilter

        return OneEuroPointFilter(self.min_cutoff_hz, self.beta, self.derivative_cutoff_hz)


@RETARGETERS.register
class HumanoidBodyConfig(RetargeterConfig):
    """Body skeleton (mocap, markerless) → humanoid upper body by IK with anatomical correspondence.

    Bind it with ``target: body`` to a ``mujoco_humanoid`` robot or a real ``unitree_g1`` (the
    same 29-DoF G1 model, its 17 upper-body joints). ``profile`` names the skeleton's
    joint naming (``mediapipe``, ``cmu`` for BVH / NatNet, ``motive``); None detects it from the
    first skeleton. A tick is flagged when a wrist misses its target by more than
    ``residual_threshold_m``; the wrist and elbow errors are recorded every tick.
    """

    type: Literal["humanoid_body"] = "humanoid_body"
    targets: ClassVar[tuple[str, ...]] = ("body",)
    profile: Literal["mediapipe", "cmu", "motive"] | None = None
    residual_threshold_m: Annotated[float, Field(gt=0, le=1)] = 0.05
    #: QP sub-steps per skeleton sample.
    ik_substeps: Annotated[int, Field(ge=1, le=20)] = 1
    #: Weight of the elbow position tasks relative to the wrists' (1); lower lets the hands win.
    elbow_cost: Annotated[float, Field(ge=0, le=10)] = 0.3
    filter: KeypointFilterConfig | None = None

    def bind(self, context: BindContext) -> Bound:
        """IK on the humanoid's kinematic model drives its upper-body joints (waist and arms)."""
        import numpy as np

        from telerig.errors import ConfigError
        from telerig.retarget.binding import Bound
        from telerig.retarget.humanoid import HumanoidBodyRetargeter, HumanoidIK, HumanoidRetargeter
        from telerig.robots.models.g1 import UPPER_BODY_JOINTS, build_humanoid_kinematics

        context.require_target(self.type, *self.targets)
        robot = context.robot
        names = tuple(robot.joint_names)
        if set(names) < set(UPPER_BODY_JOINTS):
            missing = ", ".join(j for j in UPPER_BODY_JOINTS if j not in names)
            raise ConfigError(
                f"{context.where}: retargeter 'humanoid_body' drives the whole G1 upper body; robot "
                f"{context.robot_id!r} commands {len(names)} of the G1's {len(UPPER_BODY_JOINTS)} "
                f"upper-body joints; add {missing} to its joints (or leave joints out)"
            )
        if set(names) != set(UPPER_BODY_JOINTS):  # any order: commands follow the driver's
            raise ConfigError(
                f"{context.where}: retargeter 'humanoid_body' drives a humanoid upper body; robot "
                f"{context.robot_id!r} is a {type(robot).__name__}, use a mujoco_humanoid robot"
            )
        scene = build_humanoid_kinematics()
        limits = robot.limits
        velocity = dict(zip(limits.names, limits.velocity, strict=True))
        ik = HumanoidIK(
            scene,
            velocity_limit=np.array([velocity[j] for j in scene.joints]),
            elbow_cost=self.elbow_cost,
            iterations=self.ik_substeps,
            residual_threshold_m=self.residual_threshold_m,
        )
        retargeter = HumanoidRetargeter(
            ik, profile=self.profile, keypoint_filter=None if self.filter is None else self.filter.build()
        )
        return Bound(joints=HumanoidBodyRetargeter(retargeter, robot.joint_names))


class PlanMarkerConfig(_Section):
    """The operator's plan marker of a whole-body robot (:class:`~telerig.retarget.reach_plan.PlanMarker`).

    ``plan`` ("plan here") without coordinates plans a reach to the latest pose of ``device.part``
    (a ``ControllerState`` or ``Pose`` stream, e.g. a VR controller), mapped by ``alignment``
    (operator frame → the robot's world frame, as the arm retargeters' alignment) and refused
    when older than ``max_age_s`` [s]. ``orientation``: plan the marker's orientation too (else
    the hand keeps its current one). ``device`` defaults to the binding's own.
    """

    device: _Id | None = None
    part: _Id
    alignment: AlignmentConfig = Field(default_factory=AlignmentConfig)
    max_age_s: Annotated[float, Field(gt=0, le=10)] = 0.5
    orientation: bool = False


@RETARGETERS.register
class WholeBodyConfig(RetargeterConfig):
    """Whole-body QP teleoperation of a mobile manipulator (TIAGo): bind with ``target: whole_body``.

    The bound stream is a SpaceMouse ``twist`` (or any ``Twist``) or a VR controller (velocity from
    successive poses while ``clutch_button`` is held). Each sample becomes the 8-D action
    ``(twist, gripper, mode)`` of :class:`~telerig.retarget.wbc.WholeBodyController`: in end-effector
    mode the twist moves the hand and the base stands still; in whole-body mode ``(vx, vy, wz)``
    drive the base, ``vz`` raises the hand, and the hand holds its pose on the base. A press of
    ``mode_button`` toggles the mode, of ``gripper_button`` the gripper (``gripper_source:
    trigger`` makes a controller's trigger close it instead); these buttons come from ``buttons``
    (a SpaceMouse sends them on ``right_controller``, apart from its twist), default the bound part.
    ``rotation`` (w, x, y, z) turns the operator frame into the robot base frame. The gripper part
    of the action drives the robot's gripper from the same binding; the residual records the
    per-task errors, the mode and the action every tick. ``plan`` offers plan-preview-execute of
    mobile reaches; ``plan_marker`` (:class:`PlanMarkerConfig`) names the device part whose pose
    designates their target.
    """

    type: Literal["wbc"] = "wbc"
    targets: ClassVar[tuple[str, ...]] = ("whole_body",)
    mode_button: ButtonName | None = "left"
    gripper_button: ButtonName | None = "right"
    gripper_source: Literal["button", "trigger"] = "button"
    buttons: _InputSource | None = None
    clutch_button: ButtonName | None = None
    initial_mode: Literal["ee", "whole_body"] = "ee"
    rotation: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    linear_scale: Annotated[float, Field(gt=0, le=100)] = 1.0
    angular_scale: Annotated[float, Field(gt=0, le=100)] = 1.0
    #: Norm limits of the twist after scaling [m/s], [rad/s].
    max_linear_m_s: Annotated[float, Field(gt=0, le=2)] = 0.3
    max_angular_rad_s: Annotated[float, Field(gt=0, le=3)] = 1.0
    residual_threshold_m: Annotated[float, Field(gt=0, le=1)] = 0.05
    #: Plan-preview-execute of mobile reaches on ``<robot>/plan`` (:mod:`telerig.retarget.reach_plan`):
    #: a staged plan older than ``plan_max_age_s`` [s] is refused.
    plan: bool = True
    plan_max_age_s: Annotated[float, Field(gt=0, le=600)] = 30.0
    #: The device part whose pose designates the plan target (``plan`` / "plan here"); None: the
    #: ``target X Y Z`` command designates.
    plan_marker: PlanMarkerConfig | None = None

    @model_validator(mode="after")
    def _inputs(self) -> WholeBodyConfig:
        norm = sum(c * c for c in self.rotation) ** 0.5
        if abs(norm - 1.0) > 1e-3:
            raise ValueError(f"rotation must be a unit quaternion (w, x, y, z); its norm is {norm:.4f}")
        if self.mode_button is not None and self.mode_button == self.gripper_button:
            raise ValueError(f"mode_button and gripper_button must differ, both are {self.mode_button!r}")
        if self.plan_marker is not None and not self.plan:
            raise ValueError("plan_marker designates plan targets: set plan: true, or remove plan_marker")
        return self

    def bind(self, context: BindContext) -> Bound:
        """The whole-body QP on the TIAGo kinematic model drives all ten joints; its action's gripper
        part drives the gripper; the mode/gripper switches become an aid on ``buttons``."""
        from telerig.errors import ConfigError
        from telerig.retarget.binding import Bound
        from telerig.retarget.wbc import EE_MODE, WHOLE_BODY_MODE, WholeBodyController
        from telerig.retarget.whole_body import WholeBodyGripper, WholeBodyRetargeter, WholeBodySwitches
        from telerig.robots.models.tiago import TIAGO_JOINTS, build_tiago_kinematics

        context.require_target(self.type, *self.targets)
        if tuple(context.robot.joint_names) != TIAGO_JOINTS:
            raise ConfigError(
                f"{context.where}: retargeter 'wbc' drives a TIAGo (joints {', '.join(TIAGO_JOINTS)}); "
                f"robot {context.robot_id!r} is a {type(context.robot).__name__}, use a mujoco_tiago robot"
            )
        switches = WholeBodySwitches(
            mode_button=self.mode_button,
            gripper_button=self.gripper_button if self.gripper_source == "button" else None,
            mode=WHOLE_BODY_MODE if self.initial_mode == "whole_body" else EE_MODE,
        )
        retargeter = WholeBodyRetargeter(
            WholeBodyController(build_tiago_kinematics()),
            switches,
            context.robot.joint_names,
            rotation=self.rotation,
            linear_scale=self.linear_scale,
            angular_scale=self.angular_scale,
            max_linear_m_s=self.max_linear_m_s,
            max_angular_rad_s=self.max_angular_rad_s,
            clutch_button=self.clutch_button,
            trigger_gripper=self.gripper_source == "trigger",
            residual_threshold_m=self.residual_threshold_m,
        )
        source = self.buttons or _InputSource()
        topic = context.topic_of(source.device, source.part, what="buttons")
        aids: list[tuple[str, Aid]] = [(topic, switches)]
        bound = Bound(joints=retargeter, gripper=WholeBodyGripper(switches), aids=aids)
        if self.plan:
            from telerig.retarget.reach_plan import ReachPlanAid

            marker = None if self.plan_marker is None else self._marker(context, bound)
            # Fed by the driving stream: each of its ticks publishes what the planner changed.
            retargeter.plan = ReachPlanAid(
                retargeter.controller, max_age_s=self.plan_max_age_s, marker=marker
            )
            aids.append((context.topic, retargeter.plan))
        return bound

    def _marker(self, context: BindContext, bound: Bound) -> PlanMarker:
        """The plan marker, its stream fed to it by the control node (``bound.feeds``)."""
        from telerig.errors import ConfigError
        from telerig.retarget.alignment import Alignment
        from telerig.retarget.reach_plan import PlanMarker

        config = self.plan_marker
        assert config is not None
        topic = context.topic_of(config.device, config.part, what="plan_marker")
        device = config.device or context.device
        robots = {robot for d, robot in context.drives if d == device}
        if robots and context.robot_id not in robots:
            raise ConfigError(
                f"{context.where}: plan_marker.device {device!r} drives {', '.join(sorted(robots))}, not "
                f"{context.robot_id!r}: its pose is another robot's operator input; use a device of "
                f"{context.robot_id!r}'s operator (bound to it, or to no robot)"
            )
        marker = PlanMarker(
            f"{device}.{config.part}",
            Alignment.from_config(config.alignment),
            max_age_s=config.max_age_s,
            orientation=config.orientation,
        )
        bound.feeds.append((topic, marker.take))
        return marker
