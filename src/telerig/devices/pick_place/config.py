"""Configs of the pick-and-place operators (registered by ``type``); numpy-only at build time."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import Field

from telerig.config.schema import AlignmentConfig, DeviceConfig, Identifier
from telerig.registry import DEVICES

if TYPE_CHECKING:
    from telerig.devices.pick_place.operator import OperatorFrame, ScriptedPickPlace
    from telerig.devices.pick_place.replay import RetargetedReplay

__all__ = ["RetargetedReplayConfig", "ScriptedPickPlaceConfig"]

Vec3 = tuple[float, float, float]


class _TaskOperatorConfig(DeviceConfig):
    #: The task robot whose ``object_pose`` stream (cube and target, world frame) it watches.
    robot: Identifier
    #: The binding's alignment (operator frame → robot base), so it finds the cube in its own frame.
    alignment: AlignmentConfig = Field(default_factory=AlignmentConfig)
    #: World position of the robot base [m] (its axes along the world's); the arm scene's is (0, 0, 0.8).
    robot_base: Vec3 = (0.0, 0.0, 0.8)

    def frame(self) -> OperatorFrame:
        import numpy as np

        from telerig.devices.pick_place.operator import OperatorFrame

        a = self.alignment
        return OperatorFrame(
            np.array(a.rotation, dtype=np.float64),
            np.array(a.operator_origin, dtype=np.float64),
            np.array(a.robot_origin, dtype=np.float64),
            a.scale,
            np.array(self.robot_base, dtype=np.float64),
        )


@DEVICES.register
class ScriptedPickPlaceConfig(_TaskOperatorConfig):
    """A scripted VR operator solving the pick-and-place task from the cube's observed pose, with a
    human's variation (pace, pauses, approach and yaw errors it corrects) drawn from the episode's
    seed (``seed + k`` for episode k, as the task robot)."""

    type: Literal["scripted_pick_place"] = "scripted_pick_place"
    hand: Literal["left", "right"] = "right"
    rate_hz: Annotated[float, Field(gt=0, le=1000)] = 100.0
    #: Where the hand starts and ends [m], operator frame.
    home: Vec3 = (0.40, 0.0, 1.10)
    seed: Annotated[int, Field(ge=0, le=2**31 - 1)] = 0
    #: Speed factor on every motion (pauses excluded).
    pace: Annotated[float, Field(gt=0.1, le=5)] = 1.0

    def build(self) -> ScriptedPickPlace:
        from telerig.devices.pick_place.operator import ScriptedPickPlace

        return ScriptedPickPlace(
            self.id,
            robot=self.robot,
            frame=self.frame(),
            home=self.home,
            seed=self.seed,
            rate_hz=self.rate_hz,
            hand=self.hand,
            pace=self.pace,
        )


@DEVICES.register
class RetargetedReplayConfig(_TaskOperatorConfig):
    """Replays a recorded operator's controller stream bent toward this episode's cube."""

    type: Literal["replay_retargeted"] = "replay_retargeted"
    #: The demonstration's ``episode.mcap``.
    path: Path
    #: The controller stream in it, ``telerig/v1/<rig>/<device>/<part>``.
    topic: Annotated[str, Field(pattern=r"^telerig/v1/[A-Za-z0-9_.\-]+/[A-Za-z0-9_.\-]+/[A-Za-z0-9_.\-]+$")]

    def build(self) -> RetargetedReplay:
        from telerig.devices.pick_place.replay import RetargetedReplay

        return RetargetedReplay(self.path, topic=self.topic, robot=self.robot, frame=self.frame(), id=self.id)
