"""BVH motion files: parse the HIERARCHY/MOTION text and run forward kinematics into BodySkeleton frames.

Real files differ in two ways this module reads from the skeleton itself rather than from a fixed list:
their unit (millimetres, centimetres, inches, metres, or the CMU mocap database's 1/0.45 inch,
0.056444 m), found by comparing the body's proportions with a human's (:func:`detect_scale`); and the
names of the arm joints (``LeftArm/LeftForeArm/LeftHand`` in the CMU and Mixamo skeletons, where
``LeftShoulder`` is the collar bone, or ``LeftShoulder/LeftElbow/LeftWrist`` in others), found by
walking the tree from the root: the spine chain up to the head, the two branches off it that reach
furthest to each side are the arms, and along each arm the hand is where the fingers branch (or,
without fingers, the shoulder-elbow-wrist triple spans the two long bones) (:func:`body_keypoints`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np

from telerig.devices.mocap._axes import MountTransform, matrix_to_quat
from telerig.errors import WireError
from telerig.ir.types import BodySkeleton, FloatArray, Stamp

__all__ = [
    "BVH_FUZZ_TARGET",
    "CMU_NAMES",
    "CMU_UNIT_M",
    "HUMAN_ARM_M",
    "HUMAN_HEIGHT_M",
    "MAX_RANGE_M",
    "UNITS_M",
    "BvhClip",
    "BvhJoint",
    "body_keypoints",
    "cmu_renames",
    "detect_scale",
    "parse_bvh",
]

_MAX_JOINTS = 512
#: Largest accepted |joint coordinate| [m] after scaling.
MAX_RANGE_M = 1e4
_MAX_VALUES = 20_000_000  # frames x channels: ~160 MB of float64, far above any real clip
_MAX_UNITS = 1e7  # |offset| and |position channel| in file units
_CHANNELS = ("Xposition", "Yposition", "Zposition", "Xrotation", "Yrotation", "Zrotation")

#: The CMU motion-capture database's length unit [m]: its ASF skeletons are in inches scaled by 0.45
#: (``length 0.45`` in their ``:units`` block), which its BVH release keeps.
CMU_UNIT_M = 0.0254 / 0.45
#: File units a BVH may be in [m].
UNITS_M: Mapping[str, float] = {"mm": 0.001, "cm": 0.01, "inch": 0.0254, "cmu": CMU_UNIT_M, "m": 1.0}
#: An adult's standing height and arm length, shoulder to wrist [m]: the prior the unit is chosen against.
HUMAN_HEIGHT_M = 1.70
HUMAN_ARM_M = 0.55
#: Keypoint (the humanoid retargeter's vocabulary) → the CMU / Mixamo joint name of it.
CMU_NAMES: Mapping[str, str] = {
    "right_shoulder": "RightArm",
    "right_elbow": "RightForeArm",
    "right_wrist": "RightHand",
    "left_shoulder": "LeftArm",
    "left_elbow": "LeftForeArm",
    "left_wrist": "LeftHand",
    "right_hip": "RightUpLeg",
    "left_hip": "LeftUpLeg",
}


@dataclass(frozen=True, slots=True)
class BvhJoint:
    """One joint of the hierarchy (End Sites included, with no channels).

    Attributes:
        name: Joint name; End Sites are named ``"<parent>_end"``.
        parent: Index of the parent joint, -1 for the root.
        offset: Rest translation from the parent [file units], file axes. Shape (3,).
        channels: Channel names in file order, e.g. ``("Zrotation", "Xrotation", "Yrotation")``.
        first_channel: Column of the first channel in the MOTION rows.
        end_site: Whether this is an End Site (a leaf with no channels).
    """

    name: str
    parent: int
    offset: tuple[float, float, float]
    channels: tuple[str, ...]
    first_channel: int
    end_site: bool = False


@dataclass(frozen=True, slots=True)
class BvhClip:
    """A parsed BVH clip.

    Attributes:
        joints: Joints in file order (parents before children).
        frame_time_s: Time between frames [s].
        motion: Channel values, degrees for rotations and file units for positions. Shape (F, C).
    """

    joints: tuple[BvhJoint, ...]
    frame_time_s: float
    motion: FloatArray

    @property
    def num_frames(self) -> int:
        """Number of frames F."""
        return int(self.motion.shape[0])

    @property
    def duration_s(self) -> float:
        """Clip length [s]: frames x frame time."""
        return self.num_frames * self.frame_time_s

    def rest_positions(self) -> FloatArray:
        """Joint positions of the rest pose (every OFFSET, no motion) in file units and axes. Shape (J, 3)."""
        pos = np.zeros((len(self.joints), 3))
        for j, joint in enumerate(self.joints):
            base = pos[joint.parent] if joint.parent >= 0 else 0.0
            pos[j] = base + np.asarray(joint.offset, dtype=np.float64)
        return pos

    def forward_kinematics(self, frames: slice | None = None) -> tuple[FloatArray, FloatArray]:
        """World joint positions and rotation matrices in file units and file axes.

        Joints with position channels take the channel values as their translation from the
        parent (the root: from the world origin), others their OFFSET. Rotation channels compose
        in file order as intrinsic rotations: ``R = R_c1 @ R_c2 @ R_c3`` (angles in degrees).

        Returns:
            positions, shape (F, J, 3), and rotations, shape (F, J, 3, 3), for the selected frames.
        """
        motion = self.motion[frames] if frames is not None else self.motion
        f, n = motion.shape[0], len(self.joints)
        pos = np.empty((f, n, 3))
        rot = np.empty((f, n, 3, 3))
        for j, joint in enumerate(self.joints):
            local_t = np.broadcast_to(np.asarray(joint.offset, dtype=np.float64), (f, 3)).copy()
            local_r = np.broadcast_to(np.eye(3), (f, 3, 3)).copy()
            for k, ch in enumerate(joint.channels):
                col = motion[:, joint.first_channel + k]
                axis = "XYZ".index(ch[0])
                if ch[1:] == "position":
                    local_t[:, axis] = col
                else:
                    local_r = local_r @ _elementary(axis, np.radians(col))
            if joint.parent < 0:
                pos[:, j] = local_t
                rot[:, j] = local_r
            else:
                pr = rot[:, joint.parent]
                pos[:, j] = pos[:, joint.parent] + np.einsum("fij,fj->fi", pr, local_t)
                rot[:, j] = pr @ local_r
        return pos, rot

    def skeletons(
        self,
        source_id: str,
        *,
        mount: MountTransform,
        frame_id: str = "mocap",
        frames: slice | None = None,
        include_end_sites: bool = True,
        rename: Mapping[int, str] | None = None,
    ) -> list[BodySkeleton]:
        """One :class:`BodySkeleton` per frame in ``frame_id`` (metres, operator axes via ``mount``).

        Stamps: ``seq`` = frame index, ``device_ns = capture_ns`` = frame index x frame time [ns];
        the playing device restamps them. ``rename`` gives joints (by index) another name, e.g.
        :func:`cmu_renames`.
        """
        pos, rot = self.forward_kinematics(frames)
        keep = [j for j, jt in enumerate(self.joints) if include_end_sites or not jt.end_site]
        renamed = rename or {}
        names = tuple(renamed.get(j, self.joints[j].name) for j in keep)
        p = mount.positions(pos[:, keep].reshape(-1, 3)).reshape(pos.shape[0], len(keep), 3)
        q = matrix_to_quat(mount.matrices(rot[:, keep]))
        if not (np.isfinite(p).all() and np.isfinite(q).all()) or (np.abs(p) > MAX_RANGE_M).any():
            raise WireError(
                f"BVH joint positions exceed ±{MAX_RANGE_M:g} m; "
                "check the scale, OFFSET and position channels"
            )
        start = (frames.start or 0) if frames is not None else 0
        out = []
        for i in range(p.shape[0]):
            k = start + i
            t_ns = round(k * self.frame_time_s * 1e9)
            out.append(BodySkeleton(Stamp(source_id, k, t_ns, t_ns), names, p[i], q[i], frame_id))
        return out


def _elementary(axis: int, angle: FloatArray) -> FloatArray:
    c, s = np.cos(angle), np.sin(angle)
    out = np.zeros((angle.shape[0], 3, 3))
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    out[:, axis, axis] = 1.0
    out[:, i, i] = c
    out[:, j, j] = c
    out[:, i, j] = -s
    out[:, j, i] = s
    return out


class _Tokens:
    __slots__ = ("items", "pos")

    def __init__(self, text: str) -> None:
        self.items = text.split()
        self.pos = 0

    def next(self, what: str) -> str:
        if self.pos >= len(self.items):
            raise WireError(f"BVH ends early: expected {what}")
        tok = self.items[self.pos]
        self.pos += 1
        return tok

    def expect(self, word: str) -> None:
        tok = self.next(repr(word))
        if tok != word:
            raise WireError(f"BVH token {self.pos}: expected {word!r}, got {tok[:40]!r}")

    def number(self, what: str) -> float:
        tok = self.next(what)
        try:
            value = float(tok)
        except ValueError:
            raise WireError(f"BVH token {self.pos}: {what} must be a number, got {tok[:40]!r}") from None
        if not math.isfinite(value) or abs(value) > _MAX_UNITS:
            raise WireError(f"BVH token {self.pos}: {what} must be finite and within ±{_MAX_UNITS:g}")
        return value


def _joint(
    tok: _Tokens, name: str, parent: int, joints: list[BvhJoint], ncols: list[int], end_site: bool = False
) -> None:
    if len(joints) >= _MAX_JOINTS:
        raise WireError(f"BVH has more than {_MAX_JOINTS} joints")
    if any(j.name == name for j in joints):
        raise WireError(f"BVH joint name {name[:40]!r} appears twice")
    tok.expect("{")
    tok.expect("OFFSET")
    offset = (tok.number("OFFSET x"), tok.number("OFFSET y"), tok.number("OFFSET z"))
    channels: tuple[str, ...] = ()
    if not end_site:  # End Sites have no CHANNELS
        tok.expect("CHANNELS")
        count = tok.next("channel count")
        if count not in ("0", "1", "2", "3", "4", "5", "6"):
            raise WireError(f"BVH joint {name[:40]!r}: channel count must be 0 to 6, got {count[:10]!r}")
        channels = tuple(tok.next("channel name") for _ in range(int(count)))
        for ch in channels:
            if ch not in _CHANNELS:
                raise WireError(
                    f"BVH joint {name[:40]!r}: unknown channel {ch[:20]!r}; valid: {', '.join(_CHANNELS)}"
                )
        if len(set(channels)) != len(channels):
            raise WireError(f"BVH joint {name[:40]!r}: a channel appears twice")
    index = len(joints)
    joints.append(BvhJoint(name, parent, offset, channels, ncols[0], end_site))
    ncols[0] += len(channels)
    while True:
        word = tok.next("JOINT, End Site or '}'")
        if word == "}":
            return
        if word == "JOINT":
            _joint(tok, tok.next("joint name"), index, joints, ncols)
        elif word == "End":
            tok.expect("Site")
            _joint(tok, name + "_end", index, joints, ncols, end_site=True)
        else:
            raise WireError(f"BVH token {tok.pos}: expected JOINT, End Site or '}}', got {word[:40]!r}")


def parse_bvh(text: str) -> BvhClip:
    """Parse BVH text (HIERARCHY with one ROOT, then MOTION) into a :class:`BvhClip`."""
    tok = _Tokens(text)
    tok.expect("HIERARCHY")
    tok.expect("ROOT")
    joints: list[BvhJoint] = []
    ncols = [0]
    _joint(tok, tok.next("root name"), -1, joints, ncols)
    tok.expect("MOTION")
    tok.expect("Frames:")
    frames_tok = tok.next("frame count")
    if not frames_tok.isdigit():
        raise WireError(f"BVH Frames: must be a non-negative integer, got {frames_tok[:20]!r}")
    frames = int(frames_tok)
    tok.expect("Frame")
    tok.expect("Time:")
    frame_time = tok.number("Frame Time")
    if not 1e-5 <= frame_time <= 10.0:
        raise WireError(f"BVH Frame Time must be in [1e-5, 10] s, got {frame_time}")
    cols = ncols[0]
    if frames < 1:
        raise WireError("BVH has no frames; Frames: must be at least 1")
    if frames * max(cols, 1) > _MAX_VALUES:
        raise WireError(f"BVH motion of {frames} x {cols} values exceeds {_MAX_VALUES}")
    values = tok.items[tok.pos :]
    if len(values) != frames * cols:
        raise WireError(
            f"BVH MOTION holds {len(values)} values; Frames {frames} x {cols} channels needs {frames * cols}"
        )
    try:
        motion = np.array(values, dtype=np.float64).reshape(frames, cols)
    except ValueError:
        raise WireError("BVH MOTION values must all be numbers") from None
    if not np.isfinite(motion).all() or (np.abs(motion) > _MAX_UNITS).any():
        raise WireError(f"BVH MOTION values must be finite and within ±{_MAX_UNITS:g}")
    motion.flags.writeable = False
    return BvhClip(tuple(joints), frame_time, motion)


def detect_scale(clip: BvhClip, up_axis: str = "+y") -> float:
    """File units to metres, from the body's proportions: the unit of :data:`UNITS_M` that makes the
    arms (shoulder to wrist, see :func:`body_keypoints`) closest to :data:`HUMAN_ARM_M`, or, without
    arms, the rest pose's standing height closest to :data:`HUMAN_HEIGHT_M` (ratios compared in log).

    A CMU database file (a 1.7 m person is 30 units tall) reads as its 0.056444 m unit, not as cm.
    """
    keypoints = body_keypoints(clip, up_axis, _orthogonal(up_axis))
    rest = clip.rest_positions()
    estimates = []
    for side in ("right", "left"):
        rows = [keypoints.get(f"{side}_{part}") for part in ("shoulder", "elbow", "wrist")]
        if all(r is not None for r in rows):
            s, e, w = (rest[r] for r in rows if r is not None)
            length = float(np.linalg.norm(e - s) + np.linalg.norm(w - e))
            if length > 0.0:
                estimates.append(HUMAN_ARM_M / length)
    if not estimates:
        axis = "xyz".index(up_axis[1])
        height = float(np.ptp(rest[:, axis]))
        if not height > 0.0:
            return 1.0
        estimates.append(HUMAN_HEIGHT_M / height)
    estimate = math.exp(sum(math.log(e) for e in estimates) / len(estimates))
    if not 0.0 < estimate < math.inf:  # a body of (nearly) zero size: nothing to compare
        return 1.0
    return min(UNITS_M.values(), key=lambda unit: abs(math.log(unit / estimate)))


def _orthogonal(up_axis: str) -> str:
    return "+x" if up_axis[1] != "x" else "+y"


def body_keypoints(clip: BvhClip, up_axis: str = "+y", forward_axis: str = "+z") -> dict[str, int]:
    """Joints of the shoulders, elbows, wrists and hips, found by the skeleton's structure.

    Walks the rest pose (up and forward name the file's axes, so left is told from right): the spine
    chain runs from the root to the highest leaf (the head); the arm of a side is the branch off the
    spine that reaches furthest to that side, followed to its leaf furthest from the spine; along it
    the wrist is the first joint where the fingers branch (two or more children, after two bones), else
    the shoulder-elbow-wrist triple is the most distal pair of bones whose length is within 15 % of the
    longest pair (the collar bone comes before it, the hand after). Joints at the same place as their
    parent (zero OFFSET) count as that parent. A hip is the first joint from the root towards the lowest
    foot of its side that stands off to that side.

    Returns:
        Keypoint name (``"right_shoulder"`` ... ``"left_wrist"``, ``"right_hip"``, ``"left_hip"``) →
        index in ``clip.joints``; keypoints it cannot find are left out.
    """
    mount = MountTransform(up=up_axis, forward=forward_axis)
    p = mount.positions(clip.rest_positions())  # x forward, y left, z up
    n = len(clip.joints)
    children: list[list[int]] = [[] for _ in range(n)]
    for j, joint in enumerate(clip.joints):
        if joint.parent >= 0:
            children[joint.parent].append(j)
    height = float(np.ptp(p[:, 2]))
    if n < 2 or not height > 0.0:
        return {}
    leaves = [j for j in range(n) if not children[j]]
    spine = _path(clip, max(leaves, key=lambda j: p[j, 2]))
    found: dict[str, int] = {}
    for side, sign in (("right", -1.0), ("left", 1.0)):
        arm = _arm(clip, p, children, spine, sign, height)
        if arm is not None:
            found[f"{side}_shoulder"], found[f"{side}_elbow"], found[f"{side}_wrist"] = arm
        hip = _hip(clip, p, leaves, sign, height)
        if hip is not None:
            found[f"{side}_hip"] = hip
    return found


def _path(clip: BvhClip, leaf: int) -> list[int]:
    """Joints from the root to ``leaf``, root first."""
    path = [leaf]
    while clip.joints[path[-1]].parent >= 0:
        path.append(clip.joints[path[-1]].parent)
    return path[::-1]


def _subtree(children: list[list[int]], top: int) -> list[int]:
    out, stack = [], [top]
    while stack:
        j = stack.pop()
        out.append(j)
        stack.extend(children[j])
    return out


def _arm(
    clip: BvhClip, p: FloatArray, children: list[list[int]], spine: list[int], sign: float, height: float
) -> tuple[int, int, int] | None:
    """(shoulder, elbow, wrist) of the arm on the ``sign`` side (+1 left), or None."""
    on_spine = set(spine)
    best: tuple[float, int, int] | None = None  # (reach to the side, attach joint, branch top)
    for attach in spine[1:]:  # a branch at the root is a leg
        for top in children[attach]:
            if top in on_spine:
                continue
            sub = _subtree(children, top)
            if float(np.min(p[sub, 2])) < p[spine[0], 2] - 0.25 * height:
                continue  # reaches the floor: a leg
            reach = float(np.max(sign * (p[sub, 1] - p[attach, 1])))
            if reach > 0.08 * height and (best is None or reach > best[0]):
                best = (reach, attach, top)
    if best is None:
        return None
    _, attach, top = best
    sub = _subtree(children, top)
    tip = max(sub, key=lambda j: float(np.linalg.norm(p[j] - p[attach])))
    chain = _path(clip, tip)
    chain = chain[chain.index(top) :]
    # Distinct points along the arm: joints at their parent's place count as that parent.
    eps = 0.01 * height
    points: list[list[int]] = []  # groups of joints at one place, proximal first
    last = p[attach]
    for j in chain:
        if float(np.linalg.norm(p[j] - last)) > eps:
            points.append([j])
            last = p[j]
        elif points:
            points[-1].append(j)
    if len(points) < 3:
        return None
    for k in range(2, len(points)):
        if any(len(children[j]) >= 2 for j in points[k]):  # the fingers branch at the wrist
            return points[k - 2][0], points[k - 1][0], points[k][0]
    bones = [float(np.linalg.norm(p[points[k + 1][0]] - p[points[k][0]])) for k in range(len(points) - 1)]
    pairs = [bones[k] + bones[k + 1] for k in range(len(bones) - 1)]
    k = max(i for i, pair in enumerate(pairs) if pair >= 0.85 * max(pairs))
    return points[k][0], points[k + 1][0], points[k + 2][0]


def _hip(clip: BvhClip, p: FloatArray, leaves: list[int], sign: float, height: float) -> int | None:
    """The hip joint of the leg on the ``sign`` side (+1 left), or None without such a leg."""
    root = 0
    feet = [j for j in leaves if p[j, 2] < p[root, 2] - 0.25 * height and sign * (p[j, 1] - p[root, 1]) > 0]
    if not feet:
        return None
    for j in _path(clip, min(feet, key=lambda j: p[j, 2]))[1:]:
        if sign * (p[j, 1] - p[root, 1]) > 0.02 * height:
            return j
    return None


def cmu_renames(clip: BvhClip, up_axis: str = "+y", forward_axis: str = "+z") -> dict[int, str]:
    """Joint index → new name that gives the joints :func:`body_keypoints` finds their CMU names
    (:data:`CMU_NAMES`), so one name mapping reads every file. A file joint that already bears one of
    those names without being that keypoint becomes ``"<name>_file"``; names stay unique."""
    renames = {j: CMU_NAMES[k] for k, j in body_keypoints(clip, up_axis, forward_axis).items()}
    given = set(renames.values())
    for j, joint in enumerate(clip.joints):
        if j not in renames and joint.name in given:
            renames[j] = f"{joint.name}_file"
    return {j: name for j, name in renames.items() if name != clip.joints[j].name}


def _fuzz(data: bytes) -> object:
    """Parse ``data`` as BVH text and run forward kinematics; only WireError escapes."""
    clip = parse_bvh(data.decode("utf-8", errors="replace"))
    return clip.skeletons("fuzz", mount=MountTransform(scale=detect_scale(clip)), frames=slice(0, 4))


#: BVH bytes in, skeleton frames out; raises only :class:`WireError`.
BVH_FUZZ_TARGET: Callable[[bytes], object] = _fuzz
