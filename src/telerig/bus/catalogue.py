"""The stream catalogue: every bus stream's name, payload kind, QoS, retention, rate, size and publisher.

Topics are ``telerig/v1/<rig>/<node>/<stream>``. A node has a role (a device, a robot's control
node, a camera, the coordinator, a station, a recorder, a safety supervisor, the broker
watchdog), and each role publishes the streams listed here. This module is the one place the
vocabulary lives: devices and control nodes name their streams from it, the recorder decodes
by it (never by trying), QoS and retention come from it, and the broker's ACL can be derived
from it.

=================================  ==========  ====================  ====  ======  ==================
stream                             node role   payload               QoS   retain  rate
=================================  ==========  ====================  ====  ======  ==================
``<side>_controller`` etc.         device      IR device sample      0     no      device rate
``health``                         device      JSON object           1     yes     ~1 Hz
``events``                         device      JSON object (alert)   1     no      on event
``command``                        device      JSON object           1     no      on demand
``page_in`` ``page_out``           device      relayed page (binary) 0     no      page rate
``joint_command_requested``        robot       IR JointCommand       0     no      input rate
``joint_command_sent``             robot       IR JointCommand       0     no      control rate
``gripper_command_requested/sent`` robot       IR GripperCommand     0     no      input rate
``base_command_requested/sent``    robot       IR BaseVelocity       0     no      control rate
``joint_state``                    robot       IR JointState         0     no      control rate
``gripper_state``                  robot       IR GripperCommand     0     no      control rate
``wrench``                         robot       IR Wrench             0     no      control rate
``base_pose``                      robot       IR Pose               0     no      control rate
``object_pose``                    robot       IR Pose (per object)  0     no      control rate
``status``                         robot       text (safety status)  1     yes     on change
``residual``                       robot       IR RetargetResidual   0     no      input rate
``tick``                           robot       Bundle of the above   0     no      control rate
``health``                         robot       JSON (not recorded)   1     yes     2 Hz
``latency``                        robot       JSON (stages p50/p99) 1     yes     2 Hz
``latency_view``                   robot/cam.  JSON (browser stages) 1     yes     2 Hz (``web``)
``alerts``                         robot       JSON (latency budget) 1     yes     on change
``motion_scale`` ``fixture``       robot       JSON object (aid)     1     yes     on change
``wbc_mode``                       robot       JSON object (aid)     1     yes     on change
``plan``                           robot       JSON object (aid)     1     yes     on change
``<aid>_command``                  robot       text (operator)       0     no      on demand
``control``                        robot       JSON object (aid)     1     yes     on change
``control_source``                 robot       IR ControlSource      0     no      control rate
``frames``                         camera      IR CameraFrame        0     no      camera fps
``preview``                        camera      JPEG (not recorded)   0     no      ~2 Hz
``observation``                    camera      raw RGB (not rec.)    0     no      rig-set (policy)
``session`` ``command``            coordinator JSON object           1     yes/no  on change
``session`` ``clock_ping/pong``    station     JSON object           1/0   yes/no  ~10 Hz
``health`` ``alerts``              recorder    JSON object           1     yes     ~1 Hz
``alerts`` ``events`` ``halt``     safety      JSON object           1     yes/no  on change
``command``                        safety      JSON object           1     no      on demand
``alerts``                         broker      JSON object           1     yes     on restart
``feedback``                       voice       JSON object           1     no      per utterance
``view``                           voice       JSON object           1     yes     on change
=================================  ==========  ====================  ====  ======  ==================
"""

from __future__ import annotations

import re
from collections.abc import Collection, Iterable, Iterator
from dataclasses import dataclass
from enum import StrEnum

from telerig.ir.types import (
    BaseVelocity,
    BodySkeleton,
    CameraFrame,
    ControllerState,
    ControlSource,
    GripperCommand,
    HandPose,
    JointCommand,
    JointState,
    Pose,
    RetargetResidual,
    Sample,
    Twist,
    Wrench,
)

