"""Dexterous robot hands (Inspire, Ability, Allegro) as mesh-free kinematic MuJoCo models in the hand frame.

Each model is loaded by path from the package that ships it (robosuite and robosuite_models MJCF,
example-robot-data URDF; none is imported), with every geom, mesh, actuator and sensor removed so
only the kinematic tree compiles. The model is re-rooted so that its world frame is the *hand
frame* shared with the human side (:mod:`telerig.retarget.hand.vectors`): origin at the wrist
(keypoint 0), x from the wrist toward the middle finger's MCP, z out of the back of the hand,
y = z x x (toward the thumb on a right hand). The frame is built from the robot's own wrist and
knuckle points with :func:`hand_frame_axes`, the same function that builds it from human keypoints,
so both sides agree anatomically without hand-tuned rotations.

Joint couplings (mimic joints) are read from the compiled model's joint equality constraints
(``q_follower = c0 + c1 q_leader``), which MuJoCo creates from URDF ``<mimic>`` tags. robosuite's
Inspire and Ability MJCF drive every joint on its own, whereas the real hands have 6 motors and
linkages; those linkages (values of the vendors' URDFs, as published in dex-urdf) are added as
equality constraints unless ``couplings=False``. Full joint positions are ``q_full = A q_act + b``.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Literal

import mujoco
import numpy as np

from telerig.errors import RobotError
from telerig.ir.types import FloatArray, Handedness
from telerig.robots.models.mjcf import example_robot_data_robots, robosuite_assets, robosuite_models_assets

__all__ = [
    "HAND_MODELS",
    "HUMAN_REACH_M",
    "HandKinematics",
    "HandModelName",
    "hand_frame_axes",
    "keypoint_site",
    "kinematic_urdf",
    "load_hand",
]

HandModelName = Literal["inspire", "ability", "allegro"]
#: Hand models :func:`load_hand` builds.
HAND_MODELS: tuple[HandModelName, ...] = ("inspire", "ability", "allegro")

_Vec3 = tuple[float, float, float]
#: Wrist to middle fingertip distance of an open adult hand [m] (the glove's default hand model).
HUMAN_REACH_M = 0.19


def keypoint_site(index: int) -> str:
    """Name of the site that stands for MediaPipe keypoint ``index`` on a robot hand model."""
    return f"kp{index}"


def hand_frame_axes(
    wrist: FloatArray,
    index_mcp: FloatArray,
    middle_mcp: FloatArray,
    little_mcp: FloatArray,
    handedness: Handedness,
) -> FloatArray:
    """Rotation whose columns are the hand frame's x, y, z axes, in the frame of the given points.

    x points from the wrist to the middle MCP; z is the palm normal out of the back of the hand
    (from the index and little MCPs, orthogonalized against x); y = z x x. Points are [m], shape (3,).

    Raises:
        ValueError: the points are degenerate (middle MCP on the wrist, or knuckles collinear with it).
    """
    # On Python floats: a retargeter calls this every frame, and NumPy's per-call overhead on
    # 3-vectors was most of its ~30 us (benchmarks/hand_retarget.py).
    w, i, m, lt = (p.tolist() for p in (wrist, index_mcp, middle_mcp, little_mcp))
    x0, x1, x2 = m[0] - w[0], m[1] - w[1], m[2] - w[2]
    nx = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
    if not nx > 1e-6:
        raise ValueError("hand frame is degenerate: the middle MCP coincides with the wrist")
    x0, x1, x2 = x0 / nx, x1 / nx, x2 / nx
    a, b = (lt, i) if handedness != "left" else (i, lt)
    a0, a1, a2 = a[0] - w[0], a[1] - w[1], a[2] - w[2]
    b0, b1, b2 = b[0] - w[0], b[1] - w[1], b[2] - w[2]
    n0, n1, n2 = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
    along = n0 * x0 + n1 * x1 + n2 * x2
    z0, z1, z2 = n0 - along * x0, n1 - along * x1, n2 - along * x2
    nz = math.sqrt(z0 * z0 + z1 * z1 + z2 * z2)
    if not nz > 1e-9:
        raise ValueError("hand frame is degenerate: the wrist and knuckles are collinear")
    z0, z1, z2 = z0 / nz, z1 / nz, z2 / nz
    y0, y1, y2 = z1 * x2 - z2 * x1, z2 * x0 - z0 * x2, z0 * x1 - z1 * x0
    return np.array(((x0, y0, z0), (x1, y1, z1), (x2, y2, z2)))


@dataclass(frozen=True, slots=True)
class HandKinematics:
    """A robot hand's kinematic model; its world frame is the hand frame (see the module docstring).

    Attributes:
        name: Model name, e.g. ``"inspire_right"``.
        handedness: Which hand the model is.
        model: Compiled mesh-free MuJoCo model (hinge joints only, ``nq == nv``).
        joint_names: All joints, model order. Length nq.
        actuated: Independent joints (the optimization variables), model order. Length na.
        coupling: ``A`` in ``q_full = A q_act + b``. Shape (nq, na).
        offset: ``b`` [rad]. Shape (nq,).
        lower: Lower bound of the actuated joints [rad], tightened so that coupled joints stay in their
            range. Shape (na,).
        upper: Upper bound of the actuated joints [rad]. Shape (na,).
        keypoints: MediaPipe keypoint index -> site name for the robot points that stand for human
            keypoints (0 the wrist, 4/8/12/16/20 fingertips, 2 the thumb MCP, ...).
        fingertips: Fingertip sites, thumb first; four on a four-fingered hand.
        default_scale: Human-to-robot vector scale that suits this hand: the robot's wrist to
            middle fingertip distance with the hand open over an adult's (:data:`HUMAN_REACH_M`).
    """

    name: str
    handedness: Handedness
    model: mujoco.MjModel
    joint_names: tuple[str, ...]
    actuated: tuple[str, ...]
    coupling: FloatArray
    offset: FloatArray
    lower: FloatArray
    upper: FloatArray
    keypoints: Mapping[int, str]
    fingertips: tuple[str, ...]
    default_scale: float
    source: Path = field(default=Path())

    def full(self, q_act: FloatArray) -> FloatArray:
        """All joint positions [rad] from the actuated ones. Shape (na,) -> (nq,)."""
        out: FloatArray = self.coupling @ q_act + self.offset
        return out

    def neutral(self) -> FloatArray:
        """An open-hand actuated configuration: zero clipped into the bounds [rad]. Shape (na,)."""
        out: FloatArray = np.clip(np.zeros(len(self.actuated)), self.lower, self.upper)
        return out

    def keypoint_positions(self, q_act: FloatArray, indices: tuple[int, ...] | None = None) -> FloatArray:
        """Forward kinematics: robot keypoints [m] in the hand frame. Shape (k, 3), rows in ``indices`` order.

        Args:
            q_act: Actuated joint positions [rad]. Shape (na,).
            indices: MediaPipe indices to return; all of :attr:`keypoints`, sorted, when None.
        """
        idx = tuple(sorted(self.keypoints)) if indices is None else indices
        data = mujoco.MjData(self.model)
        data.qpos[:] = self.full(np.asarray(q_act, dtype=np.float64))
        mujoco.mj_kinematics(self.model, data)
        out: FloatArray = np.array([data.site(self.keypoints[i]).xpos for i in idx])
        return out


@dataclass(frozen=True, slots=True)
class _Source:
    """Where a hand's file is and which of its points stand for human keypoints."""

    file: Callable[[Handedness], Path]
    kind: Literal["mjcf", "urdf"]
    #: MediaPipe index -> (body, position in the body [m]) for a right hand.
    points: Mapping[int, tuple[str, _Vec3]]
    #: Knuckle keypoints used for the hand frame: index, middle, little (ring on 4 fingers).
    frame_points: tuple[int, int, int]
    #: Hardware couplings added when the file has none: (follower, leader, multiplier, offset).
    couplings: tuple[tuple[str, str, float, float], ...]
    #: Body and joint name rewrite for a left hand; names are shared when None.
    left_name: Callable[[str], str] | None = None
    #: Left hands mirror the y coordinate of the point offsets in their link frames.
    left_mirror_y: bool = False


