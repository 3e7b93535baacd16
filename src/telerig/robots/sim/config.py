"""Configs of the simulated robots (registered by ``type``); light: MuJoCo is imported only by ``build``."""

from __future__ import annotations

from collections.abc import Mapping
from contextlib import AbstractContextManager, nullcontext
from typing import TYPE_CHECKING, Annotated, Any, ClassVar, Literal, Protocol, TypeVar

from pydantic import Field, model_validator

from telerig.config.schema import Identifier, RobotConfig
from telerig.registry import ROBOTS

if TYPE_CHECKING:
    from telerig.robots.sim.arm import MujocoArm, SimPhysics
    from telerig.robots.sim.bimanual import BimanualArm
    from telerig.robots.sim.gripper import MujocoGripper
    from telerig.robots.sim.hand import MujocoHand
    from telerig.robots.sim.humanoid import MujocoHumanoid
    from telerig.robots.sim.pick_place import MujocoPickPlace
    from telerig.robots.sim.tiago_driver import MujocoTiago

__all__ = [
    "MujocoArmConfig",
    "MujocoBimanualArmConfig",
    "MujocoGripperConfig",
    "MujocoHandConfig",
    "MujocoHumanoidConfig",
    "MujocoPickPlaceConfig",
    "MujocoTiagoConfig",
    "SimRobotConfig",
    "shipped_scenes",
]


class _Simulated(Protocol):
    @property
    def physics(self) -> SimPhysics: ...


_Driver = TypeVar("_Driver", bound=_Simulated)


class SimRobotConfig(RobotConfig):
    """Base of simulated robots: physics stepped headless in real time, commands at the control rate.

    A subclass lists the scenes it ships in :attr:`scenes`; :func:`shipped_scenes` builds their
    configs, and one parametrized test builds and steps every one of them.
    """

    #: The scenes this type ships, by scene name: the robot entries (``type`` and ``id`` left out)
    #: that together make the scene, e.g. ``{"panda": ({"model": "panda"},)}``. Several entries
    #: share one physics (the two arms of a bimanual bench).
    scenes: ClassVar[Mapping[str, tuple[Mapping[str, Any], ...]]] = {}

    physics_rate_hz: Annotated[float, Field(ge=100, le=10_000)] = 500.0
    control_rate_hz: Annotated[float, Field(gt=0, le=1000)] = 100.0
    #: How often the physics thread wakes [Hz]; each wake-up takes ``physics_rate_hz /
    #: physics_wake_hz`` steps. None: every step (the finest pacing). On a loaded VM a wake-up
    #: costs about a step's CPU; a rig of several simulated robots on a small host wakes at twice the
    #: control rate (the fleet rig), and the state a tick reads is then up to one wake period ahead
    #: of the wall clock. At least ``control_rate_hz``, and ``physics_rate_hz`` a whole multiple of it.
    #: Where it is a whole multiple of ``control_rate_hz`` the wakes keep to the middle between the
    #: control loop's state reads, so each tick reads new states. At the control rate itself a tick
    #: over half a period late reads the next wake's state and the recorded states have a gap of two
    #: periods; at twice the rate such a tick reads a state half a period off, and a gap takes more
    #: than a period's lateness.
    physics_wake_hz: Annotated[float, Field(gt=0, le=10_000)] | None = None
    #: ``True``: a thread steps the physics paced to the wall clock (what a rig runs). ``False``:
    #: the physics advances only through the driver's ``step(n)``, deterministic (tests, offline tools).
    realtime: bool = True

    #: Most faces a robot's drawn-only mesh keeps in the simulated cameras' model: None, the
    #: default (:data:`~telerig.robots.models.visual_meshes.VISUAL_MESH_FACES`, about half the CPU per
    #: camera frame, see benchmarks/render_cost.py); 0 keeps every face (full-detail renders).
    #: Physics is the same either way.
    visual_mesh_faces: Annotated[int, Field(ge=0, le=10_000_000)] | None = None

    def control_rate(self) -> float:
        return self.control_rate_hz

    def _visual_meshes(self) -> AbstractContextManager[None]:
        """The mesh budget the scene compiles under (``visual_meshes.visual_mesh_budget``)."""
        if self.visual_mesh_faces is None:
            return nullcontext()
        from telerig.robots.models.visual_meshes import visual_mesh_budget

        return visual_mesh_budget(self.visual_mesh_faces)

    @model_validator(mode="after")
    def _mesh_budget(self) -> SimRobotConfig:
        if self.visual_mesh_faces is not None and 0 < self.visual_mesh_faces < 4:
            faces = self.visual_mesh_faces
            raise ValueError(
                f"visual_mesh_faces must be 0 (every face) or at least 4, got {faces}; e.g. 1000"
            )
        return self

    @model_validator(mode="after")
    def _whole_multiple(self) -> SimRobotConfig:
        ratio = self.physics_rate_hz / self.control_rate_hz
        if ratio < 1 or abs(ratio - round(ratio)) > 1e-9:
            raise ValueError(
                f"physics_rate_hz ({self.physics_rate_hz:g}) must be a whole multiple of control_rate_hz "
                f"({self.control_rate_hz:g}), e.g. 500 and 100"
            )
        wake = self.physics_wake_hz
        if wake is not None:
            steps = self.physics_rate_hz / wake
            if wake < self.control_rate_hz or abs(steps - round(steps)) > 1e-9:
                raise ValueError(
                    f"physics_wake_hz ({wake:g}) must be at least control_rate_hz ({self.control_rate_hz:g}) "
                    f"and divide physics_rate_hz ({self.physics_rate_hz:g}) into whole steps, e.g. "
                    f"{self.control_rate_hz:g}"
                )
        return self

    def _paced(self, driver: _Driver) -> _Driver:
        """``driver`` with its physics waking at ``physics_wake_hz``, half a wake period away from
        the control loop's state reads where the control rate fits whole wake periods
        (:attr:`~telerig.robots.sim.arm.SimPhysics.wakes_between_reads`)."""
        wake = self.physics_wake_hz
        if wake is not None:
            physics = driver.physics
            physics.steps_per_wake = round(self.physics_rate_hz / wake)
            periods = wake / self.control_rate_hz
            physics.wakes_between_reads = abs(periods - round(periods)) <= 1e-9
        return driver


