"""Control node: device samples from the bus → retargeting → safety chain → robot driver, per robot.

The loop is driven by input: a fresh sample is retargeted and applied at once
(so input-to-actuation latency is not padded by a fixed tick phase); when no
sample arrives within one control period the loop still ticks, so the safety
chain can hold the last command and its watchdog can stop the robot.

What plugs in (structural protocols in :mod:`telerig.retarget.binding`, no base class):

* :class:`~telerig.retarget.binding.Retargeter` turns one device stream into joint targets for
  the robot's commanded joints (arm pose IK, hand vectors, humanoid body IK, whole-body QP); its
  residual is published with every solve as a typed
  :class:`~telerig.ir.types.RetargetResidual` on ``<robot>/residual``.
* :class:`~telerig.retarget.binding.Aid` is a live supervisory control (motion scale, virtual
  fixtures) fed by button samples from any device stream and by text commands on
  ``<robot>/<stream>_command``; the node publishes its state as retained JSON on
  ``<robot>/<stream>`` whenever it changes.
* :class:`BaseBinding` drives a wheeled base for drivers implementing
  :class:`~telerig.robots.base.MobileBase`; the base is zeroed on input loss, e-stop and homing.

Besides the joint state, every tick publishes what the driver measures beyond its joints, where it
has the capability (:mod:`telerig.robots.base`): the gripper's opening (``gripper_state``), a
force/torque sensor (``wrench``) and a floating pelvis or base pose (``base_pose``), read after
actuation so they never add to input-to-actuation latency.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import partial

import numpy as np

from telerig import priority
from telerig.bus.base import Bus, Inbox, Message, MessageHandler
from telerig.bus.catalogue import CONTROL_SOURCE, COORDINATOR, SESSION
from telerig.bus.topics import Topic, node_of, qos_for
from telerig.config.latency import StageName
from telerig.devices.validate import REJECT_REASONS, SampleGate
from telerig.errors import WireError
from telerig.ir import wire
from telerig.ir.types import (
    BaseVelocity,
    ControlKind,
    ControllerState,
    ControlSource,
    FloatArray,
    GripperCommand,
    JointCommand,
    RetargetResidual,
    Sample,
    Stamp,
    now_ns,
)
from telerig.retarget.base_drive import BaseDrive
from telerig.retarget.binding import Aid, GripperRetargeter, Residual, Retargeter
from telerig.robots.base import (
    GripperSensor,
    MobileBase,
    ObjectSensor,
    RobotDriver,
    StandingRobot,
    WrenchSensor,
)
from telerig.runtime import streams
from telerig.runtime.control_health import ControlHealth
from telerig.runtime.handover import Handover, Source
from telerig.runtime.metrics import LatencyTracker, StreamMeter
from telerig.runtime.session import SessionStatus
from telerig.safety import Deadman, RobotSafety, SafetyChain, SafetySupervisor
from telerig.safety.commands import parse_payload

__all__ = [
    "AidBinding",
    "FeedBinding",
    "BaseBinding",
    "ControlNode",
    "ControlStats",
    "DeadmanBinding",
    "GripperBinding",
    "JointsBinding",
]

log = logging.getLogger(__name__)

#: After a tick driven by input, how many control periods the loop waits for the next sample
#: before it ticks without one (holding): a little over one, so a sample a few ms late still drives
#: the next tick, yet the robot never goes much longer than a period without a command (with
#: 1.5 the fleet benchmark counted 5-10 missed ticks per 20 s from late inputs alone; with 1.25
#: none are left from late inputs).
_LATE_INPUT_GRACE = 1.25
#: Measured opening (0 closed, 1 open) at which a homing gripper counts as open.
_GRIPPER_OPEN = 0.95


@dataclass(frozen=True, slots=True)
class JointsBinding:
    """Device stream topic whose samples drive the robot's commanded joints."""

    topic: str
    retargeter: Retargeter


@dataclass(frozen=True, slots=True)
class AidBinding:
    """Device stream topic whose buttons operate a live aid."""

    topic: str
    aid: Aid


@dataclass(frozen=True, slots=True)
class FeedBinding:
    """Device stream topic whose latest sample ``take`` keeps each tick it has a fresh one (e.g. a
    :class:`~telerig.retarget.reach_plan.PlanMarker`: stored, not acted on, on the control tick)."""

    topic: str
    take: Callable[[Sample], None]


@dataclass(frozen=True, slots=True)
class BaseBinding:
    """Device stream topic whose controller buttons and thumbstick drive a wheeled base."""

    topic: str
    drive: BaseDrive


