"""The operator scene's server side: robot geometry from the shared models, body poses from the bus.

:class:`RobotGeometry` turns a robot's kinematic model (:mod:`telerig.robots.models`, MuJoCo, the
one IK and the safety guards use) into what a browser draws: the primitive and mesh geoms of its
bodies, once, and the world pose of every body for a joint configuration (``mj_kinematics``,
microseconds). Visual meshes are sent when they are small: the models compile with their visual
meshes simplified (:func:`telerig.robots.models.mjcf.compile_spec`; the UR5e's 137 k triangles,
6 MB, become 40 k, 0.9 MB of mesh data, sent once a page), and above :data:`MAX_VISUAL_FACES` (a
model compiled with every face) the collision meshes (convex, a few thousand vertices) stand in,
coloured like the visual mesh of the same body.

:class:`SceneHub` is one per watched rig. Through the gateway's ``web`` login it listens to the
streams the scene shows, and on the bus thread it only keeps the **latest payload** of each
``(node, stream)`` (size-checked against the catalogue, unknown nodes dropped and counted): a
500 Hz joint stream costs a dictionary store per message and nothing is decoded there. The
WebSocket feed calls :meth:`SceneHub.state` at most :data:`SCENE_HZ` times a second, which
decodes what changed and runs the forward kinematics once for every client. The control loop is
never touched: the hub is one more QoS-0 subscriber of streams the control node publishes anyway.

Frames: each robot's base frame is its own world (what its joint states and aid axes are in);
robots after the first are laid out :data:`ROBOT_SPACING_M` apart along -y. The operator's hand
(a bound device part) is mapped into the robot's base frame with its binding's alignment (the
absolute-pose retargeter's, or the relative one's reference); a binding without one (a twist, a
glove's keypoints) draws no hand marker rather than one in the wrong frame. A whole-body binding's
plan marker (``plan_marker``, :class:`telerig.retarget.reach_plan.PlanMarker`) is drawn the same
way with its own alignment, as ``plan_marker``: where "plan here" will plan the reach to.
"""

from __future__ import annotations

import base64
import logging
import math
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from pydantic import JsonValue

from telerig.bus.base import Message
from telerig.bus.catalogue import (
    BASE_POSE,
    FEEDBACK,
    FIXTURE,
    JOINT_REQUESTED,
    JOINT_STATE,
    MOTION_SCALE,
    PLAN,
    RESIDUAL,
    STATUS,
    VIEW,
    VOICE,
    WBC_MODE,
    NodeRole,
    RigNodes,
    stream_spec,
)
from telerig.bus.jsonpayload import parse_json_object
from telerig.bus.ticks import TICK, picking
from telerig.bus.topics import Topic
from telerig.config.schema import RigConfig, RobotConfig
from telerig.errors import DependencyError, TelerigError, WireError
from telerig.ir import wire
from telerig.ir.mcap_log import decode_residual
from telerig.ir.types import ControllerState, FloatArray, HandPose, JointCommand, JointState, Pose

if TYPE_CHECKING:
    import mujoco

    from telerig.server.gateway import RigGateway

__all__ = [
    "MAX_MESH_BYTES",
    "MAX_VISUAL_FACES",
    "MESH_CELL_M",
    "ROBOT_SPACING_M",
    "SCENE_HZ",
    "RobotGeometry",
    "SceneHub",
    "robot_geometry",
]

log = logging.getLogger("telerig.server")
IntArray = np.ndarray[tuple[int, ...], np.dtype[np.int32 | np.int64]]