__all__ = [
    "ALERTS",
    "BASE_POSE",
    "BASE_REQUESTED",
    "BASE_SENT",
    "BROKER",
    "CAMERA_FRAMES",
    "CATALOGUE",
    "CLOCK_PING",
    "CLOCK_PONG",
    "COMMAND",
    "CONTROL",
    "CONTROL_SOURCE",
    "COORDINATOR",
    "DEVICE_SAMPLE",
    "EVENTS",
    "FEEDBACK",
    "FIXTURE",
    "GRIPPER_REQUESTED",
    "GRIPPER_SENT",
    "GRIPPER_STATE",
    "HALT",
    "HEALTH",
    "JOINT_REQUESTED",
    "JOINT_SENT",
    "JOINT_STATE",
    "LATENCY",
    "LATENCY_VIEW",
    "MOTION_SCALE",
    "OBJECT_POSE",
    "PAGE_IN",
    "PAGE_OUT",
    "PLAN",
    "PREVIEW",
    "RECORDER",
    "RESIDUAL",
    "SAFETY",
    "SESSION",
    "STATUS",
    "TICK",
    "VIEW",
    "VOICE",
    "WBC_MODE",
    "WRENCH",
    "NodeRole",
    "PayloadKind",
    "RigNodes",
    "StreamSpec",
    "bundled",
    "device_stream",
    "qos_for",
    "roles_publishing",
    "spec_by_name",
    "stream_spec",
]

# --- stream names -------------------------------------------------------------------------------

