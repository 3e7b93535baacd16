"""Any ROS robot through a rosbridge WebSocket: joint states in, joint commands out, no ROS install."""

from __future__ import annotations

import logging
import math
import threading
from types import TracebackType

import numpy as np
from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidURI
from websockets.sync.client import ClientConnection, connect

from telerig.errors import RobotError, WireError
from telerig.ir.clock import ClockOffsetEstimator
from telerig.ir.types import FloatArray, GripperCommand, JointCommand, JointState, Stamp, now_ns
from telerig.robots.base import JointLimits
from telerig.robots.rosbridge.protocol import (
    BOOL,
    FLOAT64_MULTI_ARRAY,
    JOINT_STATE,
    JOINT_TRAJECTORY,
    CommandType,
    JointStateMsg,
    advertise,
    canonical_type,
    command_msg,
    decode,
    encode,
    parse_joint_state,
    publish,
    subscribe,
    unadvertise,
    unsubscribe,
)

__all__ = ["RosbridgeRobot"]

_log = logging.getLogger(__name__)


class _State:
    """One complete joint state in driver order, with its stamps."""

    __slots__ = ("arrival_ns", "capture_ns", "device_ns", "efforts", "positions", "velocities")

    def __init__(
        self,
        positions: FloatArray,
        velocities: FloatArray,
        efforts: FloatArray,
        device_ns: int,
        capture_ns: int,
        arrival_ns: int,
    ) -> None:
        self.positions = positions
        self.velocities = velocities
        self.efforts = efforts
        self.device_ns = device_ns
        self.capture_ns = capture_ns
        self.arrival_ns = arrival_ns