def _robosuite_gripper(name: str) -> Callable[[Handedness], Path]:
    def path(side: Handedness) -> Path:
        return robosuite_assets() / "grippers" / f"{name}_{side}_hand.xml"

    return path


def _robosuite_models_gripper(name: str) -> Callable[[Handedness], Path]:
    def path(side: Handedness) -> Path:
        return robosuite_models_assets() / "grippers" / f"{name}_{side}_hand.xml"

    return path


def _allegro(side: Handedness) -> Path:
    return example_robot_data_robots() / "allegro_hand_description" / "urdf" / f"allegro_{side}_hand.urdf"


def _inspire_points() -> dict[int, tuple[str, _Vec3]]:
    # Fingertip offsets in the distal links: the tip links of the Inspire URDF (dex-urdf).
    z = (0.0, 0.0, 0.0)
    return {
        0: ("r_palm", z),
        1: ("r_thumb_proximal_1", z),
        2: ("r_thumb_middle", z),
        3: ("r_thumb_distal", z),
        4: ("r_thumb_distal", (0.0202, 0.0140, -0.006)),
        5: ("r_index_proximal", z),
        6: ("r_index_distal", z),
        8: ("r_index_distal", (-0.0008, 0.045, -0.005)),
        9: ("r_middle_proximal", z),
        10: ("r_middle_distal", z),
        12: ("r_middle_distal", (-0.001, 0.048, -0.005)),
        13: ("r_ring_proximal", z),
        14: ("r_ring_distal", z),
        16: ("r_ring_distal", (-0.0008, 0.045, -0.005)),
        17: ("r_pinky_proximal", z),
        18: ("r_pinky_distal", z),
        20: ("r_pinky_distal", (-0.0008, 0.037, -0.005)),
    }