JOINT_REQUESTED = "joint_command_requested"
JOINT_SENT = "joint_command_sent"
GRIPPER_REQUESTED = "gripper_command_requested"
GRIPPER_SENT = "gripper_command_sent"
JOINT_STATE = "joint_state"
#: Measured gripper opening (0 closed, 1 open) of a robot whose driver reports it, per control tick.
GRIPPER_STATE = "gripper_state"
#: Measured force/torque (wrist sensor or contact) of a robot whose driver reports it, per control tick.
WRENCH = "wrench"
#: Pelvis (humanoid) or base pose in the world frame of a robot with a floating base, per control tick.
BASE_POSE = "base_pose"
#: World-frame pose of each task object of a simulated scene (the cube, the target zone), per control
#: tick, one sample per object with ``stamp.source_id`` ``<robot>/<object>``: what a scripted
#: operator plans from and what a task's randomization left in the episode.
OBJECT_POSE = "object_pose"
BASE_REQUESTED = "base_command_requested"
BASE_SENT = "base_command_sent"
#: Retargeting residual of a robot per solved input sample (IR
#: :class:`~telerig.ir.types.RetargetResidual`: ``flagged`` and named per-task errors, stamped with
#: the input's capture time); episodes recorded before it carry a JSON object
#: ``{"capture_ns", "flagged", <metric>...}`` (read both with
#: :func:`telerig.ir.mcap_log.read_residuals`).
RESIDUAL = "residual"
#: A robot's safety status word (``ok``, ``limited``, ``holding``, ``estopped``...), retained.
STATUS = "status"
#: One control tick's samples in one message (a ``telerig.v1.Bundle``): the robot's IR streams above
#: travel in it, each part the Envelope its stream names (:func:`bundled`). The recorder files every
#: part under its own stream's topic, so an episode has the same channels either way; a live reader
#: of a robot stream subscribes to ``tick`` and picks its part (:func:`telerig.bus.ticks.unbundle`).
TICK = "tick"
#: Live aids' retained state (JSON); their operator commands arrive on ``<aid>_command`` (text).
MOTION_SCALE = "motion_scale"
FIXTURE = "fixture"
WBC_MODE = "wbc_mode"
#: Who drives a robot whose part several sources are bound to (a policy and an operator): the
#: handover's state (aid JSON: mode, active source, handovers); ``control_command`` takes
#: ``operator`` / ``policy`` / ``auto`` (:mod:`telerig.runtime.handover`).
CONTROL = "control"
#: A mobile reach the operator designated, previewed and may confirm (issue 17; aid JSON: id,
#: status staged/executing/done/cancelled/failed, reason, target, base and arm goals, preview
#: paths of the base and grasp point); ``plan_command`` takes ``target``/``plan``/``execute ID``/
#: ``cancel`` (:mod:`telerig.retarget.reach_plan`).
PLAN = "plan"
_AIDS = (MOTION_SCALE, FIXTURE, WBC_MODE, CONTROL, PLAN)
#: Per control tick, who was in control of the robot (IR :class:`~telerig.ir.types.ControlSource`;
#: episodes recorded before it carry a JSON object ``{"capture_ns", "source", "kind", "mode"}``),
#: published by robots with a handover (a policy bound, or several prioritized sources).
CONTROL_SOURCE = "control_source"
_AID_COMMAND_SUFFIX = "_command"
CAMERA_FRAMES = "frames"
#: Low-rate JPEG previews for the dashboard; the MP4 has every frame, so they are not recorded.
PREVIEW = "preview"
#: Low-resolution raw RGB frames at a bounded rate for a policy (:mod:`telerig.ir.observation`);
#: only when the camera's ``observation`` is set. Not recorded: the MP4 has every frame.
OBSERVATION = "observation"
#: An operator page's messages that ``telerig serve`` relays to its device after the login (a relay
#: envelope around the page's wire bytes, see ``telerig.devices.webxr.relay``); only the ``web``
#: principal (and the device's own) may publish it.
PAGE_IN = "page_in"
#: The device's answers to its relayed page (clock pings, a close), back to ``telerig serve``.
PAGE_OUT = "page_out"
#: Per-stage latency of the operator loop (JSON, retained, recorded): a control node's robot stages
#: (:data:`telerig.config.latency.ROBOT_STAGES`), ~2 Hz.
LATENCY = "latency"
#: The stages only the operator's browser sees (state drawn; a camera preview's delivery and
#: display), measured by ``telerig serve`` from the page's reports and published as the ``web``
#: principal on the robot's or camera's topic (JSON, retained, recorded), ~2 Hz.
LATENCY_VIEW = "latency_view"
#: Health counters of a device node or a recorder, a control node's latency (JSON, retained).
HEALTH = "health"
#: Alert documents of a recorder, a safety supervisor or the broker watchdog (JSON, retained).
ALERTS = "alerts"
#: Safety events (JSON, one per raise/clear).
EVENTS = "events"
#: Under ``halt_all``: a robot process faulted and every other process halts its robots (JSON).
HALT = "halt"
#: Session state (coordinator, retained) and each station's acknowledgement (JSON).
SESSION = "session"
#: Commands to the coordinator (episode commands) or to the safety node (e-stop / reset), JSON.
COMMAND = "command"
#: Station → coordinator clock requests (JSON ``{"seq", "t1"}``).
CLOCK_PING = "clock_ping"
#: Coordinator → station clock replies (JSON ``{"seq", "t1", "t2", "t3"}``).
CLOCK_PONG = "clock_pong"
#: Node name of the session coordinator; of the broker watchdog; of the safety supervisor.
COORDINATOR = "coordinator"
BROKER = "broker"
SAFETY = "safety"
RECORDER = "recorder"
#: Node name of operator commands by voice or text (:mod:`telerig.voice`): what was heard and said
#: back (``feedback``), and the operator view they chose (``view``, retained).
VOICE = "voice"
FEEDBACK = "feedback"
VIEW = "view"

#: Pseudo stream name of every device sample stream (the real name comes from the sample).
DEVICE_SAMPLE = "<device sample>"

_UNSAFE = re.compile(r"[^A-Za-z0-9_.\-]")


class NodeRole(StrEnum):
    """What kind of node a topic's ``<node>`` level names."""

    DEVICE = "device"
    ROBOT = "robot"
    CAMERA = "camera"
    COORDINATOR = "coordinator"
    STATION = "station"
    RECORDER = "recorder"
    SAFETY = "safety"
    BROKER = "broker"
    VOICE = "voice"


