"""Randomized pick-and-place in the arm scene: a cube drawn per episode from a seed, a target zone,
and success judged from the scene state (cube resting in the zone, gripper open, arm still).

The task is the demo scene (UR5e + Robotiq 2F-85 on a table) with a square target zone marked on
the table. Episode ``k`` of a run uses seed ``seed + k``: the cube's position and yaw come from
:func:`draw_cube` on that seed alone, so the same seed gives the same scene on any host. The
driver publishes the cube's and the zone's poses (``object_pose``), which is what a scripted
operator plans from, and the runtime asks :meth:`MujocoPickPlace.check_task` for the outcome.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import mujoco
import numpy as np

from telerig.errors import ConfigError, RobotError
from telerig.ir.types import FloatArray, Pose, Stamp
from telerig.robots.base import TaskCheck
from telerig.robots.sim.arm import MujocoArm
from telerig.robots.sim.scene import TABLE_TOP, build_arm_scene

__all__ = [
    "CUBE_HALF",
    "CubeDraw",
    "MujocoPickPlace",
    "PickPlaceSpec",
    "SceneState",
    "draw_cube",
    "judge",
    "yaw_quat",
]

#: Half edge of the scene's cube [m] (``objects.add_cube`` default).
CUBE_HALF = 0.02
_MAX_DRAWS = 1000


@dataclass(frozen=True, slots=True)
class PickPlaceSpec:
    """Where the cube may start, where it must go, and what counts as done.

    Attributes:
        cube_x: Range of the cube centre's x [m], world frame (the robot base is at x = y = 0).
        cube_y: Range of the cube centre's y [m], world frame.
        cube_yaw: Largest yaw of the cube about the vertical [rad], drawn in ``[-cube_yaw, cube_yaw]``.
        target: Centre (x, y) of the square target zone [m], world frame.
        target_half: Half edge of the target zone [m]; the cube's centre must lie inside.
        clearance: Smallest distance [m] between a drawn cube centre and the zone's edge, so no
            episode starts solved or with the cube on the zone's border.
        min_opening: Gripper opening (0 closed, 1 open) at or above which it counts as open.
        still_rad_s: Largest arm joint speed [rad/s] at which the arm counts as still.
        rest_height: Largest height [m] of the cube's centre above its resting height on the table
            at which it counts as put down (not held or balanced on the fingers).
    """

    cube_x: tuple[float, float] = (0.44, 0.58)
    cube_y: tuple[float, float] = (0.04, 0.20)
    cube_yaw: float = 0.4
    target: tuple[float, float] = (0.46, -0.15)
    target_half: float = 0.05
    clearance: float = 0.04
    min_opening: float = 0.8
    still_rad_s: float = 0.05
    rest_height: float = 0.01

    def __post_init__(self) -> None:
        for name in ("cube_x", "cube_y"):
            lo, hi = getattr(self, name)
            if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
                raise ConfigError(f"{name} must be a finite range [low, high] in metres, got {(lo, hi)}")
        if not 0.0 <= self.cube_yaw <= math.pi / 4:
            raise ConfigError(f"cube_yaw must be in [0, pi/4] rad (a square cube), got {self.cube_yaw}")
        if not 0.0 < self.target_half <= 0.5:
            raise ConfigError(f"target_half must be in (0, 0.5] m, got {self.target_half}")
        # The corner of the region farthest from the zone must be outside it by the clearance.
        far = max(_zone_distance(self, np.array([x, y])) for x in self.cube_x for y in self.cube_y)
        if far < self.clearance:
            raise ConfigError(
                f"the cube region x {self.cube_x}, y {self.cube_y} lies inside the target zone "
                f"(centre {self.target}, half {self.target_half} m): move the zone or the region apart"
            )


@dataclass(frozen=True, slots=True)
class CubeDraw:
    """The cube's start for one episode: centre x, y [m] in the world frame and yaw [rad]."""

    seed: int
    x: float
    y: float
    yaw: float

    @property
    def position(self) -> FloatArray:
        """Cube centre [m], world frame, resting on the table. Shape (3,)."""
        return np.array([self.x, self.y, TABLE_TOP + CUBE_HALF])

    @property
    def orientation(self) -> FloatArray:
        """Cube orientation (w, x, y, z): the yaw about world z. Shape (4,)."""
        return yaw_quat(self.yaw)