def _ability_points() -> dict[int, tuple[str, _Vec3]]:
    z = (0.0, 0.0, 0.0)
    tip = (0.035, -0.018, 0.0)  # the MJCF's own <finger>_tip sites
    points: dict[int, tuple[str, _Vec3]] = {
        0: ("base", z),
        1: ("thumb_L1", z),
        2: ("thumb_L2", z),
        4: ("thumb_L2", (0.065, 0.016, 0.0)),
    }
    for finger, mcp in (("index", 5), ("middle", 9), ("ring", 13), ("pinky", 17)):
        points[mcp] = (f"{finger}_L1", z)
        points[mcp + 1] = (f"{finger}_L2", z)
        points[mcp + 3] = (f"{finger}_L2", tip)
    return points


def _allegro_points() -> dict[int, tuple[str, _Vec3]]:
    z = (0.0, 0.0, 0.0)
    # Wrist: the bottom of the palm box, 95 mm below the finger bases (palm_link origin).
    points: dict[int, tuple[str, _Vec3]] = {
        0: ("palm_link", (0.0, 0.0, -0.095)),
        1: ("link_12.0", z),
        2: ("link_14.0", z),
        3: ("link_15.0", z),
        4: ("link_15.0_tip", z),
    }
    for first, mcp in ((0, 5), (4, 9), (8, 13)):  # index, middle, ring; no little finger
        points[mcp] = (f"link_{first + 1}.0", z)
        points[mcp + 1] = (f"link_{first + 2}.0", z)
        points[mcp + 2] = (f"link_{first + 3}.0", z)
        points[mcp + 3] = (f"link_{first + 3}.0_tip", z)
    return points


def _inspire_couplings() -> tuple[tuple[str, str, float, float], ...]:
    out = [
        ("joint_r_thumb_middle", "joint_r_thumb_proximal_2", 1.334, 0.0),
        ("joint_r_thumb_distal", "joint_r_thumb_proximal_2", 0.667, 0.0),
    ]
    for finger in ("index", "middle", "ring", "pinky"):
        out.append((f"joint_r_{finger}_distal", f"joint_r_{finger}_proximal", 1.06399, -0.04545))
    return tuple(out)


