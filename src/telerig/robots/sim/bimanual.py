"""MuJoCo bimanual station: two arms with grippers facing across a table, a cup of balls and a bowl."""

from __future__ import annotations

import contextlib
import threading
import weakref
from dataclasses import dataclass
from types import TracebackType

import mujoco

from telerig.errors import RobotError
from telerig.robots.models.arm import ArmScene, arm_scene, load_arm
from telerig.robots.models.arms import arm_model
from telerig.robots.models.mjcf import VISUAL_GROUPS, compile_spec, set_physics_options
from telerig.robots.sim import objects
from telerig.robots.sim.arm import MujocoArm, SimPhysics, SimStats
from telerig.robots.sim.scene import (
    TABLE_TOP,
    _actuate_arm,
    add_room,
    add_table,
)

__all__ = ["SIDES", "BimanualArm", "BimanualScene", "BimanualStation", "build_bimanual_scene"]

#: The two arms, in order; joint, actuator and camera names start with ``<side>_``.
SIDES = ("left", "right")
_TIMESTEP = 0.002  # [s]
_BASE_X = 0.55  # bases at x = -0.55 (left, facing +x) and +0.55 (right, facing -x) [m]
_TABLE_HALF = (0.75, 0.5)  # [m]
#: Cup of balls in front of the right arm (it pours), bowl in front of the left arm (it holds). [m]
_CUP_XY = (0.12, 0.15)
_BOWL_XY = (-0.12, -0.15)


@dataclass(frozen=True, slots=True)
class BimanualScene:
    """A compiled bimanual station.

    Attributes:
        model: The compiled MuJoCo model (world z up, table top at 0.8 m, table centre at the origin).
        arms: Per-arm scenes sharing ``model``, left then right; names prefixed ``left_`` / ``right_``.
        cameras: ``scene`` (overview) first, then ``left_wrist`` and ``right_wrist``.
        objects: Free bodies of the task set: ``cup``, ``bowl`` and the balls ``ball0``...
    """

    model: mujoco.MjModel
    arms: tuple[ArmScene, ArmScene]
    cameras: tuple[str, ...]
    objects: tuple[str, ...]
    visual_groups: tuple[int, ...] = VISUAL_GROUPS


def build_bimanual_scene(
    model: str = "ur5e_robotiq85", *, with_objects: bool = True, timestep: float = _TIMESTEP
) -> BimanualScene:
    """Build two arms facing each other across a 1.5 x 1.0 m table, a cup of 8 balls and a bowl.

    The left arm's base is at (-0.55, 0, 0.8) m facing +x, the right arm's at (0.55, 0, 0.8) m
    facing -x (world frame). Each arm's wrist camera (``<side>_wrist``) is robosuite's
    ``eye_in_hand``, looking out of the gripper.

    Args:
        model: Arm model of both arms (``ur5e_robotiq85``: 12 joints; ``panda``: 14).
        with_objects: Add the cup with balls (in front of the right arm) and the bowl (left arm).
        timestep: Physics timestep [s]; the servo gains are tuned for 0.002 s.

    Raises:
        ConfigError: no such arm model.
        DependencyError: robosuite (the model source) is not installed.
        RobotError: a model file is missing or does not compile.
    """
    if not 0 < timestep <= 0.01:
        raise ValueError(f"timestep must be in (0, 0.01] s for the arm servos to be stable, got {timestep}")
    arm = arm_model(model)
    spec = mujoco.MjSpec()
    spec.modelname = f"bimanual_{arm.name}"
    spec.compiler.degree = False
    set_physics_options(spec, timestep)
    add_room(spec)
    add_table(spec, (0.0, 0.0), _TABLE_HALF)
    for side, x, yaw_quat in (("left", -_BASE_X, [1, 0, 0, 0]), ("right", _BASE_X, [0, 0, 0, 1])):
        robot = load_arm(arm, kinematic=False)
        for camera in list(robot.cameras):
            if camera.name != "eye_in_hand":  # robosuite's robotview: the scene camera covers it
                robot.delete(camera)
        frame = spec.worldbody.add_frame(pos=[x, 0.0, TABLE_TOP], quat=yaw_quat)
        frame.attach_body(robot.body(arm.base_bodies[0]), f"{side}_", "")
        spec.camera(f"{side}_eye_in_hand").name = f"{side}_wrist"
        _actuate_arm(spec, arm, f"{side}_")
    bodies: tuple[str, ...] = ()
    if with_objects:
        cup = objects.add_cup(spec, "cup", (*_CUP_XY, TABLE_TOP))
        balls = objects.add_balls(spec, "ball", (*_CUP_XY, TABLE_TOP + 0.004))
        bowl = objects.add_bowl(spec, "bowl", (*_BOWL_XY, TABLE_TOP))
        bodies = (cup, bowl, *balls)
    # From the table's long side (-y), above: both arms, the cup and the bowl in view.
    spec.worldbody.add_camera(name="scene", pos=[0.0, -1.5, 1.75], xyaxes=[1, 0, 0, 0, 0.55, 0.83], fovy=50)
    compiled = compile_spec(spec)
    left, right = (arm_scene(compiled, arm, prefix=f"{s}_", objects=bodies) for s in SIDES)
    return BimanualScene(
        model=compiled, arms=(left, right), cameras=("scene", "left_wrist", "right_wrist"), objects=bodies
    )


