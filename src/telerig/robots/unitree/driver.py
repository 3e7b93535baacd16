"""Unitree G1 upper body over DDS ``arm_sdk``: the robot balances itself, telerig moves waist and arms.

Unitree's G1 takes upper-body targets on ``rt/arm_sdk`` (``unitree_hg`` ``LowCmd_``, PD targets
per motor) while its own locomotion controller keeps it standing, and blends them in by a weight
(motor slot 29's ``q``, 0 = the robot's controller, 1 = these targets). This driver

* reads ``rt/lowstate`` (published by the robot at 500 Hz) and returns the commanded joints'
  positions and velocities, stamped in the host clock (the robot's DDS source time, offset by
  :class:`~telerig.ir.clock.ClockOffsetEstimator`); states with a wrong CRC are dropped;
* publishes ``rt/arm_sdk`` on every :meth:`UnitreeG1.send` and from a keep-alive thread, so the
  targets hold between commands: commanded joints get the clipped targets, the other upper-body
  joints hold where they were at connect. The weight ramps 0 → 1 over ``weight_ramp_s`` after
  connect (a smooth take-over from the robot's controller) and back to 0 on close (hand-back);
* latches a software e-stop that holds the measured position with the PD gains (and refuses
  targets) until :meth:`UnitreeG1.reset_estop`. A hardware e-stop (the remote's, or the robot's)
  remains required: software cannot stop a robot whose computer or network has failed.

Full low-level control (``rt/lowcmd``, legs included) needs the robot hung in its gantry and its
motion service released; it is not offered here. Not verified against a physical G1 (none here):
message types, topics, CRC and the weight slot follow Unitree's SDK 2; the checksum is checked
equal to the SDK's own ``crc32_core`` in the tests' development, and telerig's Cyclone DDS (11.x)
is newer than the robot's (0.10.x), which the DDS wire protocol (RTPS) allows.
"""

from __future__ import annotations

import logging
import threading
import time
from types import TracebackType

import numpy as np
from cyclonedds.core import DDSStatus, Entity, GuardCondition, WaitSet
from cyclonedds.domain import DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.qos import Policy, Qos
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic

from telerig.errors import RobotError
from telerig.ir.clock import ClockOffsetEstimator
from telerig.ir.types import FloatArray, GripperCommand, JointCommand, JointState, Stamp, now_ns
from telerig.robots.base import JointLimits
from telerig.robots.unitree.dds import delete_entities, join_domain
from telerig.robots.unitree.joints import G1_UPPER_BODY
from telerig.robots.unitree.messages import LowCmd, LowState, lowcmd_crc, lowstate_crc

__all__ = ["ARM_SDK_TOPIC", "LOWSTATE_TOPIC", "UnitreeG1", "WEIGHT_SLOT"]

_log = logging.getLogger(__name__)

LOWSTATE_TOPIC = "rt/lowstate"
ARM_SDK_TOPIC = "rt/arm_sdk"
#: Motor slot whose ``q`` is the arm_sdk weight (0..1).
WEIGHT_SLOT = 29
#: Longest wait of the arrival watcher [ns] before it checks whether the driver is closing (a
#: guard condition wakes it at once on close).
_WATCH_TIMEOUT_NS = 100_000_000


_BY_NAME = {j.name: j for j in G1_UPPER_BODY}
_UPPER_MOTORS = np.array([j.motor for j in G1_UPPER_BODY])


