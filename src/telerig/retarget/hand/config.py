"""Config of the dexterous hand retargeter (registered by ``type``)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, ClassVar, Literal

from pydantic import Field, field_validator

from telerig.config.schema import RetargeterConfig
from telerig.errors import ConfigError
from telerig.ir.types import HAND_KEYPOINTS
from telerig.registry import RETARGETERS

if TYPE_CHECKING:
    from telerig.retarget.binding import BindContext, Bound
    from telerig.retarget.hand.optimizer import HandRetargeter

__all__ = ["HandVectorConfig"]

_Scale = Annotated[float, Field(gt=0, le=5)]


@RETARGETERS.register
class HandVectorConfig(RetargeterConfig):
    """A tracked hand → dexterous robot hand joints by matching keypoint vectors (wrist to tips, thumb MCP).

    ``alpha_i = scale * finger_scales[finger of vector i]``; ``scale`` defaults to the hand's own
    (robot over adult human open-hand reach: Inspire 0.98, Ability 0.92, Allegro 1.22).
    ``vectors`` are ``[origin, task]`` MediaPipe index pairs; the default is wrist to every
    fingertip the robot has, plus wrist to the thumb MCP.
    """

    type: Literal["hand_vector"] = "hand_vector"
    targets: ClassVar[tuple[str, ...]] = ("hand",)
    hand: Literal["inspire", "ability", "allegro"] = "inspire"
    handedness: Literal["left", "right"] = "right"
    vectors: tuple[tuple[int, int], ...] | None = None
    weights: tuple[Annotated[float, Field(ge=0)], ...] | None = None
    scale: _Scale | None = None
    finger_scales: tuple[_Scale, _Scale, _Scale, _Scale, _Scale] = (1.0, 1.0, 1.0, 1.0, 1.0)
    #: Smoothing weight on the change from the previous solution [m^2/rad^2].
    beta: Annotated[float, Field(ge=0, le=1)] = 1e-3
    #: Solver steps per sample (see :class:`~telerig.retarget.hand.optimizer.VectorOptimizer`).
    iterations: Annotated[int, Field(ge=1, le=50)] = 3
    min_confidence: Annotated[float, Field(ge=0, le=1)] = 0.5
    frame: Literal["keypoints", "wrist"] = "keypoints"
    #: Add the real hand's linkages (mimic joints) to models that drive every joint on its own.
    couplings: bool = True
    command: Literal["actuated", "all"] = "actuated"
    #: Mean vector error above which a sample's residual is flagged [m].
    residual_threshold_m: Annotated[float, Field(gt=0, le=0.5)] = 0.03

    @field_validator("vectors")
    @classmethod
    def _pairs(cls, value: tuple[tuple[int, int], ...] | None) -> tuple[tuple[int, int], ...] | None:
        if value is None:
            return None
        if not value:
            raise ValueError(
                "vectors: need at least one [origin, task] pair, or leave it out for the default"
            )
        for origin, task in value:
            if not (0 <= origin < HAND_KEYPOINTS and 0 <= task < HAND_KEYPOINTS):
                raise ValueError(
                    f"vectors: keypoint indices must be in [0, {HAND_KEYPOINTS - 1}], got [{origin}, {task}]"
                )
            if origin == task:
                raise ValueError(f"vectors: a vector needs two different keypoints, got [{origin}, {task}]")
        return value

    def build(self) -> HandRetargeter:
        """Load the hand model and build the retargeter.

        Raises:
            ConfigError: ``vectors`` name a keypoint the hand has no point for, or ``weights`` do
                not match ``vectors``.
            DependencyError: the package that ships the hand model is not installed.
        """
        from telerig.retarget.hand.optimizer import HandRetargeter
        from telerig.retarget.hand.vectors import KeypointVectors
        from telerig.robots.models.hands import load_hand

        hand = load_hand(self.hand, self.handedness, couplings=self.couplings)
        try:
            vectors = None if self.vectors is None else KeypointVectors.of(self.vectors)
            return HandRetargeter(
                hand,
                vectors,
                scale=self.scale,
                finger_scales=self.finger_scales,
                weights=self.weights,
                beta=self.beta,
                iterations=self.iterations,
                min_confidence=self.min_confidence,
                frame=self.frame,
                command=self.command,
            )
        except ValueError as exc:
            raise ConfigError(f"hand_vector: {exc}") from None

    def bind(self, context: BindContext) -> Bound:
        """Drive a hand robot's commanded joints (``target: hand``) from a tracked hand's keypoints.

        Raises:
            ConfigError: the target is not ``hand``, or the robot's joints are not the hand
                model's commanded joints (e.g. another hand model, or ``command: all`` on a robot
                that commands only the motors).
        """
        from telerig.retarget.binding import Bound
        from telerig.retarget.hand.joints import HandJointsRetargeter

        context.require_target(self.type, *self.targets)
        retargeter = self.build()
        try:
            joints = HandJointsRetargeter(
                retargeter, tuple(context.robot.joint_names), threshold_m=self.residual_threshold_m
            )
        except ConfigError as exc:
            raise ConfigError(
                f"{context.where}: robot {context.robot_id!r}: {exc}; use a robot of hand model "
                f"{self.hand!r} ({self.handedness}), e.g. type mujoco_hand with model {self.hand}"
            ) from None
        return Bound(joints=joints)
