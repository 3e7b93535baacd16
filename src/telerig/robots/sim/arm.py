"""MuJoCo-simulated arm driver (UR5e + Robotiq, Panda), stepping physics in real time on its own thread."""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from types import TracebackType

import mujoco
import numpy as np

from telerig.errors import RobotError
from telerig.ir.types import FloatArray, GripperCommand, JointCommand, JointState, Pose, Stamp, Wrench
from telerig.robots.base import JointLimits
from telerig.robots.models.arm import ArmScene
from telerig.robots.models.arms import UR5E_ROBOTIQ85
from telerig.robots.sim.scene import build_arm_scene

__all__ = [
    "UR5E_ACCELERATION_LIMIT",
    "UR5E_VELOCITY_LIMIT",
    "MujocoArm",
    "SimDriverLink",
    "SimPhysics",
    "SimStats",
    "between_reads",
]

#: UR5e joint speed limit [rad/s]: 180 deg/s for every joint (UR5e e-Series datasheet).
UR5E_VELOCITY_LIMIT = UR5E_ROBOTIQ85.velocity[0]
#: Joint acceleration limit [rad/s^2]. Universal Robots publishes none per joint; this is a
#: conservative teleoperation value, well above the URScript ``movej`` default of 1.4 rad/s^2.
UR5E_ACCELERATION_LIMIT = UR5E_ROBOTIQ85.acceleration[0]

_log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class SimStats:
    """Physics-loop statistics.

    Attributes:
        steps: Physics steps taken since the physics started.
        wakes: Times the real-time thread woke and stepped (``steps / wakes`` is its pacing).
        overruns: Wake-ups whose steps finished after their deadline (real-time mode only; one
            wake-up steps :attr:`SimPhysics.steps_per_wake` steps).
        resyncs: Times the loop fell more than the catch-up bound behind and dropped the lag.
        sim_time: Simulated time since start [s].
        wall_time: Wall-clock time since start [s].
        realtime_factor: ``sim_time / wall_time`` (1.0 = real time; 0 before any time passed).
    """

    steps: int
    wakes: int
    overruns: int
    resyncs: int
    sim_time: float
    wall_time: float
    realtime_factor: float


