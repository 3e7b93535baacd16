"""A fake Unitree G1 on DDS: publishes ``rt/lowstate`` and follows ``rt/arm_sdk``, as the robot does.

A public test utility: run a rig with ``type: unitree_g1, network_interface: lo`` against it to
dry-run before the real robot. It joins the same DDS domain on the loopback interface, publishes
every motor's state with its CRC at ``rate_hz``, checks the CRC of every arm_sdk command (wrong
ones are counted in :attr:`FakeG1.bad_crc` and ignored, as the robot ignores them) and moves each
upper-body motor toward its target blended with the robot's own pose by the command's weight::

    target = weight * q_cmd + (1 - weight) * standing_pose

at most ``max_velocity`` [rad/s], like a stiff PD joint. The legs stand still (the robot's own
controller balances it). Stop publishing with :meth:`FakeG1.pause` to play a lost connection.
"""

from __future__ import annotations

import threading
import time
from types import TracebackType

import numpy as np
from cyclonedds.core import Entity
from cyclonedds.domain import DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic

from telerig.ir.types import FloatArray
from telerig.robots.unitree.dds import delete_entities, join_domain
from telerig.robots.unitree.driver import ARM_SDK_TOPIC, LOWSTATE_TOPIC, WEIGHT_SLOT
from telerig.robots.unitree.joints import G1_UPPER_BODY
from telerig.robots.unitree.messages import MOTORS, LowCmd, LowState, lowcmd_crc, lowstate_crc

__all__ = ["FakeG1"]

_UPPER = np.array([j.motor for j in G1_UPPER_BODY])


class FakeG1:
    """A simulated G1 motor controller on DDS (see the module docs).

    Args:
        domain_id: DDS domain to join on ``lo`` (give each concurrent fake its own).
        rate_hz: ``rt/lowstate`` rate [Hz] (the robot's is 500).
        max_velocity: Speed of every motor toward its target [rad/s].
        standing_pose: Upper-body pose of the robot's own controller, by joint name [rad]
            (default: all zero but elbows bent 0.3 rad).
    """

    def __init__(
        self,
        domain_id: int,
        *,
        rate_hz: float = 500.0,
        max_velocity: float = 3.0,
        standing_pose: dict[str, float] | None = None,
    ) -> None:
        self.domain_id = domain_id
        self.period_s = 1.0 / rate_hz
        self.max_velocity = max_velocity
        pose = {"left_elbow_joint": 0.3, "right_elbow_joint": 0.3, **(standing_pose or {})}
        self._standing = np.zeros(MOTORS)
        for joint in G1_UPPER_BODY:
            self._standing[joint.motor] = pose.get(joint.name, 0.0)
        self._q = self._standing.copy()
        self._cmd_q = self._standing.copy()
        self._weight = 0.0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._paused = threading.Event()
        self._thread: threading.Thread | None = None
        self._participant: DomainParticipant | None = None
        self._entities: tuple[Entity, ...] = ()
        self.commands = 0
        self.bad_crc = 0
        self.states = 0

    def start(self) -> FakeG1:
        """Join the domain and start publishing; returns self."""
        join_domain(self.domain_id, "lo")
        participant = DomainParticipant(self.domain_id)
        states, commands = (
            Topic(participant, LOWSTATE_TOPIC, LowState),
            Topic(participant, ARM_SDK_TOPIC, LowCmd),
        )
        self._writer: DataWriter[LowState] = DataWriter(participant, states)
        self._reader: DataReader[LowCmd] = DataReader(participant, commands)
        self._participant = participant
        self._entities = (self._reader, self._writer, commands, states, participant)
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="fake-g1", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop publishing and leave the domain. Idempotent."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        self._participant = None
        delete_entities(self._entities)
        self._entities = ()

    def pause(self, paused: bool = True) -> None:
        """Stop (or resume) publishing states, as a robot whose network dropped."""
        if paused:
            self._paused.set()
        else:
            self._paused.clear()

    def positions(self, names: tuple[str, ...]) -> FloatArray:
        """Current positions of the named upper-body joints [rad]."""
        motors = {j.name: j.motor for j in G1_UPPER_BODY}
        with self._lock:
            return np.array([self._q[motors[n]] for n in names])

    @property
    def weight(self) -> float:
        """The arm_sdk weight of the last valid command (0 before any)."""
        return self._weight

    def __enter__(self) -> FakeG1:
        return self.start()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()

    def _run(self) -> None:
        state = LowState(mode_machine=5)  # the 29-DoF G1 reports mode_machine 5
        next_t = time.monotonic()
        while not self._stop.is_set():
            for cmd in self._reader.take(N=16):
                if not isinstance(cmd, LowCmd):
                    continue
                if cmd.crc != lowcmd_crc(cmd):
                    self.bad_crc += 1
                    continue
                self.commands += 1
                with self._lock:
                    self._weight = float(np.clip(cmd.motor_cmd[WEIGHT_SLOT].q, 0.0, 1.0))
                    for motor in _UPPER:
                        self._cmd_q[motor] = cmd.motor_cmd[motor].q
            with self._lock:
                target = self._weight * self._cmd_q + (1.0 - self._weight) * self._standing
                step = self.max_velocity * self.period_s
                previous = self._q.copy()
                self._q[_UPPER] += np.clip(target[_UPPER] - self._q[_UPPER], -step, step)
                dq = (self._q - previous) / self.period_s
            if not self._paused.is_set():
                state.tick += round(self.period_s * 1000)
                for slot, motor in enumerate(state.motor_state):
                    motor.q, motor.dq = float(self._q[slot]), float(dq[slot])
                state.crc = lowstate_crc(state)
                self._writer.write(state)
                self.states += 1
            next_t += self.period_s
            delay = next_t - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            else:
                next_t = time.monotonic()