#: Most scene state updates per second per client: smooth to the eye, a bounded cost whatever the
#: control rate (the page renders at the display rate and interpolates nothing it was not sent).
SCENE_HZ = 30.0
#: A visual mesh set larger than this many triangles is replaced by the collision meshes.
MAX_VISUAL_FACES = 50_000
#: Mesh data (float32 vertices, int32 triangles) above which meshes are simplified by vertex
#: clustering in :data:`MESH_CELL_M` cells: the G1's 4 MB and the TIAGo's 2.5 MB scene messages.
MAX_MESH_BYTES = 1 << 20
MESH_CELL_M = 0.006
#: Distance between the bases of the rig's robots in the scene [m].
ROBOT_SPACING_M = 1.2
#: Joint configurations sampled to estimate an arm's reach (the farthest grasp point from the base).
_REACH_SAMPLES = 512
#: Streams of the robots the hub keeps the latest payload of: state on their own topics, and the
#: IR samples of each control tick, which arrive in one ``tick`` message.
_ROBOT_STATE_STREAMS = (STATUS, FIXTURE, MOTION_SCALE, WBC_MODE, PLAN)
_ROBOT_TICK_STREAMS = (JOINT_STATE, JOINT_REQUESTED, RESIDUAL, BASE_POSE)
#: The voice node's streams the scene follows (issue 17): the view an operator asked for by voice or
#: text, and what the last command heard and said back (shown as a caption).
_VOICE_STREAMS = (VIEW, FEEDBACK)
#: The page's views a voice command may choose (static/scene.js and its menu in scene.html).
_VIEWS = frozenset({"auto", "navigation", "manipulation", "ee", "ee-inverted", "free"})
_JSON_STREAMS = frozenset({FIXTURE, MOTION_SCALE, WBC_MODE, VIEW, FEEDBACK})
_TEXT = 200  # longest text passed on to the page (status words, fixture names)
#: Most points of a plan's preview path passed on (the planner sends at most 64).
_PLAN_POINTS = 64
_PLAN_STATUSES = frozenset({"none", "planning", "staged", "executing", "done", "cancelled", "failed"})


@dataclass(frozen=True, slots=True)
class RobotGeometry:
    """A robot model's drawable geometry and its forward kinematics.

    Attributes:
        model: Name of the model (``ur5e_robotiq85``, ``tiago``...).
        mj: The compiled kinematic model.
        bodies: Indices of the bodies that carry a drawn geom (their poses are sent), in order.
        geoms: One document per drawn geom (see :meth:`document`).
        meshes: Vertices (float32, [m], mesh frame) and triangles (int32) of each mesh used.
        joints: ``(joint name, qpos address)`` of every hinge or slide joint.
        ee_site: Grasp-point site id, or -1.
        reach_m: Farthest the grasp point gets from the base origin [m]; 0 without one.
    """

    model: str
    mj: mujoco.MjModel
    bodies: tuple[int, ...]
    geoms: tuple[dict[str, JsonValue], ...]
    meshes: tuple[tuple[bytes, bytes], ...]
    joints: tuple[tuple[str, int], ...]
    ee_site: int
    reach_m: float
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def document(self) -> dict[str, JsonValue]:
        """What the page builds the robot from once: bodies, geoms (type, size [m], pose in the body,
        colour, mesh index), meshes (base64 little-endian float32 xyz and int32 triangles), reach."""
        return {
            "model": self.model,
            "bodies": [self.mj.body(int(b)).name for b in self.bodies],
            "geoms": list(self.geoms),
            "meshes": [
                {"vertices": base64.b64encode(v).decode(), "faces": base64.b64encode(f).decode()}
                for v, f in self.meshes
            ],
            "joints": [name for name, _ in self.joints],
            "reach_m": round(self.reach_m, 4),
        }

    def poses(self, q: dict[str, float]) -> tuple[list[JsonValue], list[JsonValue] | None]:
        """World poses of :attr:`bodies` (flat ``x y z qw qx qy qz`` per body, [m]) and the grasp
        point [m] for joint positions by name (a joint missing from ``q`` stays at 0). A state's
        names match a model joint exactly or with a prefix (``left_shoulder_pan_joint``)."""
        import mujoco

        with self._lock:
            data = _data(self)
            data.qpos[:] = 0.0
            for name, adr in self.joints:
                value = q.get(name)
                if value is not None:
                    data.qpos[adr] = value
            mujoco.mj_kinematics(self.mj, data)
            idx = np.asarray(self.bodies, dtype=np.intp)
            flat = np.concatenate([data.xpos[idx], data.xquat[idx]], axis=1).round(5).ravel()
            ee: list[JsonValue] | None = None
            if self.ee_site >= 0:
                ee = data.site_xpos[self.ee_site].round(5).tolist()
            poses: list[JsonValue] = flat.tolist()
        return poses, ee

    def match(self, names: tuple[str, ...]) -> dict[str, str]:
        """Which model joint each of a joint state's ``names`` is (unmatched names left out)."""
        model_names = {name for name, _ in self.joints}
        out: dict[str, str] = {}
        for name in names:
            if name in model_names:
                out[name] = name
                continue
            for candidate in model_names:
                if name.endswith("_" + candidate):
                    out[name] = candidate
                    break
        return out