class PayloadKind(StrEnum):
    """How a stream's payload is encoded.

    ``IR``: a ``telerig.v1.Envelope`` (protobuf) holding one of the spec's IR types. ``BUNDLE``: a
    ``telerig.v1.Bundle`` of the node's IR samples of one moment, each part an ``IR`` stream of the
    same role. ``JSON``: a UTF-8 JSON object. ``TEXT``: a short UTF-8 word or command. ``BINARY``:
    opaque bytes (JPEG).
    """

    IR = "ir"
    BUNDLE = "bundle"
    JSON = "json"
    TEXT = "text"
    BINARY = "binary"


#: Largest payload [bytes] per kind unless a stream says otherwise. An IR sample is at most a few
#: KiB (a 60-joint skeleton is ~5 KiB); node state JSON is a few KiB.
_IR_MAX = 64 * 1024
_JSON_MAX = 64 * 1024
_TEXT_MAX = 1024


@dataclass(frozen=True, slots=True)
class StreamSpec:
    """One stream of the catalogue.

    Attributes:
        name: Stream name (last topic level); :data:`DEVICE_SAMPLE` for device sample streams,
            whose name comes from the sample (:func:`device_stream`).
        role: Role of the node the topic names.
        kind: Payload encoding.
        ir_types: For ``IR``: the sample types the stream carries.
        qos: MQTT QoS the publisher uses.
        retain: Whether the publisher retains it (state a late joiner needs).
        rate_hz: Nominal rate [Hz] where the catalogue knows it; ``None`` when the rig sets it
            (device rate, control rate, camera fps) or it is event-driven.
        max_bytes: Largest payload accepted [bytes].
        recorded: Whether the recorder writes it into the episode.
        from_owner: Whether an IR sample's ``stamp.source_id`` must name the topic's node
            (``<node>`` or ``<node>/...``): samples a node makes itself (a driver's sent commands
            and joint states), which nobody else may publish.
        stamped_by_input: Whether its samples carry the stamp of the input they answer (a
            retargeted command keeps the device sample's source, seq and capture time): its
            sequence numbers skip where the control loop took a newer input in place of an older
            one (``inputs_skipped``), which is no loss, so no one counts them as drops.
        description: One line.
    """

    name: str
    role: NodeRole
    kind: PayloadKind
    description: str
    ir_types: tuple[type[Sample], ...] = ()
    qos: int = 0
    retain: bool = False
    rate_hz: float | None = None
    max_bytes: int = 0
    recorded: bool = True
    from_owner: bool = False
    stamped_by_input: bool = False

    def __post_init__(self) -> None:
        if (self.kind is PayloadKind.IR) != bool(self.ir_types):
            raise ValueError(f"stream {self.name}: ir_types are given exactly for IR streams")
        if self.max_bytes == 0:
            default = {PayloadKind.IR: _IR_MAX, PayloadKind.TEXT: _TEXT_MAX}.get(self.kind, _JSON_MAX)
            object.__setattr__(self, "max_bytes", default)

    def loss_seq(self, seq: int) -> int | None:
        """The sequence number that counts this stream's losses: a sample's own ``seq``, or None
        where it is an input's (``stamped_by_input``: its holes are no loss)."""
        return None if self.stamped_by_input else seq


def _ir(
    name: str,
    role: NodeRole,
    types: tuple[type[Sample], ...],
    desc: str,
    *,
    from_owner: bool = False,
    stamped_by_input: bool = False,
) -> StreamSpec:
    return StreamSpec(
        name,
        role,
        PayloadKind.IR,
        desc,
        ir_types=types,
        from_owner=from_owner,
        stamped_by_input=stamped_by_input,
    )


def _json(name: str, role: NodeRole, desc: str, *, state: bool = False, qos: int | None = None) -> StreamSpec:
    return StreamSpec(
        name,
        role,
        PayloadKind.JSON,
        desc,
        qos=(1 if state else 0) if qos is None else qos,
        retain=state,
        max_bytes=_JSON_MAX if role is not NodeRole.RECORDER else 1024 * 1024,
    )


#: A policy device's actions are joint-position targets (and a gripper opening), like a leader arm.
_DEVICE_TYPES: tuple[type[Sample], ...] = (
    ControllerState,
    HandPose,
    BodySkeleton,
    Pose,
    Twist,
    BaseVelocity,
    JointCommand,
    GripperCommand,
)