def _inspire_left(name: str) -> str:
    if name.startswith("joint_r_"):
        return "joint_l_" + name.removeprefix("joint_r_")
    return "l_" + name.removeprefix("r_") if name.startswith("r_") else name


_SOURCES: dict[HandModelName, _Source] = {
    "inspire": _Source(
        file=_robosuite_gripper("inspire"),
        kind="mjcf",
        points=_inspire_points(),
        frame_points=(5, 9, 17),
        couplings=_inspire_couplings(),
        left_name=_inspire_left,
        left_mirror_y=True,
    ),
    "ability": _Source(
        file=_robosuite_models_gripper("ability"),
        kind="mjcf",
        points=_ability_points(),
        frame_points=(5, 9, 17),
        couplings=tuple(
            (f"{f}_q2", f"{f}_q1", 1.05851325, 0.72349796) for f in ("index", "middle", "ring", "pinky")
        ),
    ),
    "allegro": _Source(
        file=_allegro,
        kind="urdf",
        points=_allegro_points(),
        frame_points=(5, 9, 13),
        couplings=(),
    ),
}

# MJCF elements that carry no kinematics (or reference meshes); removed before MuJoCo parses the file.
_MJCF_DROP = ("geom", "site", "camera", "light", "inertial")
_MJCF_SECTIONS_DROP = ("asset", "actuator", "sensor", "tendon", "contact", "keyframe", "visual", "statistic")
_MASS = 1e-3  # [kg] placeholder mass of every body: the model is never simulated
_INERTIA = 1e-7  # [kg m^2]


def _strip_mjcf(path: Path) -> str:
    root = ET.parse(path).getroot()
    for section in _MJCF_SECTIONS_DROP:
        for element in root.findall(section):
            root.remove(element)
    for default in root.iter("default"):
        for element in list(default):
            if element.tag in ("geom", "site", "mesh", "material"):
                default.remove(element)
    for parent in list(root.iter()):
        for element in list(parent):
            if element.tag in _MJCF_DROP:
                parent.remove(element)
    return ET.tostring(root, encoding="unicode")


def _strip_urdf(path: Path) -> str:
    root = ET.parse(path).getroot()
    for link in root.iter("link"):
        for element in list(link):
            if element.tag in ("visual", "collision", "inertial"):
                link.remove(element)
    for element in root.findall("mujoco"):
        root.remove(element)
    # Keep fixed links (fingertips) as bodies; never look for mesh files.
    ext = ET.SubElement(root, "mujoco")
    ET.SubElement(ext, "compiler", fusestatic="false", discardvisual="true", strippath="false")
    return ET.tostring(root, encoding="unicode")


def _spec(source: _Source, path: Path) -> mujoco.MjSpec:
    if not path.is_file():
        raise RobotError(f"hand model file not found: {path}")
    try:
        text = _strip_mjcf(path) if source.kind == "mjcf" else _strip_urdf(path)
        spec = mujoco.MjSpec.from_string(text)
    except (ET.ParseError, ValueError) as exc:
        raise RobotError(f"cannot load {path}: {exc}") from exc
    spec.compiler.degree = False if source.kind == "mjcf" else spec.compiler.degree
    for body in spec.bodies:
        if body.name != "world":
            body.mass = _MASS
            body.inertia = [_INERTIA] * 3
            body.explicitinertial = True
    return spec


def _compile(spec: mujoco.MjSpec, path: Path) -> mujoco.MjModel:
    try:
        return spec.compile()
    except ValueError as exc:
        raise RobotError(f"cannot compile the hand model {path}: {exc}") from exc