_DATA: dict[int, Any] = {}


def _data(geometry: RobotGeometry) -> Any:
    import mujoco

    key = id(geometry.mj)
    data = _DATA.get(key)
    if data is None:
        data = _DATA[key] = mujoco.MjData(geometry.mj)
    return data


def _model_of(robot: RobotConfig) -> tuple[str, mujoco.MjModel, str | None]:
    """The kinematic model of a rig robot: ``(name, model, grasp site)``.

    Raises:
        TelerigError: the robot names no model this scene knows (its type and what would do).
    """
    from telerig.robots.models import ARM_MODELS

    arm = getattr(robot, "model", None)
    if isinstance(arm, str) and arm in ARM_MODELS:
        from telerig.robots.models.arm import build_arm_kinematics

        scene = build_arm_kinematics(arm, drawn=True)
        return arm, scene.model, scene.ee_site
    if robot.type == "mujoco_tiago":
        from telerig.robots.models.tiago import build_tiago_kinematics

        tiago = build_tiago_kinematics(drawn=True)
        return "tiago", tiago.model, tiago.ee_site
    if robot.type in ("mujoco_humanoid", "unitree_g1"):  # the simulated G1 and the real one
        from telerig.robots.models.g1 import build_humanoid_kinematics

        g1 = build_humanoid_kinematics(drawn=True)
        return "g1", g1.model, None
    raise TelerigError(
        f"robot {robot.id!r} ({robot.type}) names no model the scene draws: give it an arm `model` "
        f"({', '.join(ARM_MODELS)}); TIAGo and the G1 are drawn too (robot hands are not: their "
        "models carry no geometry)"
    )


def robot_geometry(robot: RobotConfig) -> RobotGeometry:
    """The drawable geometry of a rig robot's model (built once per model and kept).

    Raises:
        TelerigError: no model for this robot; DependencyError: MuJoCo or the model files missing.
    """
    name, mj, site = _model_of(robot)
    return _geometry(name, mj, site)


_GEOMS_CACHE: dict[str, RobotGeometry] = {}
_GEOMS_LOCK = threading.Lock()


def _geometry(name: str, mj: mujoco.MjModel, site: str | None) -> RobotGeometry:
    with _GEOMS_LOCK:
        cached = _GEOMS_CACHE.get(name)
        if cached is None:
            cached = _GEOMS_CACHE[name] = _build_geometry(name, mj, site)
        return cached


_PRIMITIVES = {2: "sphere", 3: "capsule", 4: "ellipsoid", 5: "cylinder", 6: "box", 7: "mesh"}