class SimPhysics:
    """One MuJoCo model and data, stepped in real time on a thread or by :meth:`step`; shared by drivers.

    Several drivers may command parts of one scene (the two arms of a bimanual station): each
    :meth:`attach` registers an initializer that puts its part at home, and :meth:`acquire` /
    :meth:`release` count the connected drivers. The first acquire resets the data, runs every
    initializer and starts the thread; the last release stops it. All access to the data goes
    through :attr:`lock`.

    The thread wakes every :attr:`steps_per_wake` timesteps and takes that many steps (the lock
    held per step, so a reader waits one step at most). One step per wake-up is the finest pacing;
    on a loaded virtual machine a wake-up costs about as much CPU as a step of a 6-DoF arm scene
    (``benchmarks/sim_physics.py``), and a rig of several simulated robots spends that on every one.

    A physics that wakes as often as its control loop reads the state (the fleet rig: both at
    100 Hz) would sample one clock with another: where a wake fell next to the reads, read jitter
    of a millisecond made one tick read the same state twice and the next skip one, and the
    recorded joint states had 20 ms holes (the 20-minute fleet soak: 1-836 per episode, each
    robot's share set by the chance phase between its wakes and its ticks). With
    :attr:`wakes_between_reads` on, each wake moves a quarter of the way toward the middle between
    two reads (:func:`between_reads`), so every read finds exactly one new state. Then a read over
    half a wake period late still skips one; a physics waking at twice the control rate (the fleet
    rig) turns that into a state half a control period off, not a 20 ms hole.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        *,
        name: str,
        realtime: bool = True,
        max_catchup: int = 25,
        steps_per_wake: int = 1,
    ) -> None:
        """Create the physics (nothing runs until :meth:`acquire`).

        Args:
            model: Compiled scene.
            name: Name of the physics thread and log lines.
            realtime: Step on a thread paced to the wall clock; False for :meth:`step`.
            max_catchup: Most steps the loop may run late before it drops the lag. >= 1.
            steps_per_wake: Steps the thread takes each time it wakes (see the class docs). >= 1.
        """
        if max_catchup < 1:
            raise ValueError(f"max_catchup must be >= 1, got {max_catchup}")
        self.model = model
        self.data = mujoco.MjData(model)
        self.lock = threading.Lock()
        self.realtime = realtime
        self._name = name
        self._max_catchup = max_catchup
        self._steps_per_wake = 1
        self.steps_per_wake = steps_per_wake
        self._init: list[Callable[[mujoco.MjData], None]] = []
        self._users = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.steps = 0
        self._wakes = 0
        self._overruns = 0
        self._resyncs = 0
        self.step_ns = 0  # wall time of the latest step [ns]
        self._start_ns = 0  # monotonic time at start [ns]
        #: Keep the wakes half a wake period away from the state reads (:func:`between_reads`); for
        #: a control loop reading at the wake rate or a whole fraction of it. A rig config sets it.
        self.wakes_between_reads = False
        self._read_ns = 0  # monotonic time of the latest state read (:meth:`read_stamp`) [ns]

    @property
    def running(self) -> bool:
        """Whether at least one driver is connected."""
        return self._users > 0

    @property
    def steps_per_wake(self) -> int:
        """Steps the real-time thread takes per wake-up; the state it leaves is up to that many
        timesteps ahead of the wall clock. Settable (a rig config sets it after building the driver)."""
        return self._steps_per_wake

    @steps_per_wake.setter
    def steps_per_wake(self, steps: int) -> None:
        if steps < 1:
            raise ValueError(f"steps_per_wake must be >= 1, got {steps}")
        self._steps_per_wake = steps

    def read_stamp(self) -> int:
        """The wall time of the latest step [ns], the ``capture_ns`` of a state read now (call it
        under :attr:`lock` with the read); notes when the read happened, for :attr:`wakes_between_reads`."""
        self._read_ns = time.monotonic_ns()
        return self.step_ns

    def attach(self, init: Callable[[mujoco.MjData], None]) -> None:
        """Register a driver's initializer, run (under the lock) when the physics starts."""
        self._init.append(init)

    def acquire(self) -> None:
        """Count one more connected driver; the first resets the scene and starts the physics."""
        with self.lock:
            self._users += 1
            if self._users > 1:
                return
            mujoco.mj_resetData(self.model, self.data)
            for init in self._init:
                init(self.data)
            mujoco.mj_forward(self.model, self.data)
            self.step_ns = time.time_ns()
            self._start_ns = time.monotonic_ns()
        if self.realtime:
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name=f"{self._name}-physics", daemon=True)
            self._thread.start()

    def release(self) -> None:
        """Count one driver less; the last one stops the physics thread."""
        with self.lock:
            self._users = max(0, self._users - 1)
            last = self._users == 0
        if not last:
            return
        self._stop.set()
        thread, self._thread = self._thread, None
        if thread is not None:
            thread.join()
            _log.info("%s: physics stopped (%s)", self._name, self.stats())

    def step(self, n: int = 1) -> None:
        """Advance by ``n`` steps of ``model.opt.timestep`` (``realtime=False`` only)."""
        if self.realtime:
            raise RobotError(f"{self._name}: step() needs realtime=False; the physics thread steps")
        with self.lock:
            for _ in range(n):
                mujoco.mj_step(self.model, self.data)
            self.steps += n
            self.step_ns = time.time_ns()

    def reset_objects(self) -> None:
        """Put every free-floating object back at its initial pose, at rest; robots are not touched."""
        model = self.model
        with self.lock:
            for j in range(model.njnt):
                if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:
                    qadr, vadr = model.jnt_qposadr[j], model.jnt_dofadr[j]
                    self.data.qpos[qadr : qadr + 7] = model.qpos0[qadr : qadr + 7]
                    self.data.qvel[vadr : vadr + 6] = 0.0
            mujoco.mj_forward(model, self.data)

    @contextmanager
    def locked(self) -> Iterator[tuple[mujoco.MjModel, mujoco.MjData]]:
        """Hold the lock and yield ``(model, data)``; keep the block short."""
        with self.lock:
            yield self.model, self.data

    def stats(self) -> SimStats:
        """Physics-loop statistics since the physics started."""
        with self.lock:
            steps, sim_time = self.steps, float(self.data.time)
            wakes, overruns, resyncs = self._wakes, self._overruns, self._resyncs
        wall = (time.monotonic_ns() - self._start_ns) / 1e9 if self._start_ns else 0.0
        factor = sim_time / wall if wall > 0 else 0.0
        return SimStats(steps, wakes, overruns, resyncs, sim_time, wall, factor)

    def _run(self) -> None:
        period = round(self.model.opt.timestep * 1e9)
        max_lag = self._max_catchup * period
        deadline = time.monotonic_ns()
        aligned_to = 0  # the read the latest alignment used
        try:
            while not self._stop.is_set():
                steps = self._steps_per_wake
                for _ in range(steps):
                    with self.lock:
                        mujoco.mj_step(self.model, self.data)
                        self.steps += 1
                        self.step_ns = time.time_ns()
                self._wakes += 1
                wake_ns = steps * period
                deadline += wake_ns
                now = time.monotonic_ns()
                read = self._read_ns
                # One control loop's reads only (a shared physics has one per arm), and a recent one.
                if self.wakes_between_reads and steps > 1 and self._users == 1 and read != aligned_to:
                    aligned_to = read
                    if now - read < wake_ns:
                        deadline = between_reads(deadline, read, wake_ns)
                if now < deadline:
                    time.sleep((deadline - now) / 1e9)
                    continue
                self._overruns += 1
                if now - deadline > max_lag:
                    # Too far behind to catch up: drop the lag instead of running flat out.
                    self._resyncs += 1
                    deadline = now
                    time.sleep(0)  # let other threads in between steps
        except Exception:
            _log.exception("%s: physics thread failed", self._name)
            raise