def _couplings(model: mujoco.MjModel) -> dict[int, tuple[int, float, float]]:
    """follower joint id -> (leader joint id, multiplier, offset) from the joint equalities."""
    out: dict[int, tuple[int, float, float]] = {}
    for i in range(model.neq):
        if model.eq_type[i] != mujoco.mjtEq.mjEQ_JOINT or not model.eq_active0[i]:
            continue
        follower, leader = int(model.eq_obj1id[i]), int(model.eq_obj2id[i])
        c = model.eq_data[i, :5]
        if leader < 0 or np.any(np.abs(c[2:]) > 0.0):
            raise RobotError(
                f"joint coupling of '{model.joint(follower).name}' is not linear in one leader joint; "
                "only q1 = c0 + c1 q2 equalities are supported"
            )
        out[follower] = (leader, float(c[1]), float(c[0]))
    for follower, (leader, _, _) in out.items():
        if leader in out:
            raise RobotError(
                f"joint '{model.joint(follower).name}' follows '{model.joint(leader).name}', "
                "which follows another joint; chained couplings are not supported"
            )
    return out


def load_hand(
    name: HandModelName, handedness: Handedness = "right", *, couplings: bool = True
) -> HandKinematics:
    """Build the kinematic model of a robot hand, re-rooted in the hand frame.

    Args:
        name: ``"inspire"`` (6 motors, 12 joints), ``"ability"`` (6 motors, 10 joints) or
            ``"allegro"`` (16 joints, four fingers).
        handedness: Which hand.
        couplings: Add the real hand's linkages where the model file drives every joint on its
            own (Inspire, Ability); couplings the file declares are always kept.

    Raises:
        DependencyError: the package that ships the model is not installed.
        RobotError: the model file is missing, does not compile, or lacks a body this module names.
    """
    if name not in _SOURCES:
        raise RobotError(f"unknown hand model {name!r}. Available: {', '.join(HAND_MODELS)}")
    if handedness not in ("left", "right"):
        raise RobotError(f"handedness must be 'left' or 'right', got {handedness!r}")
    source = _SOURCES[name]
    path = source.file(handedness)
    spec = _spec(source, path)
    rename = source.left_name if handedness == "left" and source.left_name is not None else (lambda s: s)
    mirror = -1.0 if handedness == "left" and source.left_mirror_y else 1.0

    bodies = {b.name for b in spec.bodies}
    for index, (body, pos) in sorted(source.points.items()):
        body_name = rename(body)
        if body_name not in bodies:
            raise RobotError(
                f"{path.name}: body '{body_name}' not found. Available: {', '.join(sorted(bodies))}"
            )
        spec.body(body_name).add_site(name=keypoint_site(index), pos=[pos[0], mirror * pos[1], pos[2]])
    if couplings:
        joints = {j.name for j in spec.joints}
        declared = {eq.name1 for eq in spec.equalities if eq.type == mujoco.mjtEq.mjEQ_JOINT}
        for follower_name, leader_name, multiplier, offset in source.couplings:
            follower, leader = rename(follower_name), rename(leader_name)
            for joint in (follower, leader):
                if joint not in joints:
                    raise RobotError(
                        f"{path.name}: joint '{joint}' not found. Available: {', '.join(sorted(joints))}"
                    )
            if follower in declared:
                continue
            eq = spec.add_equality(
                type=mujoco.mjtEq.mjEQ_JOINT, name1=follower, name2=leader, objtype=mujoco.mjtObj.mjOBJ_JOINT
            )
            eq.data[:5] = [offset, multiplier, 0.0, 0.0, 0.0]

    # Re-root: place the model so that the hand frame, built from its own wrist and knuckles at
    # the open pose, is the world frame.
    model = _compile(spec, path)
    data = mujoco.MjData(model)
    data.qpos[:] = np.clip(0.0, model.jnt_range[:, 0], model.jnt_range[:, 1])
    mujoco.mj_kinematics(model, data)
    point = {i: data.site(keypoint_site(i)).xpos.copy() for i in (0, *source.frame_points)}
    i_idx, i_mid, i_lit = source.frame_points
    rot = hand_frame_axes(point[0], point[i_idx], point[i_mid], point[i_lit], handedness)
    origin = point[0]
    for child in spec.worldbody.bodies:
        world = _pose_in_world(model, data, child.name)
        pos = rot.T @ (world[0] - origin)
        quat = np.empty(4)
        mujoco.mju_mat2Quat(quat, (rot.T @ world[1]).ravel())
        child.pos, child.quat = pos, quat
    model = _compile(spec, path)
    data = mujoco.MjData(model)
    data.qpos[:] = np.clip(0.0, model.jnt_range[:, 0], model.jnt_range[:, 1])
    mujoco.mj_kinematics(model, data)
    reach = float(np.linalg.norm(data.site(keypoint_site(12)).xpos))
    return _kinematics(
        f"{name}_{handedness}", handedness, model, source, path, round(reach / HUMAN_REACH_M, 2)
    )