def yaw_quat(yaw: float) -> FloatArray:
    """Quaternion (w, x, y, z) of a rotation by ``yaw`` [rad] about z."""
    return np.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])


def _zone_distance(spec: PickPlaceSpec, xy: FloatArray) -> float:
    """Distance [m] from ``xy`` to the target zone (0 inside), Chebyshev (the zone is square)."""
    d = np.abs(xy - np.asarray(spec.target)) - spec.target_half
    return float(max(0.0, d.max()))


def draw_cube(spec: PickPlaceSpec, seed: int) -> CubeDraw:
    """The cube's start for ``seed``: uniform in the region, uniform yaw, at least ``clearance``
    outside the target zone. Depends on ``seed`` and ``spec`` alone (PCG64), so it is the same on
    every host and numpy 2.x version.

    Raises:
        ConfigError: ``seed`` is negative, or no draw clears the zone in 1000 tries.
    """
    if seed < 0:
        raise ConfigError(f"task seed must be >= 0, got {seed}")
    rng = np.random.Generator(np.random.PCG64(seed))
    for _ in range(_MAX_DRAWS):
        x = float(rng.uniform(*spec.cube_x))
        y = float(rng.uniform(*spec.cube_y))
        yaw = float(rng.uniform(-spec.cube_yaw, spec.cube_yaw))
        if _zone_distance(spec, np.array([x, y])) >= spec.clearance:
            return CubeDraw(seed, x, y, yaw)
    raise ConfigError(f"seed {seed}: no cube position clears the target zone; widen the cube region")


@dataclass(frozen=True, slots=True)
class SceneState:
    """What the success check reads from the scene.

    Attributes:
        cube_position: Cube centre [m], world frame. Shape (3,).
        gripper_opening: Measured opening, 0 closed, 1 open.
        joint_speeds: Arm joint speeds [rad/s]. Shape (n,).
    """

    cube_position: FloatArray
    gripper_opening: float
    joint_speeds: FloatArray


def judge(spec: PickPlaceSpec, state: SceneState) -> TaskCheck:
    """Success: the cube's centre inside the target zone and resting on the table, the gripper open
    and the arm still. The reason names the first condition that fails, with its value."""
    cube = np.asarray(state.cube_position, dtype=np.float64)
    speeds = np.asarray(state.joint_speeds, dtype=np.float64)
    if cube.shape != (3,) or not np.all(np.isfinite(cube)):
        return TaskCheck(False, f"cube position is not finite: {cube}")
    offset = _zone_distance(spec, cube[:2])
    height = float(cube[2] - (TABLE_TOP + CUBE_HALF))
    speed = float(np.max(np.abs(speeds))) if speeds.size else 0.0
    if not np.all(np.isfinite(speeds)):
        speed = math.inf
    values = {
        "cube_offset_m": offset,
        "cube_height_m": height,
        "gripper_opening": float(state.gripper_opening),
        "joint_speed_rad_s": speed,
    }
    if offset > 0.0:
        return TaskCheck(False, f"cube {offset * 100:.1f} cm outside the target zone", values)
    if height > spec.rest_height:
        return TaskCheck(False, f"cube {height * 100:.1f} cm above the table (not put down)", values)
    if not state.gripper_opening >= spec.min_opening:
        return TaskCheck(
            False, f"gripper not open ({state.gripper_opening:.2f} < {spec.min_opening:.2f})", values
        )
    if not speed <= spec.still_rad_s:
        return TaskCheck(False, f"arm moving ({speed:.3f} rad/s > {spec.still_rad_s:.3f})", values)
    return TaskCheck(True, "ok", values)