class UnitreeG1:
    """A Unitree G1's waist and arms through ``rt/arm_sdk`` (see the module docs).

    Args:
        name: Driver name (stamps' ``source_id``).
        limits: Limits of the commanded joints, a subset of
            :data:`~telerig.robots.unitree.joints.G1_UPPER_BODY` by name.
        network_interface: Host interface on the robot's network (``lo`` for a fake robot).
        domain_id: DDS domain (the G1 uses 0).
        kp: Position gain per commanded joint [N m/rad]; the held joints use the first.
        kd: Damping gain per commanded joint [N m s/rad].
        weight_ramp_s: Time to take the upper body over from the robot's controller, and to hand
            it back on close [s].
        keepalive_hz: Rate at which the targets are re-published between commands [Hz].
        timeout_s: Wait for the first state on connect [s].
        stale_timeout_s: A state older than this is a lost connection [s].
    """

    def __init__(
        self,
        name: str,
        limits: JointLimits,
        *,
        network_interface: str = "eth0",
        domain_id: int = 0,
        kp: FloatArray | float = 60.0,
        kd: FloatArray | float = 1.5,
        weight_ramp_s: float = 1.0,
        keepalive_hz: float = 100.0,
        timeout_s: float = 2.0,
        stale_timeout_s: float = 0.2,
    ) -> None:
        unknown = [n for n in limits.names if n not in _BY_NAME]
        if unknown:
            raise RobotError(
                f"{name}: {unknown[0]!r} is not an arm_sdk joint of the G1. Valid: {', '.join(_BY_NAME)}"
            )
        n = len(limits.names)
        self._name = name
        self._limits = limits
        self._motors = np.array([_BY_NAME[j].motor for j in limits.names])
        self._index = {j: i for i, j in enumerate(limits.names)}
        self.network_interface = network_interface
        self.domain_id = domain_id
        self.weight_ramp_s = weight_ramp_s
        self.keepalive_s = 1.0 / keepalive_hz
        self.timeout_s = timeout_s
        self.stale_timeout_s = stale_timeout_s

        self._lock = threading.Lock()  # guards every field below and the DDS writer
        self._participant: DomainParticipant | None = None
        self._entities: tuple[Entity, ...] = ()
        self._reader: DataReader[LowState] | None = None
        self._writer: DataWriter[LowCmd] | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._closed = False
        self._estopped = False
        # The gains never change: set once on the reused command (held joints take the first).
        self._cmd = LowCmd()
        kp_n = np.broadcast_to(np.asarray(kp, dtype=np.float64), (n,))
        kd_n = np.broadcast_to(np.asarray(kd, dtype=np.float64), (n,))
        for motor in _UPPER_MOTORS:
            self._cmd.motor_cmd[motor].kp, self._cmd.motor_cmd[motor].kd = float(kp_n[0]), float(kd_n[0])
        for i, motor in enumerate(self._motors):
            self._cmd.motor_cmd[motor].kp, self._cmd.motor_cmd[motor].kd = float(kp_n[i]), float(kd_n[i])
        # Targets of all 35 slots [rad]; the upper body's are published, the rest stay 0 / unused.
        self._targets = np.zeros(35)
        self._measured = np.zeros(35)
        self._velocities = np.zeros(35)
        self._state_capture_ns = 0
        self._state_arrival_ns = 0
        self._last_arrival_ns = 0  # of the newest rt/lowstate, taken or not (set by the watcher)
        self._taken_arrival_ns = 0  # the arrival _take_state last used
        self._watcher: threading.Thread | None = None
        self._wake: GuardCondition | None = None
        self._state_device_ns = 0
        self._connected_at = 0.0
        self._last_publish = 0.0
        self._weight = 0.0
        self._releasing = False  # close() hands the upper body back: the weight ramps down
        self._release_from = 0.0
        self._release_at = 0.0
        self._clock = ClockOffsetEstimator(reset_ns=1_000_000_000)
        self._read_seq = 0
        self._cmd_seq = 0
        self._stats = dict.fromkeys(("states", "bad_crc", "published"), 0)

    # -- RobotDriver --------------------------------------------------------------------------

    @property
    def name(self) -> str:
        """Driver name, used as the stamps' ``source_id``."""
        return self._name

    @property
    def joint_names(self) -> tuple[str, ...]:
        """Commanded joints, in the order of :attr:`limits`."""
        return self._limits.names

    @property
    def limits(self) -> JointLimits:
        """Joint position [rad], speed [rad/s] and acceleration [rad/s^2] limits."""
        return self._limits

    @property
    def has_gripper(self) -> bool:
        """Never: the G1's Dex3 hands are not driven through arm_sdk."""
        return False

    @property
    def connected(self) -> bool:
        """Whether the driver joined the DDS domain and has not been closed."""
        return self._participant is not None and not self._closed

    @property
    def estopped(self) -> bool:
        """Whether the software e-stop is latched."""
        return self._estopped

    @property
    def weight(self) -> float:
        """The arm_sdk weight last published (0 = the robot's controller, 1 = telerig's targets)."""
        return self._weight

    @property
    def stats(self) -> dict[str, int]:
        """Counters: ``states`` taken, ``bad_crc`` states dropped, ``published`` commands."""
        with self._lock:
            return dict(self._stats)

    def connect(self) -> None:
        """Join the DDS domain, wait for the robot's first state and start the keep-alive.

        Idempotent. Raises ``RobotError`` when the driver is closed, the interface is wrong, or
        no valid ``rt/lowstate`` arrives within ``timeout_s`` (the message says what to check).
        """
        if self._closed:
            raise RobotError(f"{self._name}: driver is closed; create a new one")
        if self._participant is not None:
            return
        join_domain(self.domain_id, self.network_interface)
        participant = DomainParticipant(self.domain_id)
        # Only the newest state is kept and deserialized, when read; a watcher thread just notes each
        # arrival time (the robot publishes at 500 Hz, decoding one costs ~0.5 ms in Python).
        history = Qos(Policy.History.KeepLast(1))
        states, commands = (
            Topic(participant, LOWSTATE_TOPIC, LowState),
            Topic(participant, ARM_SDK_TOPIC, LowCmd),
        )
        self._reader = DataReader(participant, states, history)
        self._reader.set_status_mask(DDSStatus.DataAvailable)
        self._writer = DataWriter(participant, commands)
        self._wake = GuardCondition(participant)
        waitset = WaitSet(participant)
        waitset.attach(self._reader)
        waitset.attach(self._wake)
        self._participant = participant
        self._entities = (waitset, self._wake, self._reader, self._writer, commands, states, participant)
        self._stop.clear()
        self._watcher = threading.Thread(
            target=self._watch_arrivals,
            args=(waitset, self._reader),
            name=f"telerig-{self._name}-arrivals",
            daemon=True,
        )
        self._watcher.start()
        deadline = time.monotonic() + self.timeout_s
        while not self._take_state():
            if time.monotonic() > deadline:
                self._shutdown()
                raise RobotError(
                    f"{self._name}: no valid {LOWSTATE_TOPIC} from the robot within {self.timeout_s:g} s on "
                    f"interface {self.network_interface!r}, DDS domain {self.domain_id}: is the robot on "
                    "and this host on its network (192.168.123.x)?"
                )
            time.sleep(0.002)
        with self._lock:
            self._targets[:] = self._measured
            self._connected_at = time.monotonic()
        self._stop.clear()
        self._thread = threading.Thread(target=self._keepalive, name=f"telerig-{self._name}-dds", daemon=True)
        self._thread.start()
        _log.info("%s: connected on %s, taking over the upper body", self._name, self.network_interface)

    def read_state(self) -> JointState:
        """Latest positions [rad] and velocities [rad/s] of the commanded joints.

        Raises:
            RobotError: not connected, or no state for ``stale_timeout_s`` (connection lost).
        """
        self._require_fresh()
        with self._lock:
            seq = self._read_seq
            self._read_seq += 1
            q = self._measured[self._motors].copy()
            dq = self._velocities[self._motors].copy()
            stamp = Stamp(self._name, seq, device_ns=self._state_device_ns, capture_ns=self._state_capture_ns)
            arrival = self._state_arrival_ns
        return JointState(stamp.arrived(arrival), self.joint_names, q, dq)

    def send(self, command: JointCommand) -> JointCommand:
        """Publish the clipped targets [rad] (any subset; the other joints keep theirs) at once.

        While the e-stop is latched nothing changes and the held position is returned.

        Raises:
            RobotError: unknown joint, not connected or connection lost.
        """
        self._require_fresh(take=False)
        idx = self._indices(command.names)
        motors = self._motors[idx]
        with self._lock:
            if not self._estopped:
                lo, hi = self._limits.lower[idx], self._limits.upper[idx]
                self._targets[motors] = np.clip(command.positions, lo, hi)
            applied = self._targets[motors].copy()
            self._publish_locked()
            seq = self._cmd_seq
            self._cmd_seq += 1
        t = now_ns()
        return JointCommand(Stamp(self._name, seq, device_ns=t, capture_ns=t), command.names, applied)

    def send_gripper(self, command: GripperCommand) -> GripperCommand:
        """Refused: the G1's hands are not driven through arm_sdk.

        Raises:
            RobotError: always, naming the fix.
        """
        raise RobotError(f"{self._name}: no gripper on this robot; remove the gripper from its binding")

    def estop(self) -> None:
        """Latch the software stop: hold the measured position with the PD gains. Never raises."""
        try:
            self._take_state()  # the newest measured position to hold
        except Exception as exc:
            _log.error("%s: no fresh state for the e-stop hold (%s); holding the last one", self._name, exc)
        with self._lock:
            self._estopped = True
            self._targets[_UPPER_MOTORS] = self._measured[_UPPER_MOTORS]
            try:
                self._publish_locked()
            except Exception as exc:  # the keep-alive keeps trying; the latch holds regardless
                _log.error("%s: e-stop latched, publishing the hold failed: %s", self._name, exc)
        _log.warning("%s: emergency stop latched (holding the measured position)", self._name)

    def reset_estop(self) -> None:
        """Release the latch; the robot holds where it is until the next :meth:`send`.

        Raises:
            RobotError: not connected or connection lost.
        """
        self._require_fresh()
        with self._lock:
            self._targets[_UPPER_MOTORS] = self._measured[_UPPER_MOTORS]
            self._estopped = False
        _log.info("%s: emergency stop released", self._name)

    def close(self) -> None:
        """Hand the upper body back to the robot's controller (weight → 0), then leave DDS. Idempotent."""
        if self._closed:
            return
        if self._thread is not None and self._participant is not None:
            with self._lock:
                self._releasing = True
                self._release_from = self._weight
                self._release_at = time.monotonic()
            deadline = time.monotonic() + self.weight_ramp_s + 0.5
            while self._weight > 0.0 and time.monotonic() < deadline and self._thread.is_alive():
                time.sleep(self.keepalive_s)
        self._closed = True
        self._shutdown()
        _log.info("%s: closed (%s)", self._name, self.stats)

    def __enter__(self) -> UnitreeG1:
        self.connect()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    # -- internals ----------------------------------------------------------------------------

    def _indices(self, names: tuple[str, ...]) -> np.ndarray:
        try:
            return np.array([self._index[n] for n in names], dtype=np.intp)
        except KeyError as exc:
            raise RobotError(
                f"{self._name}: joint {exc.args[0]!r} not found. Valid: {', '.join(self.joint_names)}"
            ) from None

    def _watch_arrivals(self, waitset: WaitSet, reader: DataReader[LowState]) -> None:
        """Note when each ``rt/lowstate`` arrives (without reading it), until :meth:`_shutdown`.

        Not a DDS listener: cyclonedds-python runs a listener's Python on DDS's receive thread,
        which must take the GIL there, while a thread that writes ``rt/lowstate`` in this process
        holds the GIL as DDS delivers the sample to this reader and waits for the listener to
        finish: a deadlock (cyclonedds-python issue #208) that hung the test suite with a
        :class:`~telerig.robots.unitree.fake.FakeG1` in the same process. A waitset is waited on
        through ctypes, which lets the GIL go.
        """
        while not self._stop.is_set():
            try:
                if waitset.wait(_WATCH_TIMEOUT_NS) <= 0 or self._stop.is_set():
                    continue
                self._last_arrival_ns = now_ns()
                reader.take_status(DDSStatus.DataAvailable)
            except Exception as exc:  # entities deleted under us: the driver is closing
                if not self._stop.is_set():
                    _log.error("%s: watching %s arrivals failed: %s", self._name, LOWSTATE_TOPIC, exc)
                return

    def _take_state(self) -> bool:
        """Take the newest ``rt/lowstate`` if one arrived; False when none (or only a bad CRC) did."""
        reader = self._reader
        if reader is None:
            return False
        samples = reader.take(N=1)
        if not samples:
            return False
        state = samples[0]
        if not isinstance(state, LowState):
            return False
        # The watcher notes arrivals; one this take beat it to (the status reset by the take) is
        # at the latest now.
        noted = self._last_arrival_ns
        arrival = noted if noted > self._taken_arrival_ns else now_ns()
        self._taken_arrival_ns = arrival
        self._last_arrival_ns = max(noted, arrival)
        if state.crc != lowstate_crc(state):
            with self._lock:
                self._stats["bad_crc"] += 1
            return False
        device_ns = int(state.sample_info.source_timestamp)  # type: ignore[attr-defined]  # set by take()
        offset = self._clock.update(device_ns, arrival)
        with self._lock:
            self._stats["states"] += 1
            for slot, motor in enumerate(state.motor_state):
                self._measured[slot] = motor.q
                self._velocities[slot] = motor.dq
            self._state_device_ns = device_ns
            self._state_capture_ns = min(device_ns + offset, arrival)
            self._state_arrival_ns = arrival
        return True

    def _require_fresh(self, *, take: bool = True) -> None:
        """Raise unless connected and the robot is alive; with ``take``, read the newest state first.

        :meth:`send` passes ``take=False``: the control loop has just read the state, and
        decoding another (~0.5 ms in Python) only to check the robot is alive is wasted there.
        """
        if self._closed or self._participant is None:
            raise RobotError(f"{self._name}: not connected; call connect() first")
        if take:
            self._take_state()
            # The newest state taken: one that waited unread in DDS's cache is old.
            arrival = self._state_arrival_ns
        else:
            arrival = self._last_arrival_ns  # the newest state received, read or not
        age_s = (now_ns() - arrival) / 1e9
        if age_s > self.stale_timeout_s:
            raise RobotError(
                f"{self._name}: no {LOWSTATE_TOPIC} for {age_s:.2f} s (> {self.stale_timeout_s:g} s): "
                "connection to the robot lost"
            )

    def _publish_locked(self) -> None:
        """Write the targets with the current weight (caller holds the lock)."""
        writer = self._writer
        if writer is None:
            return
        now = time.monotonic()
        if self._releasing:
            ramp = (now - self._release_at) / self.weight_ramp_s if self.weight_ramp_s > 0 else 1.0
            weight = max(0.0, self._release_from * (1.0 - ramp))
        else:
            ramp = (now - self._connected_at) / self.weight_ramp_s if self.weight_ramp_s > 0 else 1.0
            weight = min(1.0, ramp)
        cmd = self._cmd
        for motor in _UPPER_MOTORS:
            cmd.motor_cmd[motor].q = float(self._targets[motor])
        cmd.motor_cmd[WEIGHT_SLOT].q = weight
        cmd.crc = lowcmd_crc(cmd)
        writer.write(cmd)
        self._weight = weight
        self._last_publish = now
        self._stats["published"] += 1

    def _keepalive(self) -> None:
        while not self._stop.wait(self.keepalive_s / 2):
            with self._lock:
                if time.monotonic() - self._last_publish < self.keepalive_s and not self._releasing:
                    continue
                try:
                    self._publish_locked()
                except Exception:
                    _log.exception("%s: publishing %s failed", self._name, ARM_SDK_TOPIC)
                if self._releasing and self._weight <= 0.0:
                    return

    def _shutdown(self) -> None:
        self._stop.set()
        if self._wake is not None:
            self._wake.set(True)
        for thread in (self._thread, self._watcher):
            if thread is not None and thread is not threading.current_thread():
                thread.join(timeout=2.0)
        self._thread = self._watcher = self._wake = None
        with self._lock:
            self._reader = None
            self._writer = None
            self._participant = None
            entities, self._entities = self._entities, ()
        delete_entities(entities)