_R = NodeRole
#: Every stream, by role. A device's sample streams are one entry (:data:`DEVICE_SAMPLE`).
CATALOGUE: tuple[StreamSpec, ...] = (
    _ir(DEVICE_SAMPLE, _R.DEVICE, _DEVICE_TYPES, "a device's validated samples, one stream per part"),
    _json(HEALTH, _R.DEVICE, "device node counters: received, published, dropped per reason", state=True),
    _json(EVENTS, _R.DEVICE, "device alerts: a client took the device over, was refused, asks to", qos=1),
    _json(COMMAND, _R.DEVICE, "operator command to a device, e.g. confirm or deny a takeover", qos=1),
    StreamSpec(
        PAGE_IN,
        _R.DEVICE,
        PayloadKind.BINARY,
        "a logged-in page's messages",
        max_bytes=32 << 10,
        recorded=False,
    ),
    StreamSpec(
        PAGE_OUT,
        _R.DEVICE,
        PayloadKind.BINARY,
        "pings and closes for the page",
        max_bytes=1024,
        recorded=False,
    ),
    _ir(
        JOINT_REQUESTED,
        _R.ROBOT,
        (JointCommand,),
        "retargeted joint targets before safety",
        stamped_by_input=True,
    ),
    _ir(JOINT_SENT, _R.ROBOT, (JointCommand,), "what the driver sent after safety", from_owner=True),
    _ir(
        GRIPPER_REQUESTED,
        _R.ROBOT,
        (GripperCommand,),
        "retargeted gripper opening before safety",
        stamped_by_input=True,
    ),
    _ir(GRIPPER_SENT, _R.ROBOT, (GripperCommand,), "what the gripper driver sent", from_owner=True),
    _ir(BASE_REQUESTED, _R.ROBOT, (BaseVelocity,), "base velocity asked for", stamped_by_input=True),
    _ir(BASE_SENT, _R.ROBOT, (BaseVelocity,), "base velocity the driver sent", from_owner=True),
    _ir(JOINT_STATE, _R.ROBOT, (JointState,), "measured joint state", from_owner=True),
    _ir(GRIPPER_STATE, _R.ROBOT, (GripperCommand,), "measured gripper opening", from_owner=True),
    _ir(WRENCH, _R.ROBOT, (Wrench,), "measured force/torque (wrist sensor or contact)", from_owner=True),
    _ir(BASE_POSE, _R.ROBOT, (Pose,), "measured pelvis or floating-base pose, world frame", from_owner=True),
    _ir(OBJECT_POSE, _R.ROBOT, (Pose,), "task object poses (one per object), world frame", from_owner=True),
    StreamSpec(STATUS, _R.ROBOT, PayloadKind.TEXT, "safety status word", qos=1, retain=True),
    _ir(RESIDUAL, _R.ROBOT, (RetargetResidual,), "retargeting residual per solve", from_owner=True),
    StreamSpec(
        TICK,
        _R.ROBOT,
        PayloadKind.BUNDLE,
        "one control tick's IR samples (the streams above), one message per tick",
        max_bytes=256 * 1024,
    ),
    StreamSpec(
        HEALTH,
        _R.ROBOT,
        PayloadKind.JSON,
        "control loop latency, input-to-command and input-to-state p50/p99 over a rolling window",
        qos=1,
        retain=True,
        recorded=False,  # live only: the manifest has the episode's latency
    ),
    _json(LATENCY, _R.ROBOT, "per-stage latency p50/p99 of applied commands, against budgets", state=True),
    _json(LATENCY_VIEW, _R.ROBOT, "browser stage: joint state drawn by the operator's page", state=True),
    _json(ALERTS, _R.ROBOT, "active latency-budget alerts of the robot's stages", state=True),
    *(_json(aid, _R.ROBOT, f"live aid state ({aid})", state=True) for aid in _AIDS),
    _ir(CONTROL_SOURCE, _R.ROBOT, (ControlSource,), "who was in control this tick", from_owner=True),
    *(
        StreamSpec(aid + _AID_COMMAND_SUFFIX, _R.ROBOT, PayloadKind.TEXT, f"operator command to {aid}")
        for aid in _AIDS
    ),
    _ir(CAMERA_FRAMES, _R.CAMERA, (CameraFrame,), "timestamp and index of every encoded frame"),
    StreamSpec(PREVIEW, _R.CAMERA, PayloadKind.BINARY, "JPEG preview", max_bytes=4 << 20, recorded=False),
    _json(LATENCY_VIEW, _R.CAMERA, "video stages: preview encoded, delivered, displayed", state=True),
    StreamSpec(
        OBSERVATION,
        _R.CAMERA,
        PayloadKind.BINARY,
        "low-resolution raw RGB frame for a policy",
        max_bytes=1 << 20,
        recorded=False,
    ),
    _json(SESSION, _R.COORDINATOR, "session state", state=True),
    _json(COMMAND, _R.COORDINATOR, "episode command from the CLI or web UI", qos=1),
    _json(SESSION, _R.STATION, "a station's acknowledgement of the session state", state=True),
    _json(CLOCK_PING, _R.STATION, "clock-sync request {seq, t1}"),
    _json(CLOCK_PONG, _R.STATION, "clock-sync reply {seq, t1, t2, t3}"),
    _json(HEALTH, _R.RECORDER, "per-stream rates, gaps and drops", state=True),
    _json(ALERTS, _R.RECORDER, "stream alerts (stalled, missing, overflow)", state=True),
    _json(ALERTS, _R.SAFETY, "active safety alerts", state=True),
    _json(EVENTS, _R.SAFETY, "safety events, one per raise or clear", qos=1),
    _json(HALT, _R.SAFETY, "halt every robot of the rig (halt_all)", qos=1),
    _json(COMMAND, _R.SAFETY, "operator e-stop or reset", qos=1),
    _json(ALERTS, _R.BROKER, "embedded broker restarted", state=True),
    _json(
        FEEDBACK,
        _R.VOICE,
        "a voice or text command: heard, done, staged or rejected, what was said back",
        qos=1,
    ),
    _json(VIEW, _R.VOICE, "the operator view a voice or text command chose", state=True),
)