class MujocoPickPlace(MujocoArm):
    """The simulated arm at the pick-and-place task: object poses on ``object_pose``, a cube
    placed per episode from a seed, and success from the scene (:class:`EpisodicTask`).

    Args:
        spec: The task's randomization and success thresholds.
        seed: Base seed (episode ``k`` of a run uses ``seed + k``).
        model: Arm model (``ur5e_robotiq85`` or ``panda``).
        timestep: Physics timestep [s].
        name: Driver name (the robot id).
        realtime: Step on a thread paced to the wall clock; False for :meth:`step`.
    """

    def __init__(
        self,
        spec: PickPlaceSpec,
        *,
        seed: int = 0,
        model: str = "ur5e_robotiq85",
        timestep: float = 0.002,
        name: str = "arm0",
        realtime: bool = True,
    ) -> None:
        if seed < 0:
            raise ConfigError(f"task seed must be >= 0, got {seed}")
        scene = build_arm_scene(
            model, timestep=timestep, target_zone=(spec.target[0], spec.target[1], spec.target_half)
        )
        super().__init__(scene, name=name, realtime=realtime)
        self.spec = spec
        self._seed = seed
        m = self.scene.model
        self._cube = m.body("cube").id
        self._cube_joint = m.joint("cube_free")
        self._target = m.body("target").id
        self._bodies = {"cube": self._cube, "target": self._target}
        self._object_seq = dict.fromkeys(self._bodies, 0)
        #: The latest draw (None before the first :meth:`begin_task`).
        self.draw: CubeDraw | None = None

    # -- ObjectSensor ---------------------------------------------------------------------------

    @property
    def observed_objects(self) -> tuple[str, ...]:
        return tuple(self._bodies)

    def read_object_pose(self, name: str) -> Pose:
        """World-frame pose of ``cube`` or ``target``, stamped like :meth:`read_state`; source
        id ``<robot>/<object>``.

        Raises:
            RobotError: unknown object or the driver is not connected.
        """
        body = self._bodies.get(name)
        if body is None:
            raise RobotError(f"{self.name}: no object {name!r}. Available: {', '.join(self._bodies)}")
        self._require_connected()
        with self.locked() as (_, data):
            position = data.xpos[body].copy()
            orientation = data.xquat[body].copy()
            device_ns = round(data.time * 1e9)
            capture_ns = self.physics.step_ns
            seq = self._object_seq[name]
            self._object_seq[name] = seq + 1
        stamp = Stamp(f"{self.name}/{name}", seq, device_ns=device_ns, capture_ns=capture_ns)
        return Pose(stamp, position, orientation, "world")

    # -- EpisodicTask ---------------------------------------------------------------------------

    @property
    def task_seed(self) -> int:
        return self._seed

    def begin_task(self, seed: int) -> Mapping[str, object]:
        """Put every object back, then the cube at the pose drawn from ``seed``, at rest."""
        draw = draw_cube(self.spec, seed)
        self.reset_objects()
        qadr, vadr = self._cube_joint.qposadr[0], self._cube_joint.dofadr[0]
        with self.locked() as (model, data):
            data.qpos[qadr : qadr + 3] = draw.position
            data.qpos[qadr + 3 : qadr + 7] = draw.orientation
            data.qvel[vadr : vadr + 6] = 0.0
            mujoco.mj_forward(model, data)
        self.draw = draw
        spec = self.spec
        return {
            "type": "pick_place",
            "seed": seed,
            "cube": {
                "position_m": [round(float(v), 6) for v in draw.position],
                "yaw_rad": round(draw.yaw, 6),
            },
            "target": {"center_m": list(spec.target), "half_m": spec.target_half},
        }

    def check_task(self) -> TaskCheck:
        return judge(self.spec, self.scene_state())

    def scene_state(self) -> SceneState:
        """Cube position, gripper opening and arm joint speeds now (no stream's sequence advances)."""
        self._require_connected()
        with self.locked() as (_, data):
            cube = data.xpos[self._cube].copy()
            opening = float(data.qpos[self._grip_qadr] @ self._grip_gain) - self._grip_offset
            speeds = data.qvel[self._vadr].copy()
        return SceneState(cube, min(1.0, max(0.0, opening)), speeds)
