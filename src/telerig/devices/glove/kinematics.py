"""Parametric hand model: glove joint angles -> 21 MediaPipe-order keypoints -> ``HandPose``.

Hand frame ``"<hand>_glove"`` (metres): origin at the wrist (keypoint 0); with the hand flat, palm
down, fingers pointing forward, its axes coincide with the operator frame: x toward the fingers,
z out of the back of the hand (up), y = z x x (left). So the thumb lies at +y on a right hand and at
-y on a left hand; the model is defined for a right hand and mirrored (y -> -y) for a left one.

A glove measures the fingers relative to itself, not where the hand is in the room: the wrist pose
is the identity in ``"<hand>_glove"``, unless the glove reports wrist angles, in which case the
frame is the forearm's (the glove's wrist strap) and ``wrist_orientation`` is the wrist rotation,
R = Ry(flex) Rz(+-deviation). Placing the hand in the operator frame is the job of a tracker pose
fused later (e.g. a VR controller or a mocap marker on the glove), which re-expresses the sample.

Each finger is a serial chain from its base (thumb CMC; MCP for the others): yaw about z by the
finger's rest splay plus its spread angle, roll about the chain's long axis (thumb only, so it
flexes across the palm), then three flexions about the chain's y axis (flex > 0 toward the palm).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

from telerig.devices.glove.protocol import GloveFrame, decode_frame
from telerig.errors import ConfigError
from telerig.ir.types import HAND_KEYPOINTS, FloatArray, Handedness, HandPose, Stamp

__all__ = ["DEFAULT_BASES_MM", "DEFAULT_LENGTHS_MM", "FUZZ_TARGET", "HandModel", "glove_hand_pose"]

#: Chain bases of a right adult hand [mm] in the hand frame: thumb CMC, index..little MCP. Shape (5, 3).
DEFAULT_BASES_MM: tuple[tuple[float, float, float], ...] = (
    (28.0, 20.0, -12.0),
    (92.0, 24.0, 0.0),
    (94.0, 3.0, 0.0),
    (88.0, -16.0, -2.0),
    (80.0, -34.0, -5.0),
)
#: Segment lengths of an adult hand [mm]: thumb metacarpal, proximal, distal; fingers proximal,
#: middle, distal phalanx. Rows thumb..little. Shape (5, 3).
DEFAULT_LENGTHS_MM: tuple[tuple[float, float, float], ...] = (
    (46.0, 32.0, 27.0),
    (42.0, 25.0, 20.0),
    (46.0, 28.0, 21.0),
    (43.0, 27.0, 21.0),
    (34.0, 20.0, 19.0),
)
#: Rest splay of each chain about z [rad] (toward the thumb > 0), thumb..little. Shape (5,).
DEFAULT_YAW_RAD: tuple[float, ...] = (0.75, 0.08, 0.0, -0.08, -0.18)
#: Roll of the thumb chain about its long axis [rad], so thumb flexion curls across the palm.
DEFAULT_THUMB_ROLL_RAD = -0.9


def _table(value: Sequence[Sequence[float]], name: str, lo: float, hi: float) -> FloatArray:
    arr = np.array(value, dtype=np.float64)
    if arr.shape != (5, 3) or not np.all(np.isfinite(arr)):
        raise ConfigError(f"{name} must be 5 rows (thumb..little) of 3 finite numbers [mm], got {value!r}")
    if not np.all((arr >= lo) & (arr <= hi)):
        raise ConfigError(f"{name} values must be within [{lo}, {hi}] mm, got {value!r}")
    return arr


class HandModel:
    """Segment geometry of a hand; :meth:`keypoints` is the forward kinematics.

    Args:
        lengths_mm: Segment lengths [mm], rows thumb..little, see :data:`DEFAULT_LENGTHS_MM`.
            Shape (5, 3).
        bases_mm: Chain bases [mm] of a right hand in the hand frame, see :data:`DEFAULT_BASES_MM`.
            Shape (5, 3).
        scale: Uniform scale applied to all lengths and bases (e.g. 0.9 for a small hand), in
            [0.5, 1.5].
    """

    def __init__(
        self,
        lengths_mm: Sequence[Sequence[float]] = DEFAULT_LENGTHS_MM,
        bases_mm: Sequence[Sequence[float]] = DEFAULT_BASES_MM,
        *,
        scale: float = 1.0,
    ) -> None:
        if not (math.isfinite(scale) and 0.5 <= scale <= 1.5):
            raise ConfigError(f"hand scale must be in [0.5, 1.5], got {scale}")
        lengths = _table(lengths_mm, "segment lengths", 5.0, 120.0)
        bases = _table(bases_mm, "chain bases", -150.0, 150.0)
        self.scale = float(scale)
        self.lengths_m: FloatArray = lengths * (scale * 1e-3)
        self.bases_m: FloatArray = bases * (scale * 1e-3)
        self._bases: list[list[float]] = self.bases_m.tolist()
        self._lengths: list[list[float]] = self.lengths_m.tolist()
        roll = (DEFAULT_THUMB_ROLL_RAD, 0.0, 0.0, 0.0, 0.0)
        self._sr = [math.sin(r) for r in roll]
        self._cr = [math.cos(r) for r in roll]
        for arr in (self.lengths_m, self.bases_m):
            arr.flags.writeable = False

    @classmethod
    def default(cls) -> HandModel:
        """The adult default model (shared instance; it is immutable)."""
        return _DEFAULT

    @property
    def palm_length_m(self) -> float:
        """Wrist to middle-finger MCP distance [m]."""
        return float(np.linalg.norm(self.bases_m[2]))

    def keypoints(
        self,
        finger_angles: FloatArray,
        handedness: Handedness = "right",
        wrist_angles: FloatArray | None = None,
    ) -> FloatArray:
        """21 MediaPipe-order keypoints [m] in the ``"<hand>_glove"`` frame. Shape (21, 3).

        Args:
            finger_angles: Joint angles [rad], rows thumb..little, columns spread, flex1..3.
                Shape (5, 4).
            handedness: Mirrors the model for a left hand.
            wrist_angles: Optional wrist (flex, deviation) [rad]; rotates the hand about the
                wrist. Shape (2,).
        """
        # Pure-Python chain arithmetic: ~2x faster than NumPy on arrays this small.
        mirror = -1.0 if handedness == "left" else 1.0
        points: list[tuple[float, float, float]] = [(0.0, 0.0, 0.0)]
        cos, sin = math.cos, math.sin
        for (spread, f1, f2, f3), (bx, by, bz), lengths, yaw0, sr, cr in zip(
            finger_angles.tolist(),
            self._bases,
            self._lengths,
            DEFAULT_YAW_RAD,
            self._sr,
            self._cr,
            strict=True,
        ):
            yaw = yaw0 + spread
            cy, sy = cos(yaw), sin(yaw)
            points.append((bx, mirror * by, bz))
            x = z = c = 0.0
            for length, flex in zip(lengths, (f1, f2, f3), strict=True):
                c += flex
                x += length * cos(c)
                z -= length * sin(c)
                y = -sr * z
                points.append((cy * x - sy * y + bx, mirror * (sy * x + cy * y + by), cr * z + bz))
        kp = np.array(points)
        if wrist_angles is not None:
            kp = kp @ _wrist_matrix(wrist_angles, handedness).T
        return kp


def _wrist_matrix(wrist: FloatArray, handedness: Handedness) -> FloatArray:
    flex = float(wrist[0])
    dev = float(wrist[1]) if handedness == "right" else -float(wrist[1])
    cf, sf, cd, sd = math.cos(flex), math.sin(flex), math.cos(dev), math.sin(dev)
    ry = np.array([[cf, 0.0, sf], [0.0, 1.0, 0.0], [-sf, 0.0, cf]])
    rz = np.array([[cd, -sd, 0.0], [sd, cd, 0.0], [0.0, 0.0, 1.0]])
    out: FloatArray = ry @ rz
    return out


def _wrist_quaternion(wrist: FloatArray | None, handedness: Handedness) -> FloatArray:
    """(w, x, y, z) of Ry(flex) Rz(+-deviation); identity without wrist angles."""
    if wrist is None:
        return _IDENTITY
    flex = float(wrist[0])
    dev = float(wrist[1]) if handedness == "right" else -float(wrist[1])
    cf, sf = math.cos(flex / 2.0), math.sin(flex / 2.0)
    cd, sd = math.cos(dev / 2.0), math.sin(dev / 2.0)
    # q_y(flex) * q_z(dev)
    return np.array([cf * cd, sf * sd, sf * cd, cf * sd])


_IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])
_IDENTITY.flags.writeable = False
_ORIGIN = np.zeros(3)
_ORIGIN.flags.writeable = False
_TIP_ROWS = np.array([4, 8, 12, 16, 20])
_DEFAULT = HandModel()


def glove_hand_pose(
    frame: GloveFrame,
    model: HandModel,
    stamp: Stamp,
    *,
    use_measured_tips: bool = True,
    frame_id: str | None = None,
) -> HandPose:
    """Normalize one glove frame into a :class:`HandPose` in the ``"<hand>_glove"`` frame.

    Keypoints [m] come from the hand model's forward kinematics; when the frame carries fingertip
    positions and ``use_measured_tips`` is set, the five tip keypoints are the measured ones (the
    vendor SDK's tips are calibrated to the operator's hand, the model's are not). Keypoint
    confidence is 1 for the wrist (the frame's origin) and the finger's confidence for its four
    points; ``stamp`` is used as is (its confidence should be the mean finger confidence).

    Args:
        frame: A decoded glove frame.
        model: Hand geometry.
        stamp: Stamp of the sample.
        use_measured_tips: Prefer the bridge's fingertip positions when present.
        frame_id: Override of the frame name (default ``"<hand>_glove"``).
    """
    hand = frame.handedness
    kp = model.keypoints(frame.finger_angles, hand, frame.wrist_angles)
    tips = frame.fingertips_mm
    if use_measured_tips and tips is not None:
        measured = tips * 1e-3
        if frame.wrist_angles is not None:
            measured = measured @ _wrist_matrix(frame.wrist_angles, hand).T
        kp[_TIP_ROWS] = measured
    conf = np.empty(HAND_KEYPOINTS)
    conf[0] = 1.0
    conf[1:] = np.repeat(frame.confidence, 4)
    return HandPose(
        stamp=stamp,
        handedness=hand,
        wrist_position=_ORIGIN,
        wrist_orientation=_wrist_quaternion(frame.wrist_angles, hand),
        keypoints=kp,
        keypoint_confidence=conf,
        frame_id=frame_id or f"{hand}_glove",
    )


def _fuzz(data: bytes) -> object:
    return glove_hand_pose(decode_frame(data), HandModel.default(), Stamp("fuzz", 0, 0, 0))


#: The glove's untrusted-bytes path: one wire frame -> HandPose (default hand model); raises only
#: WireError. It lives here, not in ``protocol`` like the other families' targets, because the
#: frame is decoded there and turned into keypoints here (protocol must not import kinematics back).
FUZZ_TARGET: Callable[[bytes], object] = _fuzz