@ROBOTS.register
class MujocoArmConfig(SimRobotConfig):
    """A simulated arm with a gripper on a table."""

    type: Literal["mujoco_arm"] = "mujoco_arm"
    scenes: ClassVar[Mapping[str, tuple[Mapping[str, Any], ...]]] = {
        "ur5e_robotiq85": ({"model": "ur5e_robotiq85"},),
        "panda": ({"model": "panda"},),
    }
    #: Arm model (``telerig.robots.models.ARM_MODELS``): UR5e + Robotiq 2F-85 (6 DoF) or Panda (7 DoF).
    model: Literal["ur5e_robotiq85", "panda"] = "ur5e_robotiq85"

    def build(self) -> MujocoArm:
        from telerig.robots.sim.arm import MujocoArm
        from telerig.robots.sim.scene import build_arm_scene

        with self._visual_meshes():
            scene = build_arm_scene(self.model, timestep=1.0 / self.physics_rate_hz)
            return self._paced(MujocoArm(scene, name=self.id, realtime=self.realtime))


@ROBOTS.register
class MujocoPickPlaceConfig(SimRobotConfig):
    """The simulated arm at a randomized pick-and-place task (:mod:`telerig.robots.sim.pick_place`).

    Each episode the cube starts at a pose drawn from ``seed + k`` (episode ``k`` of a run; the
    seed and the pose go into the manifest), and the outcome is judged from the scene: cube resting
    in the target zone, gripper open, arm still. The cube's and the zone's poses are published on
    ``<robot>/object_pose``. Positions are in the world frame [m] (robot base at x = y = 0, on the
    0.8 m table), yaw about the vertical [rad].
    """

    type: Literal["mujoco_pick_place"] = "mujoco_pick_place"
    scenes: ClassVar[Mapping[str, tuple[Mapping[str, Any], ...]]] = {"ur5e_pick_place": ({},)}
    model: Literal["ur5e_robotiq85", "panda"] = "ur5e_robotiq85"
    #: Base seed: episode k of a run (``telerig collect``/``eval``) uses ``seed + k``.
    seed: Annotated[int, Field(ge=0, le=2**31 - 1)] = 0
    cube_x: tuple[float, float] = (0.44, 0.58)
    cube_y: tuple[float, float] = (0.04, 0.20)
    cube_yaw_rad: Annotated[float, Field(ge=0, le=0.785)] = 0.4
    target: tuple[float, float] = (0.46, -0.15)
    target_half_m: Annotated[float, Field(gt=0, le=0.5)] = 0.05
    clearance_m: Annotated[float, Field(ge=0, le=0.5)] = 0.04
    #: Gripper opening (0 closed, 1 open) from which the gripper counts as open.
    min_opening: Annotated[float, Field(ge=0, le=1)] = 0.8
    #: Largest arm joint speed [rad/s] at which the arm counts as still.
    still_rad_s: Annotated[float, Field(gt=0, le=10)] = 0.05

    @model_validator(mode="after")
    def _task_fits(self) -> MujocoPickPlaceConfig:
        from telerig.errors import ConfigError

        try:
            self.spec()
        except ConfigError as exc:
            raise ValueError(str(exc)) from None
        return self

    def spec(self) -> Any:
        """The task's :class:`~telerig.robots.sim.pick_place.PickPlaceSpec`."""
        from telerig.robots.sim.pick_place import PickPlaceSpec

        return PickPlaceSpec(
            cube_x=self.cube_x,
            cube_y=self.cube_y,
            cube_yaw=self.cube_yaw_rad,
            target=self.target,
            target_half=self.target_half_m,
            clearance=self.clearance_m,
            min_opening=self.min_opening,
            still_rad_s=self.still_rad_s,
        )

    def build(self) -> MujocoPickPlace:
        from telerig.robots.sim.pick_place import MujocoPickPlace

        with self._visual_meshes():
            return self._paced(
                MujocoPickPlace(
                    self.spec(),
                    seed=self.seed,
                    model=self.model,
                    timestep=1.0 / self.physics_rate_hz,
                    name=self.id,
                    realtime=self.realtime,
                )
            )