class BimanualArm(MujocoArm):
    """One arm of a :class:`BimanualStation`: a RobotDriver of its joints and gripper, physics shared."""

    def __init__(self, station: BimanualStation, scene: ArmScene, *, name: str) -> None:
        super().__init__(scene, name=name, physics=station.physics)
        self._station = station

    @property
    def station(self) -> BimanualStation:
        """The station this arm belongs to."""
        return self._station

    def _rename(self, name: str) -> None:
        if name != self.name and self._link.connected:
            raise RobotError(f"{self.name}: cannot rename a connected arm to {name!r}; close it first")
        self._name = self._link.name = name


# Stations built by configs, by (key, model, timestep, realtime), so that the two arm configs of one
# station share it; weak, so a station goes when both its arms are gone.
_STATIONS: weakref.WeakValueDictionary[tuple[str, str, float, bool], BimanualStation] = (
    weakref.WeakValueDictionary()
)
_STATIONS_LOCK = threading.Lock()


class BimanualStation:
    """Two simulated arms in one physics: :attr:`left` and :attr:`right`, each a RobotDriver.

    Why two drivers and not one of 12-14 joints: :class:`~telerig.robots.base.RobotDriver` has one
    gripper per driver, and each arm has its own safety chain, e-stop (a fault on one arm may
    pause only that arm), IK and control loop. The physics is shared: it starts with the first
    arm connected and stops with the last one closed, and :meth:`locked` serves both arms' and
    the cameras' renders.
    """

    def __init__(
        self,
        scene: BimanualScene | None = None,
        *,
        name: str = "bimanual_sim",
        realtime: bool = True,
        max_catchup: int = 25,
    ) -> None:
        """Create the station (the physics starts when an arm connects).

        Args:
            scene: Scene to simulate; :func:`build_bimanual_scene` when None.
            name: Station name; the arms are ``<name>_left`` and ``<name>_right``.
            realtime: Step on a thread paced to the wall clock; False for :meth:`step`.
            max_catchup: Most steps the loop may run late before it drops the lag. >= 1.
        """
        self.scene = scene if scene is not None else build_bimanual_scene()
        self.physics = SimPhysics(self.scene.model, name=name, realtime=realtime, max_catchup=max_catchup)
        self.left = BimanualArm(self, self.scene.arms[0], name=f"{name}_left")
        self.right = BimanualArm(self, self.scene.arms[1], name=f"{name}_right")

    @classmethod
    def shared(
        cls, key: str, model: str = "ur5e_robotiq85", *, timestep: float = _TIMESTEP, realtime: bool = True
    ) -> BimanualStation:
        """The station called ``key`` of this process, built on first use (how rig configs share one)."""
        with _STATIONS_LOCK:
            station = _STATIONS.get((key, model, timestep, realtime))
            # A closed arm cannot connect again: a station an earlier rig closed, still alive
            # through a lingering reference, is replaced (the full suite hit "driver is closed").
            if station is None or station.closed:
                scene = build_bimanual_scene(model, timestep=timestep)
                station = cls(scene, name=key, realtime=realtime)
                _STATIONS[(key, model, timestep, realtime)] = station
            return station

    @property
    def closed(self) -> bool:
        """Whether an arm of this station was closed (its physics cannot start again)."""
        return self.left._link.closed or self.right._link.closed

    def arm(self, side: str, *, name: str | None = None) -> BimanualArm:
        """The ``left`` or ``right`` arm.

        Args:
            side: ``"left"`` or ``"right"``.
            name: New driver name of the arm (the stamps' ``source_id``): a rig names it by its
                robot id. None keeps ``<station>_<side>``.

        Raises:
            RobotError: renaming an arm that is connected.
        """
        if side not in SIDES:
            raise ValueError(f"side must be one of {', '.join(SIDES)}, got {side!r}")
        arm = self.left if side == "left" else self.right
        if name is not None:
            arm._rename(name)
        return arm

    def connect(self) -> None:
        """Connect both arms (home, grippers open) and start the physics. Idempotent."""
        self.left.connect()
        self.right.connect()

    def close(self) -> None:
        """Close both arms and stop the physics. Idempotent."""
        self.left.close()
        self.right.close()

    def step(self, n: int = 1) -> None:
        """Advance the physics by ``n`` timesteps (``realtime=False`` only)."""
        self.left.step(n)

    def reset_objects(self) -> None:
        """Put the cup, balls and bowl back at their initial poses, at rest; the arms are not touched."""
        self.physics.reset_objects()

    def locked(self) -> contextlib.AbstractContextManager[tuple[mujoco.MjModel, mujoco.MjData]]:
        """Hold the physics lock and yield ``(model, data)``; keep the block short."""
        return self.physics.locked()

    def stats(self) -> SimStats:
        """Physics-loop statistics."""
        return self.physics.stats()

    def __enter__(self) -> BimanualStation:
        self.connect()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()