#: How far each wake moves toward the middle between two state reads (:func:`between_reads`): a
#: read's jitter moves the wakes a quarter of it, and a wake next to the reads is in the middle
#: after ~10 wakes (0.1 s at 100 Hz).
_ALIGN_GAIN = 0.25


def between_reads(deadline_ns: int, read_ns: int, wake_ns: int) -> int:
    """The next wake's deadline [ns] moved a quarter of the way toward the middle between two reads.

    The reads come once per wake period ``wake_ns`` (or a whole multiple of it), the latest at
    ``read_ns``; the middle is half a wake period after each. A wake there leaves every read one
    new state to find, however the reads jitter by up to half a period; a wake next to the reads
    (the chance phase of two clocks of the same rate) gives one read the same state twice and the
    next a state that skipped one.
    """
    error = (deadline_ns - read_ns) % wake_ns - wake_ns // 2
    return deadline_ns - round(_ALIGN_GAIN * error)


class SimDriverLink:
    """One simulated driver's hold on its physics: connect, close, stepping and the e-stop latch.

    Composition, not a base class: each simulated driver owns one and keeps its own API; the
    driver decides what holding means at an e-stop (``latch(hold)``) and what joining a running
    shared physics does (``connect(join)``). ``close`` is idempotent; a closed driver cannot connect.
    """

    def __init__(self, physics: SimPhysics, name: str) -> None:
        """Args:
        physics: The physics the driver steps (possibly shared with other drivers).
        name: The driver's name, for errors and logs (a renamed driver updates it).
        """
        self.physics = physics
        self.name = name
        self.connected = False
        self.closed = False
        #: Whether the emergency stop is latched (read under the physics lock by the driver's sends).
        self.estopped = False

    def connect(self, join: Callable[[mujoco.MjData], None] | None = None) -> None:
        """Start (or join) the physics. Idempotent.

        Args:
            join: Called with the data under the lock when the physics already runs (a later
                driver of a shared physics), e.g. to put its arm at home.

        Raises:
            RobotError: the driver was closed.
        """
        if self.closed:
            raise RobotError(f"{self.name}: driver is closed; create a new one")
        if self.connected:
            return
        if join is not None and self.physics.running:
            with self.physics.lock:
                join(self.physics.data)
        self.physics.acquire()
        self.connected = True
        _log.info("%s: connected (%s)", self.name, "real time" if self.physics.realtime else "stepped")

    def close(self) -> None:
        """Release the physics (it stops with its last driver). Idempotent."""
        self.closed = True
        if self.connected:
            self.connected = False
            self.physics.release()

    def require_connected(self) -> None:
        """Raises RobotError naming the fix unless connected."""
        if not self.connected:
            state = "closed" if self.closed else "not connected; call connect() first"
            raise RobotError(f"{self.name}: driver is {state}")

    def step(self, n: int = 1) -> None:
        """Advance the physics by ``n`` timesteps (``realtime=False`` only).

        Raises:
            RobotError: the physics runs in real time, or the driver is not connected.
        """
        if self.physics.realtime:
            raise RobotError(f"{self.name}: step() needs realtime=False; the physics thread steps")
        self.require_connected()
        self.physics.step(n)

    def latch(self, hold: Callable[[mujoco.MjData], None]) -> None:
        """Latch the emergency stop: ``hold(data)`` sets the hold targets under the lock."""
        with self.physics.lock:
            hold(self.physics.data)
            self.estopped = True
        _log.warning("%s: emergency stop latched", self.name)

    def reset_estop(self) -> None:
        """Release the emergency stop."""
        with self.physics.lock:
            self.estopped = False
        _log.info("%s: emergency stop released", self.name)