def _build_geometry(name: str, mj: mujoco.MjModel, site: str | None) -> RobotGeometry:
    import mujoco

    visual = [g for g in range(mj.ngeom) if int(mj.geom_group[g]) in (1, 2)]
    collision = [g for g in range(mj.ngeom) if int(mj.geom_group[g]) == 0]
    faces = sum(int(mj.mesh_facenum[mj.geom_dataid[g]]) for g in visual if int(mj.geom_type[g]) == 7)
    drawn = visual if visual and faces <= MAX_VISUAL_FACES else collision or visual
    colour = {int(mj.geom_bodyid[g]): _rgba(mj, g) for g in sorted(visual, key=lambda g: -_size(mj, g))}
    meshes: list[tuple[FloatArray, IntArray]] = []
    mesh_index: dict[int, int] = {}
    geoms: list[dict[str, JsonValue]] = []
    bodies: list[int] = []
    for g in drawn:
        kind = _PRIMITIVES.get(int(mj.geom_type[g]))
        if kind is None or float(mj.geom_rgba[g][3]) == 0.0:
            continue  # planes, height fields and invisible geoms
        body = int(mj.geom_bodyid[g])
        if body == 0:
            continue  # the world: the page draws its own floor
        if body not in bodies:
            bodies.append(body)
        doc: dict[str, JsonValue] = {
            "body": bodies.index(body),
            "type": kind,
            "size": [round(float(s), 5) for s in mj.geom_size[g]],
            "pos": [round(float(p), 5) for p in mj.geom_pos[g]],
            "quat": [round(float(q), 6) for q in mj.geom_quat[g]],
            "rgba": colour.get(body, _rgba(mj, g)) if g not in visual else _rgba(mj, g),
        }
        if kind == "mesh":
            mesh = int(mj.geom_dataid[g])
            if mesh not in mesh_index:
                mesh_index[mesh] = len(meshes)
                v0, nv = int(mj.mesh_vertadr[mesh]), int(mj.mesh_vertnum[mesh])
                f0, nf = int(mj.mesh_faceadr[mesh]), int(mj.mesh_facenum[mesh])
                meshes.append((mj.mesh_vert[v0 : v0 + nv], mj.mesh_face[f0 : f0 + nf]))
            doc["mesh"] = mesh_index[mesh]
        geoms.append(doc)
    joints = tuple(
        (mj.joint(j).name, int(mj.jnt_qposadr[j]))
        for j in range(mj.njnt)
        if int(mj.jnt_type[j]) in (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))
    )
    ee = -1 if site is None else mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_SITE, site)
    if sum(4 * (v.size + f.size) for v, f in meshes) > MAX_MESH_BYTES:  # as float32 / int32
        meshes = [_simplify(v, f, MESH_CELL_M) for v, f in meshes]
    packed = tuple(
        (np.ascontiguousarray(v, dtype="<f4").tobytes(), np.ascontiguousarray(f, dtype="<i4").tobytes())
        for v, f in meshes
    )
    geometry = RobotGeometry(name, mj, tuple(bodies), tuple(geoms), packed, joints, ee, 0.0)
    return RobotGeometry(name, mj, geometry.bodies, geometry.geoms, packed, joints, ee, _reach(geometry))


def _simplify(vertices: FloatArray, faces: IntArray, cell: float) -> tuple[FloatArray, IntArray]:
    """Vertex clustering: vertices in one ``cell`` [m] cube merge into their mean; triangles that
    collapse, and repeated ones, go. Coarse but shape-keeping at a few millimetres, and numpy only
    (the robots' STL meshes repeat each vertex per triangle and carry sub-millimetre detail)."""
    keys = np.floor(vertices / cell).astype(np.int64)
    _, cluster, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    cluster = cluster.reshape(-1)
    merged = np.zeros((len(counts), 3))
    np.add.at(merged, cluster, vertices)
    merged /= counts[:, None]
    tri = cluster[faces]
    keep = (tri[:, 0] != tri[:, 1]) & (tri[:, 1] != tri[:, 2]) & (tri[:, 0] != tri[:, 2])
    tri = np.unique(tri[keep], axis=0)
    return merged, tri


def _size(mj: mujoco.MjModel, g: int) -> int:
    return int(mj.mesh_vertnum[mj.geom_dataid[g]]) if int(mj.geom_type[g]) == 7 else 0


def _rgba(mj: mujoco.MjModel, g: int) -> list[JsonValue]:
    mat = int(mj.geom_matid[g])
    rgba = mj.mat_rgba[mat] if mat >= 0 else mj.geom_rgba[g]
    return [round(float(c), 3) for c in rgba]


def _reach(geometry: RobotGeometry) -> float:
    """The farthest grasp point from the base over random joint configurations inside the limits
    (unlimited joints: a full turn); 0 without a grasp site. Deterministic (fixed seed)."""
    if geometry.ee_site < 0:
        return 0.0
    mj = geometry.mj
    rng = np.random.default_rng(0)
    best = 0.0
    names = [name for name, _ in geometry.joints]
    for _ in range(_REACH_SAMPLES):
        q = {}
        for name in names:
            j = mj.joint(name).id
            lo, hi = (float(v) for v in mj.jnt_range[j])
            if not bool(mj.jnt_limited[j]) or hi <= lo:
                lo, hi = -math.pi, math.pi
            if name.startswith("base_"):
                lo = hi = 0.0  # a mobile base's planar joints: reach is the arm's
            q[name] = float(rng.uniform(lo, hi))
        _, ee = geometry.poses(q)
        if ee is not None:
            best = max(best, float(np.linalg.norm(np.asarray(ee, dtype=np.float64))))
    return best