@ROBOTS.register
class MujocoGripperConfig(SimRobotConfig):
    """A simulated Robotiq 2F-85 alone on a fixed mount over a table (1 DoF)."""

    type: Literal["mujoco_gripper"] = "mujoco_gripper"
    scenes: ClassVar[Mapping[str, tuple[Mapping[str, Any], ...]]] = {"robotiq_2f85_bench": ({},)}

    def build(self) -> MujocoGripper:
        from telerig.robots.sim.gripper import MujocoGripper, build_gripper_scene

        with self._visual_meshes():
            scene = build_gripper_scene(timestep=1.0 / self.physics_rate_hz)
            return self._paced(MujocoGripper(scene, name=self.id, realtime=self.realtime))


@ROBOTS.register
class MujocoBimanualArmConfig(SimRobotConfig):
    """One arm of a simulated bimanual station; the two arm configs naming one ``bench`` share its physics.

    A rig lists both arms, e.g. ``{id: left, type: mujoco_bimanual_arm, bench: pour, side: left}``
    and the same with ``side: right``; their joints are named ``left_...`` and ``right_...``.
    """

    type: Literal["mujoco_bimanual_arm"] = "mujoco_bimanual_arm"
    scenes: ClassVar[Mapping[str, tuple[Mapping[str, Any], ...]]] = {
        f"bimanual_{model}": tuple(
            {"bench": f"bimanual_{model}", "side": side, "model": model} for side in ("left", "right")
        )
        for model in ("ur5e_robotiq85", "panda")
    }
    #: The shared scene (table, cup, bowl, cameras) both arms of a station stand at.
    bench: Identifier = "bench0"
    side: Literal["left", "right"]
    model: Literal["ur5e_robotiq85", "panda"] = "ur5e_robotiq85"

    def build(self) -> BimanualArm:
        from telerig.robots.sim.bimanual import BimanualStation

        with self._visual_meshes():
            station = BimanualStation.shared(
                self.bench, self.model, timestep=1.0 / self.physics_rate_hz, realtime=self.realtime
            )
            return self._paced(station.arm(self.side, name=self.id))


@ROBOTS.register
class MujocoHumanoidConfig(SimRobotConfig):
    """A simulated Unitree G1 at a table, upper body (waist + arms) teleoperated, MuJoCo, headless.

    ``support``: ``fixed`` bolts the pelvis to a stand; ``harness`` keeps the floating base and holds
    the pelvis with a soft weld (it can sag and sway), the legs held at the stance by joint springs.
    """

    type: Literal["mujoco_humanoid"] = "mujoco_humanoid"
    scenes: ClassVar[Mapping[str, tuple[Mapping[str, Any], ...]]] = {"g1_humanoid": ({},)}
    model: Literal["g1"] = "g1"
    support: Literal["fixed", "harness"] = "fixed"

    def build(self) -> MujocoHumanoid:
        from telerig.robots.sim.humanoid import MujocoHumanoid, build_humanoid_scene

        with self._visual_meshes():
            scene = build_humanoid_scene(support=self.support, timestep=1.0 / self.physics_rate_hz)
            return self._paced(MujocoHumanoid(scene, name=self.id, realtime=self.realtime))