def _pose_in_world(model: mujoco.MjModel, data: mujoco.MjData, body: str) -> tuple[FloatArray, FloatArray]:
    b = data.body(body)
    return b.xpos.copy(), b.xmat.reshape(3, 3).copy()


def _kinematics(
    name: str, handedness: Handedness, model: mujoco.MjModel, source: _Source, path: Path, scale: float
) -> HandKinematics:
    if model.nq != model.nv or np.any(model.jnt_type != mujoco.mjtJoint.mjJNT_HINGE):
        raise RobotError(f"{path.name}: only hinge joints are supported in a hand model")
    nq = model.nq
    coupled = _couplings(model)
    act_ids = [j for j in range(nq) if j not in coupled]
    col = {j: k for k, j in enumerate(act_ids)}
    a = np.zeros((nq, len(act_ids)))
    b = np.zeros(nq)
    limited = model.jnt_limited.astype(bool)
    lo = np.where(limited, model.jnt_range[:, 0], -np.inf)
    hi = np.where(limited, model.jnt_range[:, 1], np.inf)
    lower, upper = lo[act_ids].copy(), hi[act_ids].copy()
    for j in range(nq):
        if j not in coupled:
            a[j, col[j]] = 1.0
            continue
        leader, mult, off = coupled[j]
        a[j, col[leader]] = mult
        b[j] = off
        if mult == 0.0:
            continue
        # lo_j <= mult * q + off <= hi_j, as bounds on the leader q.
        l1, l2 = (lo[j] - off) / mult, (hi[j] - off) / mult
        k = col[leader]
        lower[k] = max(lower[k], min(l1, l2))
        upper[k] = min(upper[k], max(l1, l2))
    names = tuple(model.joint(j).name for j in range(nq))
    empty = [names[act_ids[k]] for k in range(len(act_ids)) if lower[k] > upper[k]]
    if empty:
        raise RobotError(f"{path.name}: the couplings leave no valid range for joint(s) {', '.join(empty)}")
    for arr in (a, b, lower, upper):
        arr.flags.writeable = False
    sites = {i: keypoint_site(i) for i in sorted(source.points)}
    tips = tuple(keypoint_site(i) for i in (4, 8, 12, 16, 20) if i in source.points)
    return HandKinematics(
        name=name,
        handedness=handedness,
        model=model,
        joint_names=names,
        actuated=tuple(names[j] for j in act_ids),
        coupling=a,
        offset=b,
        lower=lower,
        upper=upper,
        keypoints=MappingProxyType(sites),
        fingertips=tips,
        default_scale=scale,
        source=path,
    )


def _rpy(mat: FloatArray) -> tuple[float, float, float]:
    """URDF roll-pitch-yaw (R = Rz(yaw) Ry(pitch) Rx(roll)) of a rotation matrix."""
    pitch = math.asin(max(-1.0, min(1.0, -float(mat[2, 0]))))
    if abs(float(mat[2, 0])) < 1.0 - 1e-12:
        roll = math.atan2(float(mat[2, 1]), float(mat[2, 2]))
        yaw = math.atan2(float(mat[1, 0]), float(mat[0, 0]))
    else:  # gimbal lock: fold the roll into the yaw
        roll = 0.0
        yaw = math.atan2(-float(mat[0, 1]), float(mat[1, 1]))
    return roll, pitch, yaw