class MujocoArm:
    """A simulated arm with a gripper, implementing :class:`~telerig.robots.base.RobotDriver`.

    In real-time mode (the default) :meth:`connect` starts a thread that steps the physics
    every ``model.opt.timestep`` seconds (2 ms by default) against absolute deadlines. When it falls
    behind it steps without sleeping until it has caught up, up to ``max_catchup`` steps;
    beyond that it drops the lag (counted in :attr:`SimStats.resyncs`), so it never spins.
    With ``realtime=False`` nothing runs on its own: call :meth:`step`, which is deterministic.

    All access to the MuJoCo data goes through one lock; a renderer uses :meth:`locked`. Given a
    shared ``physics``, the driver commands only its own arm and gripper in that scene (see
    :class:`~telerig.robots.sim.bimanual.BimanualStation`).
    """

    def __init__(
        self,
        scene: ArmScene | None = None,
        *,
        name: str = "ur5e_sim",
        realtime: bool = True,
        max_catchup: int = 25,
        physics: SimPhysics | None = None,
    ) -> None:
        """Create the driver (the physics starts on :meth:`connect`).

        Args:
            scene: Scene to simulate; :func:`~telerig.robots.sim.scene.build_arm_scene` when None.
            name: Driver name; the ``source_id`` of every stamp it produces.
            realtime: Step on a thread paced to the wall clock; False for :meth:`step`.
                Ignored with ``physics`` (its own setting applies).
            max_catchup: Most steps the loop may run late before it drops the lag. >= 1.
            physics: Physics shared with other drivers of the same scene model; a new one when None.

        Raises:
            RobotError: the scene has no arm actuators, or ``physics`` simulates another model.
        """
        self._scene = scene if scene is not None else build_arm_scene()
        model = self._scene.model
        if not self._scene.arm_actuators:
            raise RobotError("scene has no arm actuators (a kinematic model?); use build_arm_scene()")
        if physics is None:
            physics = SimPhysics(model, name=name, realtime=realtime, max_catchup=max_catchup)
        elif physics.model is not model:
            raise RobotError(f"{name}: the shared physics simulates another model; pass the scene's own")
        self._physics = physics
        self._name = name
        self._model = model
        self._data = physics.data
        self._lock = physics.lock
        self._qadr = np.array([model.joint(j).qposadr[0] for j in self._scene.arm_joints])
        self._vadr = np.array([model.joint(j).dofadr[0] for j in self._scene.arm_joints])
        self._arm_act = np.array([model.actuator(a).id for a in self._scene.arm_actuators])
        self._grip_act = np.array([model.actuator(a).id for a in self._scene.gripper_actuators], dtype=int)
        ctrlrange = model.actuator_ctrlrange[self._grip_act]
        given_open, given_closed = self._scene.gripper_open, self._scene.gripper_closed
        self._grip_open = ctrlrange[:, 0].copy() if given_open is None else np.asarray(given_open, float)
        self._grip_closed = (
            ctrlrange[:, 1].copy() if given_closed is None else np.asarray(given_closed, float)
        )
        if self._grip_open.shape != self._grip_act.shape or self._grip_closed.shape != self._grip_act.shape:
            raise RobotError(f"{name}: gripper_open/closed must have one value per gripper actuator")
        self._ctrl_lo = model.actuator_ctrlrange[self._arm_act, 0].copy()
        self._ctrl_hi = model.actuator_ctrlrange[self._arm_act, 1].copy()
        jids = [model.joint(j).id for j in self._scene.arm_joints]
        self._limits = JointLimits(
            names=self._scene.arm_joints,
            lower=model.jnt_range[jids, 0],
            upper=model.jnt_range[jids, 1],
            velocity=_or_full(self._scene.velocity_limit, len(jids), UR5E_VELOCITY_LIMIT),
            acceleration=_or_full(self._scene.acceleration_limit, len(jids), UR5E_ACCELERATION_LIMIT),
        )
        self._index = {j: i for i, j in enumerate(self._scene.arm_joints)}
        self._grip_qadr = np.array([model.joint(j).qposadr[0] for j in self._scene.gripper_joints], dtype=int)
        # The measured opening is mean((q - closed) / span) over the servos whose open and closed
        # targets differ, = q @ _grip_gain - _grip_offset.
        span = self._grip_open - self._grip_closed
        moving = span != 0.0
        self._grip_gain = np.zeros_like(span)
        self._grip_gain[moving] = 1.0 / (span[moving] * max(1, int(moving.sum())))
        self._grip_offset = float(self._grip_closed @ self._grip_gain)
        self._ft = _WristFT.of(model, self._scene.ft_site)
        physics.attach(self._go_home)
        self._link = SimDriverLink(physics, name)
        self._cmd_seq = 0
        self._grip_seq = 0
        self._state_seq = 0
        self._pose_seq = 0
        self._grip_state_seq = 0
        self._wrench_seq = 0

    # -- RobotDriver ------------------------------------------------------------------------

    @property
    def name(self) -> str:
        """Driver name, used as the stamps' ``source_id``."""
        return self._name

    @property
    def joint_names(self) -> tuple[str, ...]:
        """Arm joints commanded by :meth:`send`, base to tool."""
        return self._scene.arm_joints

    @property
    def limits(self) -> JointLimits:
        """Joint ranges from the model [rad], the vendor's speed [rad/s] and acceleration [rad/s^2] limits."""
        return self._limits

    @property
    def scene(self) -> ArmScene:
        """The simulated scene (model and names)."""
        return self._scene

    @property
    def robot_model(self) -> str | None:
        """Name of the arm model this scene simulates (:class:`~telerig.robots.models.ModelledRobot`)."""
        return self._scene.arm_model

    @property
    def physics(self) -> SimPhysics:
        """The physics this driver steps (shared with the other arm of a bimanual station)."""
        return self._physics

    @property
    def estopped(self) -> bool:
        """Whether the emergency stop is latched."""
        return self._link.estopped

    def connect(self) -> None:
        """Put the arm at home with the gripper open and start the physics. Idempotent.

        The first driver of a shared physics resets the whole scene; later ones join it running.

        Raises:
            RobotError: the driver was closed.
        """
        self._link.connect(join=self._join)

    def read_state(self) -> JointState:
        """Arm joint positions [rad], velocities [rad/s] and actuator torques [N m].

        Stamped with the wall time of the latest physics step (``capture_ns``) and the
        simulation clock (``device_ns``).
        """
        self._require_connected()
        with self._lock:
            data = self._data
            positions = data.qpos[self._qadr].copy()
            velocities = data.qvel[self._vadr].copy()
            efforts = data.actuator_force[self._arm_act].copy()
            device_ns = round(data.time * 1e9)
            capture_ns = self._physics.read_stamp()
            seq = self._state_seq
            self._state_seq += 1
        stamp = Stamp(self._name, seq, device_ns=device_ns, capture_ns=capture_ns)
        return JointState(stamp, self.joint_names, positions, velocities, efforts)

    def send(self, command: JointCommand) -> JointCommand:
        """Set arm position targets [rad] for the named joints (any subset, any order).

        Targets are clipped to the actuator ranges; feed-forward velocities are ignored
        (position servos). While the e-stop is latched the command is ignored and the held
        targets are returned.

        Returns:
            The targets in force for ``command.names`` after the call, stamped at that moment.

        Raises:
            RobotError: a joint name is unknown, or the driver is not connected.
        """
        self._require_connected()
        idx = self._indices(command.names)
        target = np.clip(command.positions, self._ctrl_lo[idx], self._ctrl_hi[idx])
        with self._lock:
            if not self._link.estopped:
                self._data.ctrl[self._arm_act[idx]] = target
            applied = self._data.ctrl[self._arm_act[idx]].copy()
            seq = self._cmd_seq
            self._cmd_seq += 1
            t = time.time_ns()
        return JointCommand(Stamp(self._name, seq, device_ns=t, capture_ns=t), command.names, applied)

    @property
    def has_gripper(self) -> bool:
        """Whether the scene has gripper (or hand synergy) actuators."""
        return bool(self._grip_act.size)

    def send_gripper(self, command: GripperCommand) -> GripperCommand:
        """Set the gripper opening (0 closed, 1 open; clipped to [0, 1]).

        The opening maps linearly onto each finger servo, from ``scene.gripper_closed`` to
        ``scene.gripper_open``. ``max_force`` is not simulated: the returned command has 0 (the
        default). While the e-stop is latched the command is ignored and the held opening is returned.

        Raises:
            RobotError: the driver is not connected, or the robot has no gripper.
        """
        self._require_connected()
        if not self._grip_act.size:
            raise RobotError(f"{self._name}: no gripper on this robot; remove the gripper from its binding")
        opening = float(np.clip(command.opening, 0.0, 1.0))
        closed, span = self._grip_closed, self._grip_open - self._grip_closed
        with self._lock:
            if not self._link.estopped:
                self._data.ctrl[self._grip_act] = closed + opening * span
            held = self._data.ctrl[self._grip_act]
            applied = float(np.mean((held - closed) / span))
            seq = self._grip_seq
            self._grip_seq += 1
            t = time.time_ns()
        return GripperCommand(Stamp(self._name, seq, device_ns=t, capture_ns=t), opening=applied)

    def read_gripper(self) -> GripperCommand:
        """The measured opening (0 closed, 1 open): the finger joints' positions mapped like
        :meth:`send_gripper`'s targets, averaged and clipped to [0, 1]; stamped like :meth:`read_state`.

        Raises:
            RobotError: the driver is not connected, or the robot has no gripper.
        """
        self._require_connected()
        if not self._grip_act.size:
            raise RobotError(f"{self._name}: no gripper on this robot to read")
        with self._lock:
            opening = float(self._data.qpos[self._grip_qadr] @ self._grip_gain) - self._grip_offset
            device_ns = round(self._data.time * 1e9)
            capture_ns = self._physics.step_ns
            seq = self._grip_state_seq
            self._grip_state_seq += 1
        stamp = Stamp(self._name, seq, device_ns=device_ns, capture_ns=capture_ns)
        return GripperCommand(stamp, opening=min(1.0, max(0.0, opening)))

    @property
    def has_wrench_sensor(self) -> bool:
        """Whether the scene has a wrist force/torque sensor (:attr:`ArmScene.ft_site`)."""
        return self._ft is not None

    def read_wrench(self) -> Wrench:
        """The wrist force/torque sensor: the load on the gripper (what it holds, what it pushes
        against), with the gripper's own weight compensated as a real sensor's tool compensation does.

        Force [N] and torque [N m] about the sensor site, in the sensor frame (``<name>/ft_sensor``,
        the gripper mount's axes); stamped like :meth:`read_state`. A held mass reads its weight
        (pointing down in the world); pushing the gripper onto the table reads the table's push (up).

        Raises:
            RobotError: the driver is not connected, or the scene has no F/T sensor.
        """
        self._require_connected()
        ft = self._ft
        if ft is None:
            raise RobotError(f"{self._name}: this scene has no wrist force/torque sensor")
        with self._lock:
            data = self._data
            force, torque = ft.load(data)
            device_ns = round(data.time * 1e9)
            capture_ns = self._physics.step_ns
            seq = self._wrench_seq
            self._wrench_seq += 1
        stamp = Stamp(self._name, seq, device_ns=device_ns, capture_ns=capture_ns)
        return Wrench(stamp, force, torque, f"{self._name}/ft_sensor")

    def estop(self) -> None:
        """Latch the emergency stop: the arm holds its current position, commands are ignored.

        The gripper keeps its last command, so a held object is not dropped.
        """

        def hold(data: mujoco.MjData) -> None:
            data.ctrl[self._arm_act] = np.clip(data.qpos[self._qadr], self._ctrl_lo, self._ctrl_hi)

        self._link.latch(hold)

    def reset_estop(self) -> None:
        """Release the emergency stop; the arm keeps holding until the next :meth:`send`."""
        self._link.reset_estop()

    def close(self) -> None:
        """Release the driver; the physics stops with its last driver. Idempotent."""
        self._link.close()

    # -- simulation access -------------------------------------------------------------------

    def step(self, n: int = 1) -> None:
        """Advance the physics by ``n`` steps of ``model.opt.timestep`` (``realtime=False`` only).

        Raises:
            RobotError: the driver runs in real time or is not connected.
        """
        self._link.step(n)

    def reset_objects(self) -> None:
        """Put every free-floating object (e.g. the cube) back at its initial pose, at rest.

        The arm is not touched: between episodes it is moved only through commands, so it never jumps.
        """
        self._physics.reset_objects()

    def locked(self) -> contextlib.AbstractContextManager[tuple[mujoco.MjModel, mujoco.MjData]]:
        """Hold the physics lock and yield ``(model, data)``, e.g. for ``renderer.update_scene``.

        Keep the block short: the physics waits for it. Do not keep references to ``data``.
        """
        return self._physics.locked()

    def stats(self) -> SimStats:
        """Physics-loop statistics since the physics started."""
        return self._physics.stats()

    def __enter__(self) -> MujocoArm:
        self.connect()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # -- internals ----------------------------------------------------------------------------

    def _go_home(self, data: mujoco.MjData) -> None:
        """Arm at home holding it, gripper open (called under the lock)."""
        data.qpos[self._qadr] = self._scene.home
        data.qvel[self._vadr] = 0.0
        data.ctrl[self._arm_act] = np.clip(self._scene.home, self._ctrl_lo, self._ctrl_hi)
        if self._grip_act.size:
            data.ctrl[self._grip_act] = self._grip_open

    def _require_connected(self) -> None:
        self._link.require_connected()

    def _body_pose(self, body: int) -> Pose:
        """Pose of ``body`` in the world frame, stamped like :meth:`read_state`."""
        self._require_connected()
        with self._lock:
            data = self._data
            position = data.xpos[body].copy()
            orientation = data.xquat[body].copy()
            device_ns = round(data.time * 1e9)
            capture_ns = self._physics.step_ns
            seq = self._pose_seq
            self._pose_seq += 1
        return Pose(Stamp(self._name, seq, device_ns, capture_ns), position, orientation, "world")

    def _join(self, data: mujoco.MjData) -> None:
        """A later driver of a running shared physics: its arm to home (under the lock)."""
        self._go_home(data)
        mujoco.mj_forward(self._model, data)

    def _indices(self, names: tuple[str, ...]) -> list[int]:
        try:
            return [self._index[n] for n in names]
        except KeyError as exc:
            raise RobotError(
                f"{self._name}: joint {exc.args[0]!r} not found. Available: {', '.join(self.joint_names)}"
            ) from None