# --- the hub ---------------------------------------------------------------------------------------


@dataclass(slots=True)
class _Latest:
    """The newest payload of one topic and when it arrived (monotonic ns)."""

    payload: bytes
    at_ns: int
    seq: int


@dataclass(slots=True)
class _Hand:
    device: str
    part: str
    robot: str
    alignment: Any  # telerig.retarget.alignment.Alignment | None
    label: str = "hand"


class SceneHub:
    """The scene's view of a rig (see the module docs): latest payloads in, one shared state out.

    Args:
        gateway: The server's link to the rig (its ``web`` login).
    """

    def __init__(self, gateway: RigGateway) -> None:
        self.gateway = gateway
        self.rig: RigConfig = gateway.rig
        self._nodes = RigNodes.of(
            devices=[d.id for d in self.rig.devices],
            robots=[r.id for r in self.rig.robots],
            cameras=[c.id for c in self.rig.cameras],
            stations=[s.id for s in self.rig.stations],
        )
        self._lock = threading.Lock()
        self._latest: dict[tuple[str, str], _Latest] = {}
        self._seq = 0
        #: Messages dropped before decoding, and payloads that did not decode, by reason.
        self.dropped: Counter[str] = Counter()
        #: Bound device parts whose pose maps into a robot's base frame (a binding with an alignment:
        #: the pose retargeters); a twist or keypoint binding has no place to draw the hand at.
        self._hands = [h for h in map(_hand, self.rig.bindings) if h.alignment is not None]
        #: The whole-body bindings' plan markers (the target "plan here" plans to), aligned likewise.
        self._markers = [m for m in map(_plan_marker, self.rig.bindings) if m is not None]
        self._geometry: dict[str, RobotGeometry | str] = {}  # robot -> geometry, or why none
        self._decoded: dict[tuple[str, str], tuple[int, Any]] = {}
        self._state: tuple[float, dict[str, JsonValue]] | None = None
        self._state_lock = threading.Lock()
        self._subscribed = False
        self._start_lock = threading.Lock()
        self._q: dict[str, tuple[dict[str, float], float | None]] = {}  # robot -> (last good q, when)
        #: robot -> stamp.capture_ns [ns] of the joint state its last good q came from (issue 17: the
        #: page reports when it drew that state, the ``rendered`` latency stage).
        self._q_ns: dict[str, int] = {}
        self._bad: dict[tuple[str, str], int] = {}

    # --- setup (first client) ------------------------------------------------------------------

    def start(self) -> None:
        """Subscribe (once) and build every robot's geometry (seconds: mesh files load); a second
        client that comes meanwhile waits for it."""
        with self._start_lock:
            if self._subscribed:
                return
            parts = sorted({h.part for h in (*self._hands, *self._markers)})
            for stream in (*_ROBOT_STATE_STREAMS, *_VOICE_STREAMS, *parts):
                self.gateway.add_listener(stream, self._on_message)
            # The robots' IR streams travel in their ticks (telerig.bus.ticks).
            self.gateway.add_listener(TICK, picking(_ROBOT_TICK_STREAMS, self._on_message))
            for robot in self.rig.robots:
                try:
                    self._geometry[robot.id] = robot_geometry(robot)
                except (TelerigError, DependencyError) as exc:
                    self._geometry[robot.id] = str(exc).splitlines()[0][:_TEXT]
                    log.warning("scene: %s", exc)
            self._subscribed = True

    def document(self) -> dict[str, JsonValue]:
        """The scene message sent once: the rig, each robot's geometry (or why none), cameras."""
        robots: list[JsonValue] = []
        for i, robot in enumerate(self.rig.robots):
            geometry = self._geometry.get(robot.id, "not built")
            entry: dict[str, JsonValue] = {
                "id": robot.id,
                "type": robot.type,
                "origin": [0.0, -ROBOT_SPACING_M * i, 0.0],
                "mobile": robot.type == "mujoco_tiago",
            }
            if isinstance(geometry, str):
                entry["error"] = geometry
            else:
                entry.update(geometry.document())
            robots.append(entry)
        return {
            "type": "scene",
            "rig": self.rig.name,
            "hz": SCENE_HZ,
            "robots": robots,
            "cameras": [c.id for c in self.rig.cameras],
            "hands": [{"device": h.device, "part": h.part, "robot": h.robot} for h in self._hands],
            "plan_markers": [{"device": m.device, "part": m.part, "robot": m.robot} for m in self._markers],
        }

    # --- bus thread ------------------------------------------------------------------------------

    def _on_message(self, message: Message) -> None:
        """Keep the newest payload of a rig node's topic (size-checked); decode nothing here."""
        topic = Topic.try_parse(message.topic)
        if topic is None:
            self._count("bad_topic")
            return
        roles = [
            r for r in self._nodes.roles(topic.node) if r in (NodeRole.ROBOT, NodeRole.DEVICE, NodeRole.VOICE)
        ]
        spec = next((stream_spec(r, topic.stream) for r in roles), None)
        if spec is None:
            self._count("unknown_node")
            return
        if len(message.payload) > spec.max_bytes:
            self._count("oversize")
            return
        with self._lock:
            self._seq += 1
            self._latest[(topic.node, topic.stream)] = _Latest(
                message.payload, time.monotonic_ns(), self._seq
            )

    def _count(self, reason: str) -> None:
        with self._lock:
            self.dropped[reason] += 1

    # --- the feed (bounded rate) -----------------------------------------------------------------

    def state(self) -> dict[str, JsonValue]:
        """The scene's state now, computed at most once per ``1 / SCENE_HZ`` for every client:
        per robot the body poses (``state_ns``: the stamp of the joint state they come from, a
        decimal string), grasp point, commanded target, hand marker, aids and status."""
        with self._state_lock:
            now = time.monotonic()
            if self._state is not None and now - self._state[0] < 0.5 / SCENE_HZ:
                return self._state[1]
            state = self._compute()
            self._state = (now, state)
            return state

    def _payload(self, node: str, stream: str) -> tuple[Any, float] | None:
        """The decoded newest payload of a topic and its age [s]; ``None`` when none, or it did not
        decode (counted once per payload)."""
        with self._lock:
            latest = self._latest.get((node, stream))
        if latest is None:
            return None
        age = (time.monotonic_ns() - latest.at_ns) / 1e9
        cached = self._decoded.get((node, stream))
        if cached is not None and cached[0] == latest.seq:
            return (cached[1], age) if cached[1] is not None else None
        value: Any = None
        try:
            if stream == PLAN:
                value = _plan_cue(parse_json_object(latest.payload, max_bytes=64 * 1024))
            elif stream in _JSON_STREAMS:
                value = _clean(parse_json_object(latest.payload, max_bytes=64 * 1024))
            elif stream == RESIDUAL:  # typed (the JSON object of earlier nodes never came in a tick)
                residual = decode_residual(
                    latest.payload, json_form=False, source_id=node, seq=latest.seq, log_time_ns=0
                )
                value = _clean({"flagged": residual.flagged, **residual.metrics()})
            elif stream == STATUS:
                value = latest.payload.decode("utf-8", errors="replace").strip()[:_TEXT]
            else:
                value = wire.decode(latest.payload)
        except (WireError, ValueError, TypeError) as exc:
            self._count(f"bad_{stream}"[:40])
            log.debug("scene: %s/%s did not decode: %s", node, stream, exc)
        self._decoded[(node, stream)] = (latest.seq, value)
        return (value, age) if value is not None else None

    def _compute(self) -> dict[str, JsonValue]:
        with self._lock:
            seq = self._seq  # what arrived before this state; a feed resends only when it grows
        robots: dict[str, JsonValue] = {}
        for robot in self.rig.robots:
            geometry = self._geometry.get(robot.id)
            if not isinstance(geometry, RobotGeometry):
                continue
            robots[robot.id] = self._robot_state(robot.id, geometry)
        connected = self.gateway.connected  # False: the rig is not running or its broker unreachable
        return {
            "type": "state",
            "t_ns": time.time_ns(),
            "seq": seq,
            "connected": connected,
            "robots": robots,
            "voice": self._voice(),
        }

    def _voice(self) -> dict[str, JsonValue]:
        """The view the last voice or text command chose (a name of the page's view menu, or None)
        with the arrival number of that choice (the page applies each choice once, so a view picked
        by hand afterwards stays), and the last command's feedback: the words heard, its status
        and the sentence said back."""
        with self._lock:
            latest = self._latest.get((VOICE, VIEW))
        view = self._payload(VOICE, VIEW)
        chosen = view[0].get("view") if view is not None else None
        feedback = self._payload(VOICE, FEEDBACK)
        said: JsonValue = None
        if feedback is not None:
            said = {k: v for k in ("heard", "status", "say") if isinstance(v := feedback[0].get(k), str)}
        return {
            "view": chosen if chosen in _VIEWS else None,
            "view_seq": None if latest is None or chosen not in _VIEWS else latest.seq,
            "feedback": said,
        }

    def _robot_state(self, robot: str, geometry: RobotGeometry) -> dict[str, JsonValue]:
        out: dict[str, JsonValue] = {}
        q, age = self._measured(robot, geometry)
        out["poses"], out["ee"] = geometry.poses(q)
        out["joint_age_s"] = None if age is None else round(age, 3)
        # A decimal string: a JS number loses the last digits of a ns time (see static/latency.js).
        stamp_ns = self._q_ns.get(robot)
        out["state_ns"] = None if stamp_ns is None else str(stamp_ns)
        requested = self._payload(robot, JOINT_REQUESTED)
        commanded = None if requested is None else _configuration(requested[0], geometry)
        out["target"] = None if commanded is None else geometry.poses({**q, **commanded})[1]
        base = self._payload(robot, BASE_POSE)
        out["base"] = (
            [*base[0].position.round(5).tolist(), *base[0].orientation.round(6).tolist()]
            if base is not None and isinstance(base[0], Pose) and _finite(base[0].position)
            else None
        )
        status = self._payload(robot, STATUS)
        out["status"] = status[0] if status is not None else None
        for stream, key in (
            (FIXTURE, "fixture"),
            (MOTION_SCALE, "scale"),
            (WBC_MODE, "wbc"),
            (RESIDUAL, "residual"),
            (PLAN, "plan"),
        ):
            got = self._payload(robot, stream)
            out[key] = got[0] if got is not None else None
        out["hand"] = self._hand(robot, self._hands)
        out["plan_marker"] = self._hand(robot, self._markers)
        return out

    def _measured(self, robot: str, geometry: RobotGeometry) -> tuple[dict[str, float], float | None]:
        """The robot's last good measured configuration (model joint names) and its age [s]; a
        joint state with a non-finite value or none of the model's joints keeps the previous one
        (counted as ``bad_joint_state`` once per payload)."""
        got = self._payload(robot, JOINT_STATE)
        q_last, at = self._q.get(robot, ({}, None))
        last = (q_last, None if at is None else time.monotonic() - at)
        if got is None:
            return last
        q = _configuration(got[0], geometry)
        if q is None:
            key = (robot, "bad")
            seq = self._decoded.get((robot, JOINT_STATE), (0, None))[0]
            if self._bad.get(key) != seq:
                self._bad[key] = seq
                self._count(f"bad_{JOINT_STATE}")
            return last
        self._q[robot] = (q, time.monotonic() - got[1])
        self._q_ns[robot] = int(got[0].stamp.capture_ns)
        return q, got[1]

    def _hand(self, robot: str, hands: list[_Hand]) -> JsonValue:
        """The first of ``hands`` (bound hands or controllers, or plan markers) of ``robot`` with a
        finite pose, mapped into its base frame; ``None`` when none."""
        for hand in hands:
            if hand.robot != robot:
                continue
            got = self._payload(hand.device, hand.part)
            if got is None:
                continue
            sample, age = got
            if isinstance(sample, ControllerState | Pose):
                position, orientation = sample.position, sample.orientation
            elif isinstance(sample, HandPose):
                position, orientation = sample.wrist_position, sample.wrist_orientation
            else:
                continue
            if not (_finite(position) and _finite(orientation)):
                continue
            position, orientation = hand.alignment.apply(position, orientation)
            return {
                "device": hand.device,
                "part": hand.part,
                "label": hand.label,
                "pose": [*np.round(position, 5).tolist(), *np.round(orientation, 6).tolist()],
                "age_s": round(age, 3),
            }
        return None