_BY_ROLE: dict[NodeRole, dict[str, StreamSpec]] = {}
for _spec in CATALOGUE:
    _BY_ROLE.setdefault(_spec.role, {})[_spec.name] = _spec
_BY_NAME: dict[str, list[StreamSpec]] = {}
for _spec in CATALOGUE:
    _BY_NAME.setdefault(_spec.name, []).append(_spec)


def stream_spec(role: NodeRole, stream: str) -> StreamSpec | None:
    """The spec of ``stream`` on a node of ``role``; ``None`` when that role does not publish it.

    Any stream name of a device other than its ``health`` is a device sample stream.
    """
    specs = _BY_ROLE[role]
    spec = specs.get(stream)
    if spec is None and role is NodeRole.DEVICE and stream != DEVICE_SAMPLE:
        return specs[DEVICE_SAMPLE]
    return spec


def bundled(role: NodeRole, stream: str) -> StreamSpec | None:
    """The spec of a bundle part's ``stream`` from a node of ``role``: an IR stream of that role;
    ``None`` for anything else (an unknown name, a JSON or text stream, a bundle in a bundle)."""
    spec = _BY_ROLE[role].get(stream)
    return spec if spec is not None and spec.kind is PayloadKind.IR else None


def roles_publishing(stream: str) -> tuple[NodeRole, ...]:
    """The roles whose nodes publish a stream of this name (a device for any unknown name)."""
    specs = _BY_NAME.get(stream)
    return tuple(s.role for s in specs) if specs else (NodeRole.DEVICE,)


def qos_for(stream: str) -> tuple[int, bool]:
    """``(qos, retain)`` of a stream by name: QoS 1 + retain for state, QoS 0 for high-rate data."""
    specs = _BY_NAME.get(stream)
    if not specs:
        return 0, False
    return specs[0].qos, specs[0].retain