@dataclass(frozen=True, slots=True)
class _WristFT:
    """A wrist force/torque sensor in a compiled model: its site, the addresses of its force and
    torque readings in ``sensordata``, and the tool it carries (the gripper's subtree): its mass [kg]
    and centre of mass [m] in the sensor frame, taken once at the model's reference pose, as a real
    sensor's tool calibration is."""

    site: int
    force: int
    torque: int
    #: The tool's weight in the world [N] (mass times gravity). Shape (3,).
    weight: FloatArray
    #: ``cross(com, v)`` as a matrix: the moment [N m] of a force ``v`` at the tool's centre of mass. (3, 3).
    com_cross: FloatArray

    @classmethod
    def of(cls, model: mujoco.MjModel, site: str | None) -> _WristFT | None:
        if site is None:
            return None
        sid = model.site(site).id
        body = int(model.site_bodyid[sid])
        reference = mujoco.MjData(model)
        mujoco.mj_kinematics(model, reference)
        mujoco.mj_comPos(model, reference)
        rot = reference.site_xmat[sid].reshape(3, 3)
        x, y, z = rot.T @ (reference.subtree_com[body] - reference.site_xpos[sid])
        return cls(
            sid,
            int(model.sensor_adr[model.sensor(f"{site}_force").id]),
            int(model.sensor_adr[model.sensor(f"{site}_torque").id]),
            float(model.body_subtreemass[body]) * model.opt.gravity.copy(),
            np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]]),
        )

    def load(self, data: mujoco.MjData) -> tuple[FloatArray, FloatArray]:
        """Force [N] and torque [N m] of the load on the gripper, sensor frame (call under the lock).

        MuJoCo reads the flange's force and torque on the gripper's subtree; at rest they balance
        the gripper's weight and the load, so the load is minus their sum.
        """
        weight = self.weight @ data.site_xmat[self.site].reshape(3, 3)  # R^T w: in the sensor frame
        f = data.sensordata[self.force : self.force + 3]
        t = data.sensordata[self.torque : self.torque + 3]
        return -(f + weight), -(t + self.com_cross @ weight)


def _or_full(values: FloatArray | None, n: int, default: float) -> FloatArray:
    return np.full(n, default) if values is None else np.asarray(values, dtype=np.float64)