@dataclass(frozen=True, slots=True)
class DeadmanBinding:
    """Device stream topic whose button enables commands (a deadman/enable switch).

    Attributes:
        button: ``ControllerState.buttons`` name, or ``"trigger"`` / ``"grip"`` for the analog inputs.
        threshold: Analog inputs count as held at or above it.
    """

    topic: str
    button: str
    threshold: float
    deadman: Deadman

    def feed(self, latest: dict[str, Sample], now_ns: int) -> None:
        """Update the deadman from this tick's sample on ``topic``, if any (silence times it out)."""
        sample = latest.get(self.topic)
        if isinstance(sample, ControllerState):
            if self.button == "trigger":
                held = sample.trigger >= self.threshold
            elif self.button == "grip":
                held = sample.grip >= self.threshold
            else:
                held = self.button in sample.buttons
            self.deadman.update(held, now_ns)


@dataclass(frozen=True, slots=True)
class GripperBinding:
    """Device stream topic whose samples (controller trigger, hand pinch) drive the gripper."""

    topic: str
    retargeter: GripperRetargeter


def _no_rejections() -> dict[str, int]:
    return dict.fromkeys(REJECT_REASONS, 0)


@dataclass(slots=True)
class ControlStats:
    """Counters of one control node.

    Attributes:
        rejected: Decoded input samples its :class:`~telerig.devices.validate.SampleGate` rejected,
            per :data:`~telerig.devices.validate.RejectReason` (every reason present).
        tick_faults: Control ticks that raised; each latched a ``driver_fault`` e-stop (counted in
            the chain's ``counts`` on the next tick) and the loop went on.
        paused_inputs: Samples of paused input devices dropped (``paused_devices`` of the session).
        bad_session: Session status messages dropped as malformed.
    """

    ticks: int = 0
    applied: int = 0
    decode_errors: int = 0
    rejected: dict[str, int] = field(default_factory=_no_rejections)
    tick_faults: int = 0
    wrong_type: int = 0
    ik_flagged: int = 0
    inputs_skipped: int = 0
    aid_changes: int = 0
    bad_commands: int = 0
    base_stops: int = 0
    paused_inputs: int = 0
    bad_session: int = 0
    handovers: int = 0
    safety_status: str = "idle"
    safety_events: dict[str, int] = field(default_factory=dict)


