"""A scripted VR operator that solves the pick-and-place task from the cube's observed pose.

It watches ``<robot>/object_pose`` (the cube and the target zone, world frame), waits until the
cube is seen at rest, then plans a pick-and-place in its own operator frame with a human's
variation drawn from the episode's seed: overall pace, a reaction pause, an approach that lands
off the cube and is corrected after a look, a wrong wrist yaw corrected in the same pause, an
occasional pause mid-transfer, a placing error inside the zone and a slight sway of the hand. The
controller state goes out on the ordinary VR-controller path (``ControllerState`` with the
trigger closing the gripper), so it drives the same binding, retargeting and safety chain as a
person with a headset.

Frames: the operator frame as in :mod:`telerig.devices.scripted`; the binding's alignment maps it
onto the robot base (``p_robot = R s (p_op - o_op) + o_robot``), and the robot base sits at
``robot_base`` in the world with its axes along the world's. The plan inverts both.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from telerig.devices.base import SampleSink
from telerig.devices.scripted import POINTING_DOWN
from telerig.devices.worker import DeviceWorker, FixedRate
from telerig.errors import ConfigError
from telerig.ir.frames import quat_conjugate, quat_multiply, quat_normalize, quat_rotate
from telerig.ir.types import ControllerState, FloatArray, Handedness, Pose, Sample, Stamp, now_ns

__all__ = [
    "OBJECT_POSE",
    "OperatorFrame",
    "PickPlacePlan",
    "ScriptedPickPlace",
    "Waypoint",
    "plan_pick_place",
]

_log = logging.getLogger(__name__)

#: The robot stream the operator watches (``telerig.bus.catalogue.OBJECT_POSE``; devices sit below
#: the bus layer's users, so the name is repeated here).
OBJECT_POSE = "object_pose"
#: How long the cube must be seen at rest before planning [s], and how still [m].
_SETTLE_S = 0.1
_SETTLE_M = 0.001


def _min_jerk(u: float) -> float:
    u = 0.0 if u < 0.0 else 1.0 if u > 1.0 else u
    return u * u * u * (10.0 + u * (-15.0 + 6.0 * u))


def _yaw_quat(yaw: float) -> FloatArray:
    return np.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])


def quat_yaw(q: FloatArray) -> float:
    """Yaw [rad] about z of a rotation (w, x, y, z) (the heading of its x axis)."""
    x = quat_rotate(np.asarray(q, dtype=np.float64), np.array([1.0, 0.0, 0.0]))
    return math.atan2(float(x[1]), float(x[0]))


def grasp_yaw(cube_yaw: float) -> float:
    """The gripper yaw [rad] in [-pi/4, pi/4) that grasps a cube of this yaw across two faces."""
    quarter = math.pi / 2
    return (cube_yaw + quarter / 2) % quarter - quarter / 2


@dataclass(frozen=True, slots=True)
class OperatorFrame:
    """Where the operator frame lies: the binding's alignment and the robot base in the world.

    Attributes:
        rotation: Operator → robot base rotation (w, x, y, z). Shape (4,).
        operator_origin: Operator point mapped onto ``robot_origin`` [m]. Shape (3,).
        robot_origin: Robot-base point [m]. Shape (3,).
        scale: Human-to-robot motion scale.
        robot_base: World position of the robot base [m] (axes along the world's). Shape (3,).
    """

    rotation: FloatArray
    operator_origin: FloatArray
    robot_origin: FloatArray
    scale: float
    robot_base: FloatArray

    def to_operator(self, world: FloatArray) -> FloatArray:
        """A world point [m] in the operator frame. Shape (3,)."""
        base = np.asarray(world, dtype=np.float64) - self.robot_base
        local = quat_rotate(quat_conjugate(self.rotation), base - self.robot_origin) / self.scale
        return np.asarray(self.operator_origin + local, dtype=np.float64)

    def orientation(self, world_yaw: float) -> FloatArray:
        """Controller orientation (operator frame) that points the gripper down at ``world_yaw``."""
        robot = quat_multiply(_yaw_quat(world_yaw), np.array(POINTING_DOWN))
        return quat_normalize(quat_multiply(quat_conjugate(self.rotation), robot))


@dataclass(frozen=True, slots=True)
class Waypoint:
    """The hand at the end of one motion: reached at ``t_s`` [s] after the plan starts.

    Attributes:
        phase: What the motion is, e.g. ``approach``, ``look``, ``correct``, ``grasp``.
        t_s: Arrival time [s].
        position: Controller position [m], operator frame. Shape (3,).
        yaw: Gripper yaw [rad] in the world.
        trigger: Trigger value in [0, 1] (1 closes the gripper).
    """

    phase: str
    t_s: float
    position: FloatArray
    yaw: float
    trigger: float


@dataclass(frozen=True, slots=True)
class PickPlacePlan:
    """A planned pick-and-place: waypoints joined by minimum-jerk motions, plus a slight tremor.

    Attributes:
        seed: The episode seed it was drawn from.
        waypoints: In time order; the first is the start (``t_s`` 0).
        tremor: Per axis: amplitude [m], frequency [Hz] and phase [rad] of the hand's slight sway
            (0.1-0.4 mm at 1-3 Hz), faded out over the plan's last second. (3, 3).
        style: The drawn variation (pace, pauses, errors), for logs and tests.
    """

    seed: int
    waypoints: tuple[Waypoint, ...]
    tremor: FloatArray
    style: dict[str, float]

    @property
    def duration_s(self) -> float:
        """Time until the hand rests at home again [s]."""
        return self.waypoints[-1].t_s

    def at(self, t_s: float) -> tuple[FloatArray, float, float]:
        """Controller position [m], gripper yaw [rad] and trigger at ``t_s`` [s] into the plan."""
        wps = self.waypoints
        if t_s <= 0.0:
            prev = nxt = wps[0]
            s = 0.0
        elif t_s >= wps[-1].t_s:
            prev = nxt = wps[-1]
            s = 0.0
        else:
            i = next(k for k in range(1, len(wps)) if wps[k].t_s > t_s)
            prev, nxt = wps[i - 1], wps[i]
            s = _min_jerk((t_s - prev.t_s) / max(nxt.t_s - prev.t_s, 1e-9))
        position = prev.position + s * (nxt.position - prev.position)
        amp, freq, phase = self.tremor
        # The sway fades over the last second: at rest the hand is still (the task's "robot still").
        fade = min(1.0, max(0.0, self.duration_s - t_s))
        position = position + fade * amp * np.sin(2 * math.pi * freq * max(t_s, 0.0) + phase)
        return position, prev.yaw + s * (nxt.yaw - prev.yaw), prev.trigger + s * (nxt.trigger - prev.trigger)


def plan_pick_place(
    seed: int,
    frame: OperatorFrame,
    home: FloatArray,
    cube: FloatArray,
    cube_yaw: float,
    target: FloatArray,
    *,
    pace: float = 1.0,
) -> PickPlacePlan:
    """Plan one pick-and-place from the observed cube and target (world frame) with a human's
    variation drawn from ``seed`` alone (the same seed and poses give the same plan).

    Args:
        seed: Episode seed.
        frame: Operator frame.
        home: Start and end of the hand [m], operator frame. Shape (3,).
        cube: Cube centre [m], world frame (the grasp point). Shape (3,).
        cube_yaw: Cube yaw about the vertical [rad].
        target: Target zone centre [m], world frame (its surface). Shape (3,).
        pace: Speed factor on every motion (> 0; 2 is twice as fast).
    """
    if not (math.isfinite(pace) and pace > 0.0):
        raise ConfigError(f"pace must be a finite factor > 0, got {pace}")
    rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence([seed, 0x0B5E])))
    speed = float(rng.uniform(0.8, 1.25)) * pace
    react = float(rng.uniform(0.3, 0.9))
    lift = float(rng.uniform(0.08, 0.13))
    miss = np.clip(rng.normal(0.0, 0.012, 2), -0.025, 0.025)  # where the approach lands [m]
    residual = np.clip(rng.normal(0.0, 0.002, 2), -0.004, 0.004)  # what the correction leaves
    yaw_error = float(np.clip(rng.normal(0.0, 0.12), -0.25, 0.25))  # [rad]
    look = float(rng.uniform(0.2, 0.5))
    hold = float(rng.uniform(0.25, 0.5))
    pause_mid = float(rng.uniform(0.3, 0.8)) if rng.uniform() < 0.3 else 0.0
    place_error = np.clip(rng.normal(0.0, 0.008, 2), -0.015, 0.015)
    tremor = np.stack(
        [rng.uniform(0.0001, 0.0004, 3), rng.uniform(1.0, 3.0, 3), rng.uniform(0.0, 2 * math.pi, 3)]
    )

    home = np.asarray(home, dtype=np.float64)
    grasp_w = np.asarray(cube, dtype=np.float64)
    yaw = grasp_yaw(cube_yaw)
    # Where the hand would put the cube's centre: over the zone, at the height it was picked at.
    place_w = np.array([target[0] + place_error[0], target[1] + place_error[1], grasp_w[2] + 0.003])
    up = np.array([0.0, 0.0, lift])
    hover = np.array([0.0, 0.0, 0.025])
    op = frame.to_operator
    miss3 = np.array([miss[0], miss[1], 0.0])
    res3 = np.array([residual[0], residual[1], 0.0])
    moves: list[tuple[str, float, FloatArray, float, float]] = [
        # (phase, duration at speed 1 [s], world point or operator home, yaw, trigger)
        ("react", react, home, 0.0, 0.0),
        ("approach", 1.6, op(grasp_w + up + miss3), yaw + yaw_error, 0.0),
        ("descend", 0.8, op(grasp_w + hover + miss3), yaw + yaw_error, 0.0),
        ("look", look, op(grasp_w + hover + miss3), yaw + yaw_error, 0.0),
        ("correct", 0.6, op(grasp_w + hover + res3), yaw, 0.0),
        ("descend", 0.7, op(grasp_w + res3), yaw, 0.0),
        ("grasp", 0.4, op(grasp_w + res3), yaw, 1.0),
        ("hold", hold, op(grasp_w + res3), yaw, 1.0),
        ("lift", 0.9, op(grasp_w + res3 + up), yaw, 1.0),
    ]
    if pause_mid:
        mid = (grasp_w + place_w) / 2 + up
        moves += [("transfer", 0.8, op(mid), yaw, 1.0), ("pause", pause_mid, op(mid), yaw, 1.0)]
        moves.append(("transfer", 0.8, op(place_w + up), 0.0, 1.0))
    else:
        moves.append(("transfer", 1.6, op(place_w + up), 0.0, 1.0))
    moves += [
        ("lower", 0.9, op(place_w), 0.0, 1.0),
        ("release", 0.4, op(place_w), 0.0, 0.0),
        ("settle", 0.3, op(place_w), 0.0, 0.0),
        ("retreat", 0.7, op(place_w + up), 0.0, 0.0),
        ("return", 1.4, home, 0.0, 0.0),
    ]
    waypoints = [Waypoint("start", 0.0, home.copy(), 0.0, 0.0)]
    t = 0.0
    for phase, duration, point, wp_yaw, trigger in moves:
        # Pauses are the operator's own; only motions speed up or slow down with the pace.
        t += duration if phase in ("react", "look", "hold", "pause") else duration / speed
        waypoints.append(Waypoint(phase, t, np.asarray(point, dtype=np.float64), wp_yaw, trigger))
    style = {
        "speed": speed,
        "react_s": react,
        "lift_m": lift,
        "miss_m": float(np.hypot(*miss)),
        "yaw_error_rad": yaw_error,
        "pause_mid_s": pause_mid,
        "place_error_m": float(np.hypot(*place_error)),
    }
    return PickPlacePlan(seed, tuple(waypoints), tremor, style)


class ScriptedPickPlace:
    """The scripted operator as a device: holds still at home until the cube is seen at rest on
    ``<robot>/object_pose``, then plays :func:`plan_pick_place` for the episode's seed and rests
    at home until stopped.

    Episode ``k`` (the k-th :meth:`start`, from 0) uses seed ``seed + k``, as the task robot does,
    so one seed fixes both the scene and the operator's variation.
    """

    def __init__(
        self,
        id: str,
        *,
        robot: str,
        frame: OperatorFrame,
        home: Sequence[float] = (0.40, 0.0, 1.10),
        seed: int = 0,
        rate_hz: float = 100.0,
        hand: Handedness = "right",
        pace: float = 1.0,
        cube: str = "cube",
        target: str = "target",
    ) -> None:
        if not (math.isfinite(rate_hz) and 0.0 < rate_hz <= 2000.0):
            raise ConfigError(f"rate_hz must be in (0, 2000], got {rate_hz}")
        if seed < 0:
            raise ConfigError(f"seed must be >= 0, got {seed}")
        self._id = id
        self.robot = robot
        self.frame = frame
        self.home = np.array(home, dtype=np.float64)
        if self.home.shape != (3,) or not np.all(np.isfinite(self.home)):
            raise ConfigError(f"home must be three finite coordinates [m], got {home!r}")
        self.seed = seed
        self.rate_hz = float(rate_hz)
        self.hand: Handedness = hand
        self.pace = pace
        self._cube = f"{robot}/{cube}"
        self._target = f"{robot}/{target}"
        self.source_id = f"{id}/{hand}"
        self._worker = DeviceWorker(id, kind="scripted operator", thread_name=f"telerig-pick-{id}", log=_log)
        self._lock = threading.Lock()
        self._seen: dict[str, tuple[float, Pose]] = {}  # source → (monotonic time seen, pose)
        self._settled_since: float | None = None
        self._watch_from = math.inf
        #: Starts so far (the next episode's index).
        self.episodes = 0
        #: The plan of the running or latest episode (None before the cube was seen).
        self.plan: PickPlacePlan | None = None
        #: Observed samples ignored: not a world-frame pose of the cube or target, or not finite.
        self.ignored = 0

    @property
    def id(self) -> str:
        return self._id

    @property
    def running(self) -> bool:
        return self._worker.running

    @property
    def observes(self) -> tuple[tuple[str, str], ...]:
        return ((self.robot, OBJECT_POSE),)

    def observe(self, sample: Sample) -> None:
        """Keep the latest world-frame pose of the cube and target (bus thread; never blocks long)."""
        source = sample.stamp.source_id
        if not (
            isinstance(sample, Pose)
            and sample.frame_id == "world"
            and source in (self._cube, self._target)
            and np.all(np.isfinite(sample.position))
            and np.all(np.isfinite(sample.orientation))
            and float(np.abs(sample.position).max()) < 100.0
        ):
            self.ignored += 1
            return
        now = time.monotonic()
        with self._lock:
            if now < self._watch_from:
                return  # seen before this episode's start: the scene may not be reset yet
            previous = self._seen.get(source)
            self._seen[source] = (now, sample)
            if source != self._cube:
                return
            moved = (
                previous is None or float(np.abs(previous[1].position - sample.position).max()) > _SETTLE_M
            )
            if moved:
                self._settled_since = now

    def start(self, sink: SampleSink) -> None:
        """Begin the next episode: hold at home until the cube is seen at rest, then play the plan."""
        seed = self.seed + self.episodes
        self.episodes += 1
        with self._lock:
            self._seen.clear()
            self._settled_since = None
            self._watch_from = time.monotonic()
        self.plan = None
        self._worker.start(self._run, sink, seed)

    def stop(self) -> None:
        self._worker.stop()
        with self._lock:
            self._watch_from = math.inf

    def _ready(self, seed: int) -> PickPlacePlan | None:
        with self._lock:
            cube = self._seen.get(self._cube)
            target = self._seen.get(self._target)
            since = self._settled_since
        if cube is None or target is None or since is None or time.monotonic() - since < _SETTLE_S:
            return None
        pose = cube[1]
        return plan_pick_place(
            seed,
            self.frame,
            self.home,
            pose.position,
            quat_yaw(pose.orientation),
            target[1].position,
            pace=self.pace,
        )

    def _run(self, sink: SampleSink, seed: int, stop: threading.Event) -> None:
        rate = FixedRate(self.rate_hz)
        t_plan: float | None = None
        for seq, (device_ns, t) in enumerate(rate.ticks(stop)):
            plan = self.plan
            if plan is None:
                plan = self._ready(seed)
                if plan is not None:
                    self.plan, t_plan = plan, t
                    _log.info(
                        "%s: episode seed %d, plan %.1f s, style %s",
                        self._id,
                        seed,
                        plan.duration_s,
                        plan.style,
                    )
            if plan is None or t_plan is None:
                position, yaw, trigger = self.home, 0.0, 0.0
            else:
                position, yaw, trigger = plan.at(t - t_plan)
            stamp = Stamp(self.source_id, seq, device_ns, now_ns())
            self._worker.deliver(sink, self.state(stamp, position, yaw, trigger))

    def state(self, stamp: Stamp, position: FloatArray, yaw: float, trigger: float) -> ControllerState:
        """The controller sample for a hand at ``position`` with the gripper at ``yaw``."""
        return ControllerState(
            stamp=stamp,
            hand=self.hand,
            position=np.asarray(position, dtype=np.float64),
            orientation=self.frame.orientation(yaw),
            frame_id="operator",
            buttons=frozenset(),
            trigger=float(min(1.0, max(0.0, trigger))),
            grip=1.0,
            joystick=np.zeros(2),
        )