@ROBOTS.register
class MujocoTiagoConfig(SimRobotConfig):
    """A simulated TIAGo mobile manipulator (holonomic base, torso, arm, Robotiq 2F-85) at a table
    with a cup, MuJoCo, headless; ten commanded joints: base x, y, yaw, torso, six arm joints.

    Base pose targets become base velocity-servo commands (step feed-forward plus ``base_gain``
    times the position error [1/s]); ``send_base`` (``base_drive`` bindings) adds a base-frame velocity.
    """

    type: Literal["mujoco_tiago"] = "mujoco_tiago"
    scenes: ClassVar[Mapping[str, tuple[Mapping[str, Any], ...]]] = {"tiago": ({},)}
    model: Literal["tiago_robotiq85"] = "tiago_robotiq85"
    with_cup: bool = True
    #: At least 200 Hz: the TIAGo servos are tuned for a timestep of at most 5 ms.
    physics_rate_hz: Annotated[float, Field(ge=200, le=10_000)] = 500.0
    base_gain: Annotated[float, Field(gt=0, le=100)] = 5.0

    @model_validator(mode="after")
    def _stable_base_loop(self) -> MujocoTiagoConfig:
        if self.base_gain >= self.control_rate_hz:
            raise ValueError(
                f"base_gain ({self.base_gain:g} 1/s) must be below control_rate_hz ({self.control_rate_hz:g})"
                " for the sampled base loop to be stable, e.g. 5"
            )
        return self

    def build(self) -> MujocoTiago:
        from telerig.robots.sim.tiago import build_tiago_scene
        from telerig.robots.sim.tiago_driver import MujocoTiago

        with self._visual_meshes():
            scene = build_tiago_scene(with_cup=self.with_cup, timestep=1.0 / self.physics_rate_hz)
            return self._paced(
                MujocoTiago(
                    scene,
                    name=self.id,
                    control_period_s=1.0 / self.control_rate_hz,
                    base_gain=self.base_gain,
                    realtime=self.realtime,
                )
            )


@ROBOTS.register
class MujocoHandConfig(SimRobotConfig):
    """A simulated dexterous hand on a fixed wrist over a table with a can and a ball, MuJoCo, headless.

    Commanded joints are the hand's motors (Inspire and Ability: 6 each); the other joints follow
    through the hand's linkage couplings (mimic joints). ``send_gripper`` opens/closes every finger.
    """

    type: Literal["mujoco_hand"] = "mujoco_hand"
    scenes: ClassVar[Mapping[str, tuple[Mapping[str, Any], ...]]] = {
        f"{model}_hand_table": ({"model": model},) for model in ("inspire", "ability")
    }
    model: Literal["inspire", "ability"] = "inspire"
    handedness: Literal["left", "right"] = "right"
    with_objects: bool = True
    #: At least 250 Hz: the finger servos and mimic constraints are tuned for a timestep of at most 4 ms.
    physics_rate_hz: Annotated[float, Field(ge=250, le=10_000)] = 500.0

    def build(self) -> MujocoHand:
        from telerig.robots.sim.hand import MujocoHand, build_hand_scene

        with self._visual_meshes():
            scene = build_hand_scene(
                self.model,
                self.handedness,
                with_objects=self.with_objects,
                timestep=1.0 / self.physics_rate_hz,
            )
            return self._paced(MujocoHand(scene, name=self.id, realtime=self.realtime))


def shipped_scenes(*, realtime: bool = True) -> dict[str, list[SimRobotConfig]]:
    """Every scene of every registered simulated robot type, as the validated robot configs that
    build it (ids ``<scene>`` or, for several robots, ``<scene>_<i>``), by scene name.

    Args:
        realtime: The configs' ``realtime``; False for stepped drivers.
    """
    out: dict[str, list[SimRobotConfig]] = {}
    for name in ROBOTS.names():
        cls = ROBOTS.get(name)
        if not (isinstance(cls, type) and issubclass(cls, SimRobotConfig)):
            continue
        for scene, entries in cls.scenes.items():
            if scene in out:
                raise ValueError(f"sim scene {scene!r} is shipped twice (again by {name!r})")
            ids = [scene] if len(entries) == 1 else [f"{scene}_{i}" for i in range(len(entries))]
            out[scene] = [
                cls.model_validate({**entry, "type": name, "id": id_, "realtime": realtime})
                for id_, entry in zip(ids, entries, strict=True)
            ]
    return out