def _configuration(sample: object, geometry: RobotGeometry) -> dict[str, float] | None:
    """Model joint positions of a joint state or command; ``None`` when it is neither, has a
    non-finite value or names none of the model's joints."""
    if not isinstance(sample, JointState | JointCommand) or not _finite(sample.positions):
        return None
    names = geometry.match(sample.names)
    q = {names[n]: float(p) for n, p in zip(sample.names, sample.positions, strict=True) if n in names}
    return q or None


def _hand(binding: Any) -> _Hand:
    alignment = None
    config = getattr(binding.retargeter, "alignment", None)
    if config is not None:
        from telerig.retarget.alignment import Alignment

        alignment = Alignment.from_config(config)
    return _Hand(binding.device, binding.part, binding.robot, alignment)


def _plan_marker(binding: Any) -> _Hand | None:
    """A whole-body binding's plan marker (``retargeter.plan_marker``), or None."""
    config = getattr(binding.retargeter, "plan_marker", None)
    if config is None or not getattr(binding.retargeter, "plan", False):
        return None
    from telerig.retarget.alignment import Alignment

    device = config.device or binding.device
    return _Hand(device, config.part, binding.robot, Alignment.from_config(config.alignment), "target")


def _finite(values: Any) -> bool:
    return bool(np.all(np.isfinite(np.asarray(values, dtype=np.float64))))


