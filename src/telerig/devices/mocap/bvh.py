"""BVH motion files: parse the HIERARCHY/MOTION text and run forward kinematics into BodySkeleton frames."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from telerig.devices.mocap._axes import MountTransform, matrix_to_quat
from telerig.errors import WireError
from telerig.ir.types import BodySkeleton, FloatArray, Stamp

__all__ = ["BVH_FUZZ_TARGET", "MAX_RANGE_M", "BvhClip", "BvhJoint", "detect_scale", "parse_bvh"]

_MAX_JOINTS = 512
#: Largest accepted |joint coordinate| [m] after scaling.
MAX_RANGE_M = 1e4
_MAX_VALUES = 20_000_000  # frames x channels: ~160 MB of float64, far above any real clip
_MAX_UNITS = 1e7  # |offset| and |position channel| in file units
_CHANNELS = ("Xposition", "Yposition", "Zposition", "Xrotation", "Yrotation", "Zrotation")


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
    ) -> list[BodySkeleton]:
        """One :class:`BodySkeleton` per frame in ``frame_id`` (metres, operator axes via ``mount``).

        Stamps: ``seq`` = frame index, ``device_ns = capture_ns`` = frame index x frame time [ns];
        the playing device restamps them.
        """
        pos, rot = self.forward_kinematics(frames)
        keep = [j for j, jt in enumerate(self.joints) if include_end_sites or not jt.end_site]
        names = tuple(self.joints[j].name for j in keep)
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
    """File units to metres from the hip height in the first frame: > 300 mm, > 10 cm, else m.

    The hip height is the root's height above the lowest joint; a human's is about 0.9 m.
    """
    pos, _ = clip.forward_kinematics(slice(0, 1))
    axis = "xyz".index(up_axis[1])
    sign = -1.0 if up_axis[0] == "-" else 1.0
    heights = sign * pos[0, :, axis]
    hip = float(heights[0] - heights.min())
    if hip > 300.0:
        return 0.001
    if hip > 10.0:
        return 0.01
    return 1.0


def _fuzz(data: bytes) -> object:
    """Parse ``data`` as BVH text and run forward kinematics; only WireError escapes."""
    clip = parse_bvh(data.decode("utf-8", errors="replace"))
    return clip.skeletons("fuzz", mount=MountTransform(scale=detect_scale(clip)), frames=slice(0, 4))


#: BVH bytes in, skeleton frames out; raises only :class:`WireError`.
BVH_FUZZ_TARGET: Callable[[bytes], object] = _fuzz