def _origin(parent: ET.Element, pos: FloatArray, quat: FloatArray) -> None:
    mat = np.empty(9)
    mujoco.mju_quat2Mat(mat, quat)
    rpy = _rpy(mat.reshape(3, 3))
    ET.SubElement(
        parent, "origin", xyz=" ".join(f"{v:.9g}" for v in pos), rpy=" ".join(f"{v:.9g}" for v in rpy)
    )


def kinematic_urdf(hand: HandKinematics) -> str:
    """The hand's kinematic model as URDF text, for tools that read URDF (e.g. dex-retargeting).

    The root link ``hand_frame`` is the hand frame; every body becomes a link named as the body
    (no geometry, placeholder inertia), every keypoint site a fixed link named as the site
    (``kp0``, ``kp4``, ...). Actuated joints carry :attr:`HandKinematics.lower`/``upper`` (the
    bounds the couplings leave), coupled joints a ``<mimic>`` tag and their own range.

    Raises:
        RobotError: a joint is not on its body's origin (URDF cannot express that here).
    """
    model = hand.model
    robot = ET.Element("robot", name=hand.name)
    ET.SubElement(robot, "link", name="hand_frame")
    link_of = {0: "hand_frame"}

    def link(name: str) -> None:
        element = ET.SubElement(robot, "link", name=name)
        inertial = ET.SubElement(element, "inertial")
        ET.SubElement(inertial, "mass", value=f"{_MASS:g}")
        ET.SubElement(
            inertial,
            "inertia",
            ixx=f"{_INERTIA:g}",
            iyy=f"{_INERTIA:g}",
            izz=f"{_INERTIA:g}",
            ixy="0",
            ixz="0",
            iyz="0",
        )

    act = {name: k for k, name in enumerate(hand.actuated)}
    for body in range(1, model.nbody):
        name = model.body(body).name or f"body{body}"
        link_of[body] = name
        link(name)
        n_jnt = int(model.body_jntnum[body])
        if n_jnt > 1:
            raise RobotError(f"{hand.name}: body '{name}' has {n_jnt} joints; URDF allows one per link")
        joint = ET.SubElement(robot, "joint")
        ET.SubElement(joint, "parent", link=link_of[int(model.body_parentid[body])])
        ET.SubElement(joint, "child", link=name)
        _origin(joint, model.body_pos[body], model.body_quat[body])
        if n_jnt == 0:
            joint.set("name", f"{name}_fixed")
            joint.set("type", "fixed")
            continue
        j = int(model.body_jntadr[body])
        if np.any(np.abs(model.jnt_pos[j]) > 1e-9):
            raise RobotError(f"{hand.name}: joint '{model.joint(j).name}' is off its body's origin")
        jname = model.joint(j).name
        joint.set("name", jname)
        joint.set("type", "revolute")
        ET.SubElement(joint, "axis", xyz=" ".join(f"{v:.9g}" for v in model.jnt_axis[j]))
        if jname in act:
            lo, hi = float(hand.lower[act[jname]]), float(hand.upper[act[jname]])
        else:
            lo, hi = (float(v) for v in model.jnt_range[j])
            leader = int(np.flatnonzero(hand.coupling[j])[0])
            ET.SubElement(
                joint,
                "mimic",
                joint=hand.actuated[leader],
                multiplier=f"{float(hand.coupling[j, leader]):.9g}",
                offset=f"{float(hand.offset[j]):.9g}",
            )
        ET.SubElement(joint, "limit", lower=f"{lo:.9g}", upper=f"{hi:.9g}", effort="1", velocity="10")
    for site in hand.keypoints.values():
        sid = model.site(site).id
        link(site)
        joint = ET.SubElement(robot, "joint", name=f"{site}_fixed", type="fixed")
        ET.SubElement(joint, "parent", link=link_of[int(model.site_bodyid[sid])])
        ET.SubElement(joint, "child", link=site)
        _origin(joint, model.site_pos[sid], model.site_quat[sid])
    ET.indent(robot)
    return ET.tostring(robot, encoding="unicode")