def _points(value: JsonValue, what: str) -> list[JsonValue]:
    """A preview path: at most :data:`_PLAN_POINTS` finite 3-vectors."""
    if not isinstance(value, list) or len(value) > _PLAN_POINTS:
        raise ValueError(f"plan {what} must be a list of at most {_PLAN_POINTS} points")
    out: list[JsonValue] = []
    for point in value:
        if not (isinstance(point, list) and len(point) == 3):
            raise ValueError(f"plan {what} points must be [x, y, z]")
        if not all(isinstance(v, int | float) and not isinstance(v, bool) for v in point):
            raise ValueError(f"plan {what} points must be numbers")
        if not _finite(point) or max(abs(float(v)) for v in point) > 1e3:  # type: ignore[arg-type]
            raise ValueError(f"plan {what} points must be finite, within 1 km")
        out.append([round(float(v), 4) for v in point])  # type: ignore[arg-type]
    return out


def _plan_cue(doc: dict[str, JsonValue]) -> dict[str, JsonValue]:
    """A robot's reach plan as the page draws it (:mod:`telerig.retarget.reach_plan`): id, status,
    reason, target position and the preview paths of the base (x, y, yaw) and grasp point.

    Raises:
        ValueError: a field is missing, of the wrong kind, too long or not finite.
    """
    status, reason, plan_id = doc.get("status"), doc.get("reason", ""), doc.get("id")
    if status not in _PLAN_STATUSES or not isinstance(reason, str):
        raise ValueError("plan status or reason is not one the planner sends")
    if plan_id is not None and not (isinstance(plan_id, str) and len(plan_id) <= 64):
        raise ValueError("plan id must be a short string")
    cue: dict[str, JsonValue] = {"id": plan_id, "status": status, "reason": reason[:_TEXT]}
    if plan_id is None:
        return cue
    target = doc.get("target")
    position = target.get("position") if isinstance(target, dict) else None
    cue["target"] = _points([position], "target")[0] if position is not None else None
    cue["base_path"] = _points(doc.get("base_path", []), "base path")
    cue["ee_path"] = _points(doc.get("ee_path", []), "grasp point path")
    return cue


def _clean(doc: dict[str, JsonValue]) -> dict[str, JsonValue]:
    """An aid's JSON state as the page may show it: its first 32 fields, texts cut to 200
    characters, lists to 16 scalars, nested objects left out.

    Raises:
        ValueError: a number is not finite (a fixture axis of NaN is not a fixture).
    """

    def scalar(value: JsonValue) -> JsonValue:
        if isinstance(value, float) and not math.isfinite(value):
            raise ValueError("a number in the aid state is not finite")
        return value[:_TEXT] if isinstance(value, str) else value

    out: dict[str, JsonValue] = {}
    for name, value in list(doc.items())[:32]:
        if isinstance(value, list):
            out[str(name)[:64]] = [scalar(v) for v in value[:16] if not isinstance(v, list | dict)]
        elif not isinstance(value, dict):
            out[str(name)[:64]] = scalar(value)
    return out