class ControlNode:
    """Runs the control loop of one robot on its own thread.

    Args:
        rig: Rig name (topic prefix).
        robot: The driver to command; connected by the caller.
        safety: The robot's safety chain, always between retargeting and ``robot``; or the robot's
            entry in the rig's :class:`~telerig.safety.SafetySupervisor` (every driver call then goes
            through it, so a driver fault stops this robot and applies the rig's fault policy).
            A bare chain gets a supervisor of its own (``pause_affected``).
        bus: Bus client of this node.
        control_rate_hz: Nominal command rate [Hz]; also the idle tick rate.
        joints: Optional binding that drives the commanded joints.
        gripper: Optional gripper binding.
        home: Safe joint configuration [rad] that :meth:`go_home` drives to. Shape (n,).
        deadman: Optional enable button: commands pass only while it is held (see
            :class:`~telerig.safety.Deadman`); it must also be the chain's deadman.
        aids: Live supervisory controls and the device streams whose buttons operate them, and
            feeds (:class:`FeedBinding`: a stream whose latest sample a part keeps, e.g. a plan marker).
        base: Optional wheeled-base binding; ``robot`` must implement
            :class:`~telerig.robots.base.MobileBase`.
        gate: Validation of every decoded input sample before anything consumes it;
            ``SampleGate(f"control {robot.name}")`` when None.
        latency_budgets: p99 budget per latency stage [ms] (the rig's ``latency.budgets_ms``) that
            the live report on ``<robot>/latency`` judges each stage by; defaults when None.
        handover: Several sources (a policy, an operator who takes over) of the joints and gripper,
            instead of ``joints`` / ``gripper``: each tick it names the one that drives, a change
            re-anchors the incoming source, and who drove is published on ``control_source``
            (:mod:`telerig.runtime.handover`).

    Every decoded sample passes the gate (finite values, normalizable quaternions, plausible
    capture times) before retargeting, gripper, base, aids or deadman see it; a rejected one is
    counted in ``stats.rejected`` and dropped. An exception inside a tick is a fault of that tick:
    it is counted (``stats.tick_faults``), the robot is stopped through its safety supervisor
    (``driver_fault``, alert and fault policy) and the loop goes on, so a reset resumes control.

    Per-device pause (seed 000): the node follows the session's ``paused_devices`` (retained on
    ``R/coordinator/session``, which only stations publish). Samples of a paused device are dropped
    (``stats.paused_inputs``); while the device driving the joints is paused, the chain is fed the
    pose the robot had when the pause reached it, so the robot holds it with fresh input (no
    watchdog stop) while other robots go on. On resume the retargeter re-anchors (relative mode:
    on the next clutch press, from the current end effector) and the chain restarts from the
    measured state through its start-up ramp, so the robot never jumps to where the hand went.

    Raises:
        ValueError: ``base`` is given but the driver has no ``send_base``.
    """

    def __init__(
        self,
        rig: str,
        robot: RobotDriver,
        safety: SafetyChain | RobotSafety,
        bus: Bus,
        *,
        control_rate_hz: float,
        joints: JointsBinding | None = None,
        gripper: GripperBinding | None = None,
        home: FloatArray | None = None,
        aids: Sequence[AidBinding | FeedBinding] = (),
        base: BaseBinding | None = None,
        deadman: DeadmanBinding | None = None,
        gate: SampleGate | None = None,
        latency_budgets: Mapping[StageName, float] | None = None,
        handover: Handover | None = None,
    ) -> None:
        if base is not None and not isinstance(robot, MobileBase):
            raise ValueError(
                f"robot {robot.name!r} has no mobile base (no send_base); bind its base to a mobile robot"
            )
        self.rig = rig
        self.robot = robot
        if isinstance(safety, SafetyChain):
            safety = SafetySupervisor("pause_affected").add(robot.name, robot, safety)
        self._rs = safety
        self.safety = safety.chain
        self._deadman = deadman
        self._gate = gate if gate is not None else SampleGate(f"control {robot.name}")
        self._bus = bus
        self._period_s = 1.0 / control_rate_hz
        self._handover = handover
        if handover is not None:
            if joints is not None or gripper is not None:
                raise ValueError("give the joints and gripper either as bindings or through the handover")
            self._source_parts = {id(s): _source_bindings(s) for s in handover.sources}
            # The lowest priority until the first tick selects.
            joints, gripper = self._source_parts[id(handover.sources[-1])]
        self._joints = joints
        self._gripper = gripper
        self._aids = tuple(b for b in aids if isinstance(b, AidBinding))
        self._feeds = tuple(b for b in aids if isinstance(b, FeedBinding))
        self._base = base
        self._base_seen_ns = 0
        self._base_moving = False
        self._commands: deque[tuple[Aid, str]] = deque(maxlen=64)
        name = robot.name
        self._t_aid = {id(b.aid): str(Topic(rig, name, b.aid.stream)) for b in self._aids}
        self._inbox = Inbox()
        self._subs = [bus.subscribe(t, self._inbox) for t in sorted(self._topics())]
        command_aids: list[Aid] = list({id(b.aid): b.aid for b in self._aids}.values())
        if handover is not None:
            self._t_aid[id(handover)] = str(Topic(rig, name, handover.stream))
            command_aids.append(handover)
        for aid in command_aids:
            self._subs.append(
                bus.subscribe(str(Topic(rig, name, f"{aid.stream}_command")), self._on_command(aid))
            )
        self._control_seq = 0  # ``stamp.seq`` of this node's ControlSource samples
        self._control_id = name  # their ``stamp.source_id``: the robot (the recorder checks it)
        self._residual_seq = 0  # ``stamp.seq`` of this node's RetargetResidual samples
        # Topics of paused devices: set on the bus thread, applied by the control thread.
        self._paused: frozenset[str] = frozenset()
        self._paused_applied: frozenset[str] = frozenset()
        self._pause_hold: FloatArray | None = None
        self._pause_seq = 0
        self._subs.append(bus.subscribe(str(Topic(rig, COORDINATOR, SESSION)), self._on_session, qos=1))
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._q_last: FloatArray | None = None
        self._home = None if home is None else np.array(home, dtype=np.float64)
        self._homing = threading.Event()
        self._home_opens_gripper = False  # set by go_home before _homing, read by the tick
        self._home_seq = 0
        self.stats = ControlStats()
        self.latency = LatencyTracker()
        self.input_meter = StreamMeter("input", control_rate_hz)
        self.command_meter = StreamMeter("commands", control_rate_hz)
        #: Live input-to-actuation latency, reported on ``<robot>/health`` at 2 Hz while running.
        self.live = ControlHealth(
            rig, name, bus, hold_ms=self.safety.watchdog.hold_timeout_ns / 1e6, budgets_ms=latency_budgets
        )
        # When this node's MQTT client received the latest sample of each topic [ns] (the ``bus``
        # latency stage ends there); the sample keeps the arrival its device node stamped.
        self._received_ns: dict[str, int] = dict.fromkeys(self._topics(), 0)
        self._t_status = str(Topic(rig, name, streams.STATUS))
        # A tick's IR samples (commands, state, sensors, residual, who drove) go out together as
        # one Bundle on ``tick`` at the end of the tick (telerig.bus.ticks): one MQTT message per
        # tick instead of one per stream.
        self._t_tick = str(Topic(rig, name, streams.TICK))
        self._tick_parts: list[tuple[str, bytes]] = []
        self._sensors = _sensors(robot)

    @property
    def handover(self) -> Handover | None:
        """Who drives the joints and gripper when several sources (or a policy) are bound; else None."""
        return self._handover

    @property
    def sensed_streams(self) -> tuple[str, ...]:
        """The measurement streams beyond ``joint_state`` this node publishes every tick (e.g.
        ``gripper_state``, ``wrench``, ``base_pose``): what its driver can measure."""
        return tuple(stream for stream, _ in self._sensors)

    @property
    def bound_topics(self) -> dict[str, str | None]:
        """The device stream driving each robot part (``joints``, ``gripper``, ``base``); None if unbound."""
        return {
            "joints": None if self._joints is None else self._joints.topic,
            "gripper": None if self._gripper is None else self._gripper.topic,
            "base": None if self._base is None else self._base.topic,
        }

    def _topics(self) -> set[str]:
        topics = {b.topic for b in (self._joints, self._gripper, self._base, self._deadman) if b is not None}
        if self._handover is not None:
            topics |= self._handover.topics
        return topics | {b.topic for b in self._aids} | {b.topic for b in self._feeds}

    def _on_command(self, aid: Aid) -> MessageHandler:
        def handle(message: Message) -> None:
            # Runs on the bus thread: queue it; the control thread applies it at its next tick.
            self._commands.append((aid, message.payload.decode("utf-8", "replace")))

        return handle

    def _on_session(self, message: Message) -> None:
        # Bus thread: only the set of paused topics changes here; the control thread applies it.
        status = parse_payload(SessionStatus, message)
        if isinstance(status, str):
            self.stats.bad_session += 1
            log.warning("%s: dropped a malformed session status: %s", self.robot.name, status)
            return
        devices = set(status.paused_devices)
        self._paused = frozenset(t for t in self._topics() if node_of(t) in devices)

    @property
    def paused_topics(self) -> frozenset[str]:
        """The bound device streams whose device is paused now (as the control thread applies it)."""
        return self._paused_applied

    def start(self) -> None:
        """Start the control thread; idempotent."""
        if self._thread is None:
            for binding in self._aids:
                self._publish_aid(binding.aid)
            if self._handover is not None:
                self._publish_aid(self._handover)  # who may drive, before anyone does
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name=f"control-{self.robot.name}", daemon=True)
            self._thread.start()
            self.live.start()

    def stop(self) -> None:
        """Stop the control thread (the robot holds its last command); idempotent."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        self.live.stop()
        if self._base is not None and self._base_moving:
            self._send_base(self._base.drive.stop(now_ns()))
        for sub in self._subs:
            sub.cancel()
        self._subs = []

    @property
    def alive(self) -> bool:
        """Whether the control thread is running."""
        thread = self._thread
        return thread is not None and thread.is_alive()

    @property
    def has_home(self) -> bool:
        """Whether :meth:`go_home` knows a home configuration."""
        return self._home is not None

    def go_home(
        self, *, timeout_s: float = 15.0, tolerance_rad: float = 0.02, open_gripper: bool = False
    ) -> bool:
        """Drive the arm to its home configuration through the safety chain, ignoring operator input.

        Used to reset the robot for safe repositioning between episodes. With ``open_gripper``
        (a task's scene reset, which puts the objects back anyway) the gripper opens on the way
        and, where the driver measures it, homing also waits until it reads open, so every
        episode starts from the same robot state whatever the last one held. Returns whether the
        arm (and that gripper) got home before ``timeout_s``; input resumes either way.
        """
        if self._home is None:
            raise RuntimeError(f"{self.robot.name}: no home configuration was given")
        robot = self.robot
        opens = open_gripper and robot.has_gripper
        sensor = robot if opens and isinstance(robot, GripperSensor) else None
        self._home_opens_gripper = opens
        self._homing.set()
        deadline = time.monotonic() + timeout_s
        try:
            while time.monotonic() < deadline:
                state = self._rs.read_state()
                if state is None:
                    return False  # the driver faulted; the supervisor stopped it
                home = np.max(np.abs(state.positions - self._home)) <= tolerance_rad
                if home and (sensor is None or sensor.read_gripper().opening >= _GRIPPER_OPEN):
                    return True
                time.sleep(self._period_s)
            return False
        finally:
            self._homing.clear()
            self._home_opens_gripper = False

    def estop(self, reason: str) -> None:
        """Latch an emergency stop through the safety chain; the next tick stops the driver."""
        self.safety.estop(reason)

    def fault(self, reason: str) -> None:
        """Report a hardware fault of this robot: stop it now and apply the rig's fault policy."""
        self._rs.fault(reason)

    def _run(self) -> None:
        # Above the station's other threads and its render processes, where the host allows it.
        priority.enter("control")
        # After an input-driven tick, allow a quarter period more before ticking without input, so
        # a slightly late sample does not cause an extra tick just before it; when idle, tick at
        # the control rate so the safety chain keeps holding or stops the robot. Deadlines count
        # from the start of a tick, so the tick's own duration does not stretch the period.
        period = self._period_s
        deadline = time.monotonic() + period
        try:
            while not self._stop.is_set():
                first = self._inbox.get(timeout=max(0.0, deadline - time.monotonic()))
                started = time.monotonic()
                try:
                    self._tick([first, *self._inbox.drain()] if first is not None else [])
                except Exception as exc:
                    self._tick_failed(exc)
                    self._publish_tick()  # what it made before it raised: a command it applied
                deadline = started + period * (_LATE_INPUT_GRACE if first is not None else 1.0)
        except Exception:
            log.exception("control loop of %s failed; stopping the robot", self.robot.name)
            self._rs.fault(f"the control loop of {self.robot.name} failed")
            raise

    def _tick_failed(self, exc: Exception) -> None:
        """A tick raised: count it, stop the robot through the supervisor, forget retargeting state."""
        self.stats.tick_faults += 1
        name = self.robot.name
        reason = f"a control tick of {name} failed ({type(exc).__name__}: {exc})"
        if not self.safety.estopped or self.stats.tick_faults == 1:
            # A bug, not bad input (the gate drops that): the traceback once per latch, to fix it.
            log.error("%s; stopping the robot, `telerig safety reset` resumes control", reason, exc_info=exc)
        else:
            log.debug("%s (already stopped)", reason)
        self._rs.fault(reason)
        if self._joints is not None:
            try:
                self._joints.retargeter.reset()  # its state may be half-updated; re-anchor on fresh input
            except Exception as reset_exc:
                log.debug("%s: retargeter reset failed: %s", name, reset_exc)

    def _decode_latest(self, messages: list[Message], now: int) -> dict[str, Sample]:
        latest: dict[str, Sample] = {}
        gate = self._gate
        for message in messages:
            try:
                decoded = wire.decode(message.payload)
            except WireError as exc:
                self.stats.decode_errors += 1
                log.debug("dropped malformed message on %s: %s", message.topic, exc)
                continue
            sample = gate.admit(message.topic, decoded, now)
            if isinstance(sample, str):
                self.stats.rejected[sample] += 1
                continue
            if message.topic in latest:
                self.stats.inputs_skipped += 1
            latest[message.topic] = sample
            self._received_ns[message.topic] = message.received_ns
        return latest

    def _tick(self, messages: list[Message]) -> None:
        self.stats.ticks += 1
        now = now_ns()
        latest = self._decode_latest(messages, now) if messages else {}
        if self._paused or self._paused_applied:
            self._apply_pause(latest)
        if self._deadman is not None:
            self._deadman.feed(latest, now)
        measured = self._rs.read_state()  # None when the driver raised: the chain latches a fault
        if measured is not None:
            self.live.measured(measured.stamp.capture_ns, now)
        if self._q_last is None and measured is not None:
            self._q_last = measured.positions
        changed_aids = self._update_aids(latest)
        handover = self._handover
        if handover is not None and self._select_source(latest, now) and handover not in changed_aids:
            changed_aids.append(handover)
        requested: JointCommand | None = None
        residual: Residual | None = None
        gripper_req: GripperCommand | None = None
        homing = self._homing.is_set()
        joint_sample = latest.get(self._joints.topic) if self._joints is not None else None
        retargeted_ns = 0  # when the retargeter returned this tick's targets (the ``retarget`` stage)
        if homing and self._home is not None:
            # Homing replaces operator input with the home target; the chain limits the motion.
            self._home_seq += 1
            stamp = Stamp(f"{self.robot.name}/home", self._home_seq, now, now)
            requested = JointCommand(stamp, self.robot.joint_names, self._home)
            if self._joints is not None:
                self._joints.retargeter.reset()  # relative mode re-anchors on the next clutch press
        elif (
            self._joints is not None
            and self._joints.topic in self._paused_applied
            and self._q_last is not None
        ):
            # The joints' device is paused: hold the pose the robot had then, as fresh input.
            if self._pause_hold is None:
                self._pause_hold = self._q_last.copy()
            self._pause_seq += 1
            stamp = Stamp(f"{self.robot.name}/pause", self._pause_seq, now, now)
            requested = JointCommand(stamp, self.safety.limits.names, self._pause_hold)
        elif self._joints is not None and joint_sample is not None and self._q_last is not None:
            retargeter = self._joints.retargeter
            if isinstance(joint_sample, retargeter.accepts):
                self.input_meter.add(joint_sample.stamp.capture_ns, joint_sample.stamp.seq)
                requested, residual = retargeter(joint_sample, self._q_last, self._period_s)
                retargeted_ns = now_ns()
                if residual is not None and residual.flagged:
                    self.stats.ik_flagged += 1
            else:
                self.stats.wrong_type += 1
        grip_sample = latest.get(self._gripper.topic) if self._gripper is not None else None
        if homing and self._home_opens_gripper:
            gripper_req = GripperCommand(
                Stamp(f"{self.robot.name}/home", self._home_seq, now, now), opening=1.0
            )
        elif self._gripper is not None and grip_sample is not None and not homing:
            gripper_req = self._gripper.retargeter(grip_sample)

        out = self._rs.step(requested, now_ns=now, measured=measured)
        sent: JointCommand | None = None
        gripper_sent: GripperCommand | None = None
        # Joints that nothing drives get no command: on a gripper alone its one joint is the gripper's,
        # and the chain's stop command (the position measured at start, open) pulled the fingers off
        # the gripper input on every tick without a fresh gripper sample.
        drives_joints = self._joints is not None or homing
        # An e-stopped output has no command: the supervisor already stopped the driver.
        if out.command is not None:
            if drives_joints:
                sent = self._rs.send(out.command)  # None when the driver raised (a fault is latched)
            self._q_last = out.command.positions
            holding = (
                self._pause_hold is not None
                and requested is not None
                and requested.stamp.source_id.endswith("/pause")
            )
            if sent is not None and requested is not None and out.status in ("ok", "limited") and not holding:
                self.latency.add(sent.stamp.capture_ns - requested.stamp.capture_ns)
                self._live_sent(
                    requested.stamp.capture_ns, sent.stamp.capture_ns, now, joint_sample, retargeted_ns
                )
                self.stats.applied += 1
            # The gripper follows only while the joints track fresh input (it holds with them); a
            # robot whose joints nothing drives (a gripper alone) follows its gripper input directly.
            tracking = out.status in ("ok", "limited") or self._joints is None
            if (sent is not None or not drives_joints) and gripper_req is not None and tracking:
                gripper_sent = self._send_gripper(gripper_req)
        base_req = self._base_command(latest, now, halt=homing or out.status == "estopped")
        if base_req is not None:
            self._send_base(base_req)
        for event in out.events:
            self.stats.safety_events[event.code] = self.stats.safety_events.get(event.code, 0) + 1
        # Publishing happens after actuation so it never adds to input-to-actuation latency.
        self._publish(requested, sent, gripper_req, gripper_sent, measured)
        self._publish_sensed()
        if residual is not None and requested is not None:
            self._publish_residual(requested.stamp.capture_ns, residual)
        if base_req is not None:
            self._tick_parts.append((streams.BASE_REQUESTED, wire.encode(base_req)))
        if self._handover is not None:
            self._publish_control(now, homing=homing)
        self._publish_tick()
        for aid in changed_aids:
            self._publish_aid(aid)
        if out.status != self.stats.safety_status:
            self.stats.safety_status = out.status
            qos, retain = qos_for(streams.STATUS)
            self._bus.publish(self._t_status, out.status.encode(), qos=qos, retain=retain)

    def _live_sent(
        self, capture_ns: int, sent_ns: int, now: int, sample: Sample | None, retargeted_ns: int
    ) -> None:
        """Feed the live latency report one applied command (its stages when it came from ``sample``)."""
        if sample is None or not retargeted_ns or self._joints is None:
            self.live.sent(capture_ns, sent_ns, now)  # homing: no input stages
            return
        received = self._received_ns.get(self._joints.topic, 0)
        self.live.sent(
            capture_ns,
            sent_ns,
            now,
            arrival_ns=sample.stamp.arrival_ns,
            received_ns=received,
            retargeted_ns=retargeted_ns,
        )

    def _select_source(self, latest: dict[str, Sample], now: int) -> bool:
        """Let the handover pick this tick's source; on a change, re-anchor the incoming one."""
        assert self._handover is not None
        source, switched = self._handover.select(latest, now)
        if source is None:
            return False
        self._joints, self._gripper = self._source_parts[id(source)]
        if switched:
            self.stats.handovers += 1
            if self._joints is not None:
                # Relative mode anchors on the current end effector; a policy blends in from here.
                self._joints.retargeter.reset()
            if source.kind == "policy":
                self.safety.hand_over()  # from the last command, through the start-up ramp
            log.info("%s: control handed to %s (%s)", self.robot.name, source.device, source.kind)
        return switched

    def _publish_control(self, now: int, *, homing: bool) -> None:
        """Who drove the robot this tick, as a :class:`ControlSource` on ``control_source`` (recorded).

        A typed sample through the reused wire message rather than a JSON object: the recorder checks
        its type, source and sequence like any robot stream, and encoding it allocates about a
        quarter of what ``json.dumps`` of the dict did (benchmarks/wire_codec.py; CPU is alike).
        """
        handover = self._handover
        assert handover is not None
        active = handover.active
        source: str | None
        kind: ControlKind
        if homing:
            source, kind = "home", "home"
        elif active is None:
            source, kind = None, "none"
        else:
            source, kind = active.device, active.kind
            if self._joints is not None and self._joints.topic in self._paused_applied:
                kind = "paused"
        self._control_seq += 1
        stamp = Stamp(self._control_id, self._control_seq, now, now)
        sample = ControlSource(stamp, source, kind, handover.mode)
        self._tick_parts.append((CONTROL_SOURCE, wire.encode(sample)))

    def _apply_pause(self, latest: dict[str, Sample]) -> None:
        """Drop this tick's samples of paused devices; start or end the joints' hold on a change."""
        paused = self._paused
        if paused != self._paused_applied:
            joints = None if self._joints is None else self._joints.topic
            if joints in paused and joints not in self._paused_applied:
                self._pause_hold = None  # the next tick holds the pose the robot has then
            elif joints in self._paused_applied and joints not in paused and self._joints is not None:
                self._pause_hold = None
                self._joints.retargeter.reset()  # re-anchor on the next sample (or clutch press)
                self.safety.restart()  # from the measured state, through the start-up ramp
            self._paused_applied = paused
        for topic in [t for t in latest if t in paused]:
            del latest[topic]
            self.stats.paused_inputs += 1

    def _send_gripper(self, command: GripperCommand) -> GripperCommand | None:
        # Through the safety layer: limits, nothing while e-stopped, a raising driver is a fault.
        return self._rs.send_gripper(command)

    def _update_aids(self, latest: dict[str, Sample]) -> list[Aid]:
        """Apply queued bus commands, then this tick's button samples, then hand the feeds their fresh
        samples; return the aids that changed."""
        changed: list[Aid] = []
        while self._commands:
            aid, text = self._commands.popleft()
            try:
                if aid.command(text) and aid not in changed:
                    changed.append(aid)
            except ValueError as exc:
                self.stats.bad_commands += 1
                log.warning("%s: ignored %s command: %s", self.robot.name, aid.stream, exc)
        for binding in self._aids:
            sample = latest.get(binding.topic)
            if sample is not None and binding.aid.update(sample) and binding.aid not in changed:
                changed.append(binding.aid)
        for feed in self._feeds:
            sample = latest.get(feed.topic)
            if sample is not None:
                feed.take(sample)
        self.stats.aid_changes += len(changed)
        return changed

    def _base_command(self, latest: dict[str, Sample], now: int, *, halt: bool) -> BaseVelocity | None:
        """This tick's base command: from a fresh sample, or zero on input loss or ``halt``; None for none."""
        if self._base is None:
            return None
        drive = self._base.drive
        sample = latest.get(self._base.topic)
        command = drive(sample) if sample is not None else None
        if sample is not None and command is None:
            self.stats.wrong_type += 1
        if command is not None:
            self._base_seen_ns = now
        lost = command is None and self._base_moving and drive.expired(self._base_seen_ns, now)
        if lost or (halt and (command is not None or self._base_moving)):
            self.stats.base_stops += int(self._base_moving)
            return drive.stop(now)
        return command

    def _send_base(self, command: BaseVelocity) -> BaseVelocity | None:
        # Through the safety layer: speed and acceleration limits, a stop while e-stopped; None
        # when the driver raised (a fault is latched; the next tick sends a stop again).
        sent = self._rs.send_base(command, now_ns=now_ns())
        if sent is None:
            return None
        self._base_moving = (sent.vx, sent.vy, sent.wz) != (0.0, 0.0, 0.0)
        self._tick_parts.append((streams.BASE_SENT, wire.encode(sent)))
        return sent

    def _publish_sensed(self) -> None:
        """Read and publish the driver's other measurements (a raising read is a driver fault)."""
        sense, parts = self._rs.sense, self._tick_parts
        for stream, read in self._sensors:
            sample = sense(read, stream)
            if sample is not None:
                parts.append((stream, wire.encode(sample)))

    def _publish_tick(self) -> None:
        """Publish what this tick made as one Bundle on ``tick`` (nothing when it made nothing)."""
        parts = self._tick_parts
        if parts:
            self._bus.publish(self._t_tick, wire.encode_bundle(parts))
            parts.clear()

    def _publish_residual(self, capture_ns: int, residual: Residual) -> None:
        """The retargeter's residual of this tick's solve as a :class:`RetargetResidual` on
        ``residual`` (recorded; the scene draws ``flagged``), stamped by the robot with the input
        sample's capture time [ns].

        A typed sample through the reused wire message rather than a JSON object: the metric names
        are written into the message once (a retargeter's names do not change), each tick writes
        only the flag and the values, and the recorder checks its type, source and sequence like
        any robot stream (numbers: benchmarks/wire_codec.py).
        """
        metrics = residual.metrics()
        self._residual_seq += 1
        stamp = Stamp(self._control_id, self._residual_seq, capture_ns, capture_ns)
        sample = RetargetResidual(stamp, residual.flagged, tuple(metrics), tuple(metrics.values()))
        self._tick_parts.append((streams.RESIDUAL, wire.encode(sample)))

    def _publish_aid(self, aid: Aid) -> None:
        payload = json.dumps(aid.state()).encode()
        self._bus.publish(self._t_aid[id(aid)], payload, qos=1, retain=True)

    def _publish(
        self,
        requested: JointCommand | None,
        sent: JointCommand | None,
        gripper_req: GripperCommand | None,
        gripper_sent: GripperCommand | None,
        measured: Sample | None,
    ) -> None:
        parts = self._tick_parts
        if requested is not None:
            parts.append((streams.JOINT_REQUESTED, wire.encode(requested)))
        if sent is not None:
            self.command_meter.add(sent.stamp.capture_ns)
            parts.append((streams.JOINT_SENT, wire.encode(sent)))
        if gripper_req is not None:
            parts.append((streams.GRIPPER_REQUESTED, wire.encode(gripper_req)))
        if gripper_sent is not None:
            parts.append((streams.GRIPPER_SENT, wire.encode(gripper_sent)))
        if measured is not None:
            parts.append((streams.JOINT_STATE, wire.encode(measured)))


def _source_bindings(source: Source) -> tuple[JointsBinding | None, GripperBinding | None]:
    """The joints and gripper bindings of one handover source."""
    joints = None if source.joints is None else JointsBinding(source.topic, source.joints)
    gripper = None if source.gripper is None else GripperBinding(source.topic, source.gripper)
    return joints, gripper


def _sensors(robot: RobotDriver) -> tuple[tuple[str, Callable[[], Sample]], ...]:
    """The measurements ``robot`` offers beyond its joint state: (stream, read) pairs, in a fixed order."""
    sensors: list[tuple[str, Callable[[], Sample]]] = []
    if isinstance(robot, GripperSensor) and robot.has_gripper:
        sensors.append((streams.GRIPPER_STATE, robot.read_gripper))
    if isinstance(robot, WrenchSensor) and robot.has_wrench_sensor:
        sensors.append((streams.WRENCH, robot.read_wrench))
    if isinstance(robot, StandingRobot) and robot.floating_base:
        sensors.append((streams.BASE_POSE, robot.read_base_pose))
    if isinstance(robot, ObjectSensor):
        # One entry per task object: each tick publishes every object's pose on one stream.
        sensors.extend(
            (streams.OBJECT_POSE, partial(robot.read_object_pose, o)) for o in robot.observed_objects
        )
    return tuple(sensors)