class RosbridgeRobot:
    """A ROS robot behind rosbridge_server, implementing :class:`~telerig.robots.base.RobotDriver`.

    Subscribes to ``sensor_msgs/JointState`` on ``state_topic`` and publishes joint targets on
    ``command_topic`` as a one-point ``trajectory_msgs/JointTrajectory`` (reach the target after
    ``trajectory_time_s``; for ``joint_trajectory_controller``) or a ``std_msgs/Float64MultiArray``
    in ``limits.names`` order (for ``forward_position_controller``). A thread owns the WebSocket
    and reconnects every ``reconnect_s`` after a loss, advertising and subscribing again.

    State: a JointState message must name every joint in ``limits.names`` (others are ignored);
    one that lacks some is dropped and counted (``partial``), and if no complete message arrives
    :meth:`read_state` raises a one-line error naming the missing joint. Stamps: ``device_ns`` =
    the header stamp (publisher's ROS clock), ``capture_ns`` = that mapped to host time by a
    windowed-minimum offset estimate (arrival time when the stamp is zero), ``arrival_ns`` =
    when the message was read.

    E-stop: rosbridge carries no safety-rated stop, so :meth:`estop` is a software stop: it
    publishes one command holding the current measured position, publishes ``True`` on
    ``estop_topic`` (``std_msgs/Bool``) when configured, and latches: :meth:`send` publishes
    nothing and returns the held position until :meth:`reset_estop`. Keep a hardware e-stop.

    A lost connection or no complete state for ``stale_timeout_s`` makes :meth:`read_state`
    and :meth:`send` raise a one-line :class:`~telerig.errors.RobotError` until the thread has
    reconnected and a fresh state has arrived. Malformed messages are counted and dropped.

    Args:
        url: rosbridge WebSocket URL, e.g. ``ws://192.168.1.10:9090``.
        limits: Commanded joints (names as in the robot's URDF) and their limits [rad].
        name: Driver name; the stamps' ``source_id``.
        state_topic: JointState topic.
        command_topic: Command topic of the controller.
        command_type: ``trajectory_msgs/JointTrajectory`` or ``std_msgs/Float64MultiArray``.
        trajectory_time_s: ``time_from_start`` of each trajectory point [s].
        estop_topic: ``std_msgs/Bool`` topic told about e-stops, or None.
        timeout_s: Connect (WebSocket and first state) and send timeout [s].
        stale_timeout_s: State silence that counts as lost [s].
        reconnect_s: Delay between reconnection attempts [s].
    """

    def __init__(
        self,
        url: str,
        limits: JointLimits,
        *,
        name: str = "ros_robot",
        state_topic: str = "/joint_states",
        command_topic: str = "/joint_trajectory_controller/joint_trajectory",
        command_type: CommandType = "trajectory_msgs/JointTrajectory",
        trajectory_time_s: float = 0.1,
        estop_topic: str | None = None,
        timeout_s: float = 2.0,
        stale_timeout_s: float = 0.5,
        reconnect_s: float = 0.5,
    ) -> None:
        if not url.startswith(("ws://", "wss://")):
            raise RobotError(f"url must start with ws:// or wss://, e.g. ws://192.168.1.10:9090; got {url!r}")
        if canonical_type(command_type) not in (JOINT_TRAJECTORY, FLOAT64_MULTI_ARRAY):
            raise RobotError(
                f"command_type must be {JOINT_TRAJECTORY} or {FLOAT64_MULTI_ARRAY}, got {command_type!r}"
            )
        for label, value in (
            ("trajectory_time_s", trajectory_time_s),
            ("timeout_s", timeout_s),
            ("stale_timeout_s", stale_timeout_s),
            ("reconnect_s", reconnect_s),
        ):
            if not (math.isfinite(value) and value > 0):
                raise RobotError(f"{label} must be > 0 s, got {value}")
        self._name = name
        self.url = url
        self._limits = limits
        self.state_topic = state_topic
        self.command_topic = command_topic
        self.command_type: CommandType = command_type
        self.trajectory_time_s = trajectory_time_s
        self.estop_topic = estop_topic
        self.timeout_s = timeout_s
        self.stale_timeout_s = stale_timeout_s
        self.reconnect_s = reconnect_s
        self._index = {j: i for i, j in enumerate(limits.names)}

        self._lock = threading.Lock()  # guards the fields below
        self._ws: ClientConnection | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._have_state = threading.Event()
        self._state: _State | None = None
        self._missing: tuple[str, tuple[str, ...]] | None = None  # (missing joint, names the message had)
        self._lost: str | None = None
        self._rejected: str | None = None  # why the last malformed message was dropped
        self._closed = False
        self._estopped = False
        self._hold: FloatArray = np.zeros(len(limits.names))
        self._target: FloatArray | None = None
        self._clock = ClockOffsetEstimator(reset_ns=1_000_000_000)
        self._read_seq = 0
        self._cmd_seq = 0
        self._stats: dict[str, int] = dict.fromkeys(
            (
                "messages",
                "states",
                "malformed",
                "partial",
                "status_errors",
                "ignored",
                "published",
                "connects",
            ),
            0,
        )

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
    def connected(self) -> bool:
        """Whether the WebSocket is open (the thread reconnects while it is not)."""
        return self._ws is not None and not self._closed

    @property
    def estopped(self) -> bool:
        """Whether the software e-stop is latched."""
        return self._estopped

    @property
    def stats(self) -> dict[str, int]:
        """Counters: ``messages`` received, ``states`` accepted, ``malformed`` (bad JSON or
        JointState), ``partial`` (a configured joint missing), ``status_errors`` (rosbridge
        warnings/errors), ``ignored`` (other operations or topics), ``published``, ``connects``."""
        with self._lock:
            return dict(self._stats)

    def connect(self) -> None:
        """Connect, advertise the command topic, subscribe to the state and wait for a complete state.

        Idempotent; while the thread is reconnecting after a loss, waits for it to succeed.

        Raises:
            RobotError: the driver is closed, or no complete state within ``timeout_s`` (the
                message gives the reason: refused connection, missing joint, silent topic).
        """
        if self._closed:
            raise RobotError(f"{self._name}: driver is closed; create a new one")
        starting = self._thread is None
        if starting:
            self._stop.clear()
            self._thread = threading.Thread(
                target=self._run, name=f"telerig-{self._name}-rosbridge", daemon=True
            )
            self._thread.start()
        if self._have_state.wait(self.timeout_s):
            return
        reason = self._problem() or (
            f"no {JOINT_STATE} on {self.state_topic} within {self.timeout_s:g} s ({self._received()})"
        )
        if starting:
            self._shutdown()
        raise RobotError(f"{self._name}: {reason}")

    def read_state(self) -> JointState:
        """Latest complete joint state: positions [rad], velocities [rad/s] (zeros when not
        published, 0 for a joint published as null/NaN), efforts [N m] (empty when not published
        or null/NaN for any joint). Each read is one sample: ``seq``
        counts reads (messages accepted are ``stats["states"]``).

        Raises:
            RobotError: not connected, connection lost, missing joint, or state stale.
        """
        state = self._require_state()
        with self._lock:
            # One sample per read, as every driver numbers them: a per-message number would make the
            # recorder count the messages a slower control loop never read as dropped samples.
            seq = self._read_seq
            self._read_seq += 1
        stamp = Stamp(self._name, seq, device_ns=state.device_ns, capture_ns=state.capture_ns)
        return JointState(
            stamp.arrived(state.arrival_ns),
            self.joint_names,
            state.positions,
            state.velocities,
            state.efforts,
        )

    def send(self, command: JointCommand) -> JointCommand:
        """Publish the clipped targets [rad] (any subset; the other joints keep their last target).

        While the e-stop is latched nothing is published and the held position is returned.

        Returns:
            The targets published for ``command.names`` [rad], stamped when written.

        Raises:
            RobotError: unknown joint, not connected, connection lost or state stale.
        """
        state = self._require_state()
        idx = self._indices(command.names)
        if self._estopped:
            return self._stamped(command.names, self._hold[idx])
        target = (state.positions if self._target is None else self._target).copy()
        target[idx] = np.clip(command.positions, self._limits.lower[idx], self._limits.upper[idx])
        self._publish(
            self.command_topic,
            command_msg(self.command_type, self.joint_names, target, self.trajectory_time_s),
        )
        self._target = target
        return self._stamped(command.names, target[idx])

    @property
    def has_gripper(self) -> bool:
        """Never: this driver commands joints only."""
        return False

    def send_gripper(self, command: GripperCommand) -> GripperCommand:
        """Refused: this driver commands joints only.

        Raises:
            RobotError: always, naming the fix.
        """
        raise RobotError(f"{self._name}: no gripper over rosbridge; remove the gripper from its binding")

    def estop(self) -> None:
        """Latch the software stop: publish a hold at the measured position (and ``True`` on
        ``estop_topic``), then publish nothing until :meth:`reset_estop`. Never raises; a
        failure to reach rosbridge is logged and the latch holds."""
        with self._lock:
            state = self._state
            if state is not None:
                self._hold = state.positions.copy()
            elif self._target is not None:
                self._hold = self._target.copy()
            self._estopped = True
        try:
            if state is not None:
                msg = command_msg(self.command_type, self.joint_names, self._hold, self.trajectory_time_s)
                self._publish(self.command_topic, msg)
            if self.estop_topic is not None:
                self._publish(self.estop_topic, {"data": True})
        except RobotError as exc:
            _log.error("%s: e-stop latched locally, rosbridge not reached: %s", self._name, exc)
            return
        _log.warning("%s: emergency stop latched (holding the measured position)", self._name)

    def reset_estop(self) -> None:
        """Release the latch (``False`` on ``estop_topic``); the robot holds until the next :meth:`send`.

        Raises:
            RobotError: not connected or connection lost.
        """
        state = self._require_state()
        if self.estop_topic is not None:
            self._publish(self.estop_topic, {"data": False})
        self._target = state.positions.copy()
        self._estopped = False
        _log.info("%s: emergency stop released", self._name)

    def close(self) -> None:
        """Unsubscribe, unadvertise and close the WebSocket. Idempotent."""
        if self._closed:
            return
        self._closed = True
        ws = self._ws
        if ws is not None:
            try:
                ws.send(encode(unsubscribe(self.state_topic, self._sub_id)))
                for topic in self._advertised():
                    ws.send(encode(unadvertise(topic, f"{self._name}:adv:{topic}")))
            except (ConnectionClosed, OSError):
                pass  # already gone
        self._shutdown()
        _log.info("%s: closed (%s)", self._name, self.stats)

    def __enter__(self) -> RosbridgeRobot:
        self.connect()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    # -- connection thread --------------------------------------------------------------------

    @property
    def _sub_id(self) -> str:
        return f"{self._name}:sub:{self.state_topic}"

    def _advertised(self) -> list[str]:
        return [self.command_topic] + ([self.estop_topic] if self.estop_topic else [])

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                ws = connect(
                    self.url,
                    legacy=True,
                    proxy=None,
                    compression=None,
                    open_timeout=self.timeout_s,
                    close_timeout=1.0,
                    ping_interval=None,
                )
            except (OSError, TimeoutError, InvalidHandshake, InvalidURI) as exc:
                self._lost = (
                    f"cannot reach rosbridge at {self.url} ({exc}); "
                    "check the address and that rosbridge_server runs"
                )
                self._stop.wait(self.reconnect_s)
                continue
            try:
                self._session(ws)
            except (ConnectionClosed, OSError) as exc:
                if not self._stop.is_set():
                    self._lost = f"rosbridge connection to {self.url} lost ({exc or type(exc).__name__})"
                    _log.error("%s: %s; reconnecting every %g s", self._name, self._lost, self.reconnect_s)
            finally:
                with self._lock:
                    self._ws = None
                    self._state = None
                self._have_state.clear()
                ws.close()
            self._stop.wait(self.reconnect_s)

    def _session(self, ws: ClientConnection) -> None:
        ws.send(
            encode(advertise(self.command_topic, self.command_type, f"{self._name}:adv:{self.command_topic}"))
        )
        if self.estop_topic is not None:
            ws.send(encode(advertise(self.estop_topic, BOOL, f"{self._name}:adv:{self.estop_topic}")))
        ws.send(encode(subscribe(self.state_topic, JOINT_STATE, self._sub_id)))
        self._clock.reset()
        with self._lock:
            self._ws = ws
            self._stats["connects"] += 1
            self._target = None  # re-seeded from the first state after a (re)connect
        self._lost = None
        while not self._stop.is_set():
            try:
                text = ws.recv(timeout=0.2)
            except TimeoutError:
                continue
            self._on_message(text)

    def _on_message(self, text: str | bytes) -> None:
        arrival = now_ns()
        with self._lock:
            self._stats["messages"] += 1
        try:
            op = decode(text)
            kind = op["op"]
            if kind == "publish" and op.get("topic") == self.state_topic:
                self._on_state(parse_joint_state(op.get("msg")), arrival)
            elif kind == "status":
                level = op.get("level")
                if level in ("error", "warning"):
                    with self._lock:
                        self._stats["status_errors"] += 1
                    _log.warning("%s: rosbridge %s: %s", self._name, level, op.get("msg"))
            else:
                with self._lock:
                    self._stats["ignored"] += 1
        except (WireError, TypeError, ValueError, KeyError) as exc:  # never let a message end the session
            with self._lock:
                self._stats["malformed"] += 1
                self._rejected = str(exc)
            _log.debug("%s: dropped malformed message: %s", self._name, exc)

    def _on_state(self, msg: JointStateMsg, arrival: int) -> None:
        where = {n: i for i, n in enumerate(msg.names)}
        missing = [j for j in self.joint_names if j not in where]
        if missing:
            with self._lock:
                self._stats["partial"] += 1
                self._missing = (missing[0], msg.names)
            return
        idx = [where[j] for j in self.joint_names]
        # NaN (JSON null) marks a joint without that state interface: its velocity reads as not
        # published (0), and efforts count as reported only when every joint reports one.
        velocities = (
            np.nan_to_num(msg.velocities[idx], nan=0.0) if msg.velocities.size else np.zeros(len(idx))
        )
        efforts = msg.efforts[idx] if msg.efforts.size else np.zeros(0)
        if np.isnan(efforts).any():
            efforts = np.zeros(0)
        # An unset stamp (0) has nothing to map: the arrival is the best capture estimate.
        capture = arrival if msg.stamp_ns <= 0 else msg.stamp_ns + self._clock.update(msg.stamp_ns, arrival)
        with self._lock:
            self._state = _State(msg.positions[idx], velocities, efforts, msg.stamp_ns, capture, arrival)
            self._stats["states"] += 1
            self._missing = None
        self._have_state.set()

    def _shutdown(self) -> None:
        self._stop.set()
        ws = self._ws
        if ws is not None:
            ws.close()
        thread, self._thread = self._thread, None
        if thread is not None:
            thread.join()
        self._have_state.clear()

    # -- helpers ------------------------------------------------------------------------------

    def _received(self) -> str:
        """What arrived while waiting for a state, for the connect error."""
        with self._lock:
            messages, malformed, rejected = self._stats["messages"], self._stats["malformed"], self._rejected
        if messages == 0:
            return f"nothing received; is the robot publishing {self.state_topic}?"
        if malformed and rejected is not None:
            return f"{messages} message(s) received, {malformed} rejected, the last because {rejected}"
        return f"{messages} message(s) received, none a {JOINT_STATE} on {self.state_topic}"

    def _problem(self) -> str | None:
        with self._lock:
            missing = self._missing
        if missing is not None:
            joint, names = missing
            return (
                f"joint {joint!r} missing from {self.state_topic} "
                f"(it names: {', '.join(names) or 'nothing'}); "
                "set the driver's joint names to the robot's"
            )
        return self._lost

    def _require_state(self) -> _State:
        if self._closed:
            raise RobotError(f"{self._name}: driver is closed")
        if self._thread is None:
            raise RobotError(f"{self._name}: driver is not connected; call connect() first")
        if self._ws is None:
            reason = self._lost or f"rosbridge connection to {self.url} lost"
            raise RobotError(f"{self._name}: {reason}; reconnecting every {self.reconnect_s:g} s")
        with self._lock:
            state = self._state
        age = math.inf if state is None else (now_ns() - state.arrival_ns) / 1e9
        if state is None or age > self.stale_timeout_s:
            problem = self._problem()
            if problem is not None:
                raise RobotError(f"{self._name}: {problem}")
            what = "yet" if state is None else f"for {age:.2f} s"
            raise RobotError(f"{self._name}: no complete {JOINT_STATE} on {self.state_topic} {what}")
        return state

    def _publish(self, topic: str, msg: dict[str, object]) -> None:
        ws = self._ws
        if ws is None:
            raise RobotError(f"{self._name}: {self._lost or 'not connected'}")
        try:
            ws.send(encode(publish(topic, msg)))
        except (ConnectionClosed, OSError) as exc:
            raise RobotError(f"{self._name}: publishing on {topic} failed, connection lost ({exc})") from None
        with self._lock:
            self._stats["published"] += 1

    def _indices(self, names: tuple[str, ...]) -> list[int]:
        try:
            return [self._index[n] for n in names]
        except KeyError as exc:
            raise RobotError(
                f"{self._name}: joint {exc.args[0]!r} not found. Available: {', '.join(self.joint_names)}"
            ) from None

    def _stamped(self, names: tuple[str, ...], positions: FloatArray) -> JointCommand:
        with self._lock:
            seq = self._cmd_seq
            self._cmd_seq += 1
        return JointCommand(Stamp.now(self._name, seq), names, positions)
