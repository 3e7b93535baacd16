"""Control node: device samples from the bus → retargeting → safety chain → robot driver, per robot.

The loop is driven by input: a fresh sample is retargeted and applied at once
(so input-to-actuation latency is not padded by a fixed tick phase); when no
sample arrives within one control period the loop still ticks, so the safety
chain can hold the last command and its watchdog can stop the robot.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from telerig.bus.base import Bus, Inbox, Message
from telerig.bus.topics import Topic, qos_for
from telerig.errors import WireError
from telerig.ir import wire
from telerig.ir.types import (
    ControllerState,
    FloatArray,
    GripperCommand,
    JointCommand,
    Pose,
    Sample,
    Stamp,
    now_ns,
)
from telerig.retarget.arm import AbsolutePoseRetargeter
from telerig.retarget.gripper import GripperRetargeter
from telerig.robots.base import RobotDriver
from telerig.runtime import streams
from telerig.runtime.metrics import LatencyTracker, StreamMeter
from telerig.safety import SafetyChain

__all__ = ["ArmBinding", "ControlNode", "ControlStats", "GripperBinding"]

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class ArmBinding:
    """Device stream topic whose poses drive the arm."""

    topic: str
    retargeter: AbsolutePoseRetargeter


@dataclass(frozen=True, slots=True)
class GripperBinding:
    """Device stream topic whose samples (controller trigger, hand pinch) drive the gripper."""

    topic: str
    retargeter: GripperRetargeter


@dataclass(slots=True)
class ControlStats:
    """Counters of one control node."""

    ticks: int = 0
    applied: int = 0
    decode_errors: int = 0
    wrong_type: int = 0
    ik_flagged: int = 0
    inputs_skipped: int = 0
    safety_status: str = "idle"
    safety_events: dict[str, int] = field(default_factory=dict)


class ControlNode:
    """Runs the control loop of one robot on its own thread.

    Args:
        rig: Rig name (topic prefix).
        robot: The driver to command; connected by the caller.
        safety: The robot's safety chain; always between retargeting and ``robot``.
        bus: Bus client of this node.
        control_rate_hz: Nominal command rate [Hz]; also the idle tick rate.
        arm: Optional arm binding.
        gripper: Optional gripper binding.
        home: Safe joint configuration [rad] that :meth:`go_home` drives to. Shape (n,).
    """

    def __init__(
        self,
        rig: str,
        robot: RobotDriver,
        safety: SafetyChain,
        bus: Bus,
        *,
        control_rate_hz: float,
        arm: ArmBinding | None = None,
        gripper: GripperBinding | None = None,
        home: FloatArray | None = None,
    ) -> None:
        self.rig = rig
        self.robot = robot
        self.safety = safety
        self._bus = bus
        self._period_s = 1.0 / control_rate_hz
        self._arm = arm
        self._gripper = gripper
        self._inbox = Inbox()
        self._subs = [bus.subscribe(t, self._inbox) for t in sorted(self._topics())]
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._q_last: FloatArray | None = None
        self._home = None if home is None else np.array(home, dtype=np.float64)
        self._homing = threading.Event()
        self._home_seq = 0
        self.stats = ControlStats()
        self.latency = LatencyTracker()
        self.input_meter = StreamMeter("input", control_rate_hz)
        self.command_meter = StreamMeter("commands", control_rate_hz)
        name = robot.name
        self._t_req = str(Topic(rig, name, streams.JOINT_REQUESTED))
        self._t_sent = str(Topic(rig, name, streams.JOINT_SENT))
        self._t_greq = str(Topic(rig, name, streams.GRIPPER_REQUESTED))
        self._t_gsent = str(Topic(rig, name, streams.GRIPPER_SENT))
        self._t_state = str(Topic(rig, name, streams.JOINT_STATE))
        self._t_status = str(Topic(rig, name, streams.STATUS))

    def _topics(self) -> set[str]:
        return {b.topic for b in (self._arm, self._gripper) if b is not None}

    def start(self) -> None:
        """Start the control thread; idempotent."""
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name=f"control-{self.robot.name}", daemon=True)
            self._thread.start()

    def stop(self) -> None:
        """Stop the control thread (the robot holds its last command); idempotent."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        for sub in self._subs:
            sub.cancel()
        self._subs = []

    @property
    def has_home(self) -> bool:
        """Whether :meth:`go_home` knows a home configuration."""
        return self._home is not None

    def go_home(self, *, timeout_s: float = 15.0, tolerance_rad: float = 0.02) -> bool:
        """Drive the arm to its home configuration through the safety chain, ignoring operator input.

        Used to reset the robot for safe repositioning between episodes. Returns whether the
        arm got within ``tolerance_rad`` of home before ``timeout_s``; input resumes either way.
        """
        if self._home is None:
            raise RuntimeError(f"{self.robot.name}: no home configuration was given")
        self._homing.set()
        deadline = time.monotonic() + timeout_s
        try:
            while time.monotonic() < deadline:
                if np.max(np.abs(self.robot.read_state().positions - self._home)) <= tolerance_rad:
                    return True
                time.sleep(self._period_s)
            return False
        finally:
            self._homing.clear()

    def estop(self, reason: str) -> None:
        """Latch an emergency stop through the safety chain; the next tick stops the driver."""
        self.safety.estop(reason)

    def _run(self) -> None:
        # After an input-driven tick, wait 1.5 periods before ticking without input, so a
        # slightly late sample does not cause an extra tick just before it; when idle, tick
        # at the control rate so the safety chain keeps holding or stops the robot.
        timeout = self._period_s
        try:
            while not self._stop.is_set():
                first = self._inbox.get(timeout=timeout)
                self._tick([first, *self._inbox.drain()] if first is not None else [])
                timeout = self._period_s * (1.5 if first is not None else 1.0)
        except Exception:
            log.exception("control loop of %s failed; stopping the robot", self.robot.name)
            self.robot.estop()
            raise

    def _decode_latest(self, messages: list[Message]) -> dict[str, Sample]:
        latest: dict[str, Sample] = {}
        for message in messages:
            try:
                sample = wire.decode(message.payload, arrival_ns=message.received_ns)
            except WireError as exc:
                self.stats.decode_errors += 1
                log.debug("dropped malformed message on %s: %s", message.topic, exc)
                continue
            if message.topic in latest:
                self.stats.inputs_skipped += 1
            latest[message.topic] = sample
        return latest

    def _tick(self, messages: list[Message]) -> None:
        self.stats.ticks += 1
        latest = self._decode_latest(messages) if messages else {}
        now = now_ns()
        measured = self.robot.read_state()
        if self._q_last is None:
            self._q_last = measured.positions
        requested: JointCommand | None = None
        gripper_req: GripperCommand | None = None
        arm_sample = latest.get(self._arm.topic) if self._arm is not None else None
        if self._homing.is_set() and self._home is not None:
            # Homing replaces operator input with the home target; the chain limits the motion.
            self._home_seq += 1
            stamp = Stamp(f"{self.robot.name}/home", self._home_seq, now, now)
            requested = JointCommand(stamp, self.robot.joint_names, self._home)
        elif self._arm is not None and arm_sample is not None:
            if isinstance(arm_sample, ControllerState | Pose):
                self.input_meter.add(arm_sample.stamp.capture_ns, arm_sample.stamp.seq)
                requested, ik = self._arm.retargeter(arm_sample, self._q_last, self._period_s)
                if ik.flagged:
                    self.stats.ik_flagged += 1
            else:
                self.stats.wrong_type += 1
        grip_sample = latest.get(self._gripper.topic) if self._gripper is not None else None
        if self._gripper is not None and grip_sample is not None and not self._homing.is_set():
            gripper_req = self._gripper.retargeter(grip_sample)

        out = self.safety.step(requested, now_ns=now, measured=measured)
        sent: JointCommand | None = None
        gripper_sent: GripperCommand | None = None
        if out.status == "estopped":
            self.robot.estop()
        elif out.command is not None:
            sent = self.robot.send(out.command)
            self._q_last = out.command.positions
            if requested is not None and out.status in ("ok", "limited"):
                self.latency.add(sent.stamp.capture_ns - requested.stamp.capture_ns)
                self.stats.applied += 1
            if gripper_req is not None and out.status in ("ok", "limited"):
                gripper_sent = self.robot.send_gripper(gripper_req)
        for event in out.events:
            self.stats.safety_events[event.code] = self.stats.safety_events.get(event.code, 0) + 1
        # Publishing happens after actuation so it never adds to input-to-actuation latency.
        self._publish(requested, sent, gripper_req, gripper_sent, measured)
        if out.status != self.stats.safety_status:
            self.stats.safety_status = out.status
            qos, retain = qos_for(streams.STATUS)
            self._bus.publish(self._t_status, out.status.encode(), qos=qos, retain=retain)

    def _publish(
        self,
        requested: JointCommand | None,
        sent: JointCommand | None,
        gripper_req: GripperCommand | None,
        gripper_sent: GripperCommand | None,
        measured: Sample,
    ) -> None:
        bus = self._bus
        if requested is not None:
            bus.publish(self._t_req, wire.encode(requested))
        if sent is not None:
            self.command_meter.add(sent.stamp.capture_ns)
            bus.publish(self._t_sent, wire.encode(sent))
        if gripper_req is not None:
            bus.publish(self._t_greq, wire.encode(gripper_req))
        if gripper_sent is not None:
            bus.publish(self._t_gsent, wire.encode(gripper_sent))
        bus.publish(self._t_state, wire.encode(measured))