def device_stream(sample: Sample) -> str:
    """The device part a sample belongs to, used as its stream name and bound by rig ``part``.

    Controllers and hands are named by side (``right_controller``, ``left_hand``); poses,
    skeletons and twists by the part of their source id after the device id (``quest/head`` →
    ``head``, ``mocap/wand`` → ``wand``; ``pose``, ``body``, ``twist`` without one), so one device
    can stream several rigid bodies; a base velocity is ``base``; a device's joint targets (a
    policy's action) ``joints`` and its gripper opening ``gripper`` unless the source id names a part.

    Raises:
        ValueError: ``sample`` is not a device sample (a command, a joint state, a frame).
    """
    match sample:
        case ControllerState():
            return f"{sample.hand}_controller"
        case HandPose():
            return f"{sample.handedness}_hand"
        case BodySkeleton():
            return _suffix(sample.stamp.source_id, "body")
        case Pose():
            return _suffix(sample.stamp.source_id, "pose")
        case Twist():
            return _suffix(sample.stamp.source_id, "twist")
        case BaseVelocity():
            return "base"
        case JointCommand():
            return _suffix(sample.stamp.source_id, "joints")
        case GripperCommand():
            return _suffix(sample.stamp.source_id, "gripper")
        case _:
            raise ValueError(f"{type(sample).__name__} is not a device sample")


def _suffix(source_id: str, default: str) -> str:
    _, sep, part = source_id.partition("/")
    # Topic levels allow letters, digits, '_', '-', '.': a rigid body named "Rigid Body 1" → Rigid_Body_1.
    return _UNSAFE.sub("_", part) if sep and part else default


@dataclass(frozen=True, slots=True)
class RigNodes:
    """The nodes of one rig by role: which ``<node>`` names may publish which streams.

    The coordinator, the broker watchdog, ``safety``/``safety-*`` and ``recorder``/``recorder-*``
    nodes and the ``voice`` node are implied. Build it from the rig's ids (the runtime does).

    Attributes:
        devices: Device ids.
        robots: Robot ids (their control nodes).
        cameras: Camera ids.
        stations: Station ids.
    """

    devices: frozenset[str] = frozenset()
    robots: frozenset[str] = frozenset()
    cameras: frozenset[str] = frozenset()
    stations: frozenset[str] = frozenset()

    @classmethod
    def of(
        cls,
        *,
        devices: Iterable[str] = (),
        robots: Iterable[str] = (),
        cameras: Iterable[str] = (),
        stations: Iterable[str] = (),
    ) -> RigNodes:
        """Nodes from id lists."""
        return cls(frozenset(devices), frozenset(robots), frozenset(cameras), frozenset(stations))

    def roles(self, node: str) -> Iterator[NodeRole]:
        """The roles of ``node`` (none for a node the rig does not have)."""
        if node in self.devices:
            yield NodeRole.DEVICE
        if node in self.robots:
            yield NodeRole.ROBOT
        if node in self.cameras:
            yield NodeRole.CAMERA
        if node in self.stations:
            yield NodeRole.STATION
        if node == COORDINATOR:
            yield NodeRole.COORDINATOR
        if node == BROKER:
            yield NodeRole.BROKER
        if node == SAFETY or node.startswith(SAFETY + "-"):
            yield NodeRole.SAFETY
        if node == RECORDER or node.startswith(RECORDER + "-"):
            yield NodeRole.RECORDER
        if node == VOICE:
            yield NodeRole.VOICE

    def spec(self, node: str, stream: str) -> StreamSpec | None:
        """The spec of ``<node>/<stream>`` in this rig; ``None`` when no node of the rig publishes it."""
        return _first_spec(self.roles(node), stream)


def spec_by_name(stream: str, roles: Collection[NodeRole] = ()) -> StreamSpec | None:
    """The spec of a stream when the node's role is unknown: by name among ``roles`` (all when empty)."""
    candidates = roles or roles_publishing(stream)
    return _first_spec(candidates, stream)


def _first_spec(roles: Iterable[NodeRole], stream: str) -> StreamSpec | None:
    for role in roles:
        spec = stream_spec(role, stream)
        if spec is not None:
            return spec
    return None
