"""Temporal action segmenters: the plug-in interface and the two offline defaults.

A segmenter turns one video (and, for a telerig episode, the robot streams recorded with it) into
labelled spans on the video's timeline. Two ship with telerig and need no model weights:

* :class:`RobotStreamsSegmenter` (``robot_streams``) reads what the robot did: gripper close/open
  events (``gripper_state``, else the commands sent), end-effector speed through the robot model's
  forward kinematics (joint speed for robots without an arm model) and its pauses, and changes of
  the measured wrench (contact). It labels ``reach``, ``grasp``, ``transport``, ``place``,
  ``release``, ``retreat``, ``move`` and ``idle``.
* :class:`MotionEnergySegmenter` (``motion_energy``) reads only pixels: the frame difference of the
  kept video, downscaled (within the hands' boxes when the filter recorded them). Active spans become
  ``manipulation`` segments.

Learned temporal action detectors (OpenTAD-class) plug in through :data:`telerig.registry.SEGMENTERS`:
a package registers a pydantic config class (``type: Literal["<name>"]``) under the entry point group
``telerig.segmenters`` whose ``build()`` returns a :class:`Segmenter`; the rig file names it in
``process.segment.video`` or ``process.segment.robot``.
"""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, Protocol, runtime_checkable

import numpy as np
import numpy.typing as npt
from pydantic import BaseModel, ConfigDict, Field, model_validator

from telerig.bus.catalogue import GRIPPER_SENT, GRIPPER_STATE, JOINT_STATE, WRENCH
from telerig.errors import ProcessError
from telerig.ir.types import FloatArray
from telerig.registry import SEGMENTERS

if TYPE_CHECKING:  # the rig loader imports this module for its configs: keep that light
    from telerig.qa.episode import EpisodeData, RobotData
    from telerig.record.align import StreamData

__all__ = [
    "HandTrack",
    "MotionEnergyConfig",
    "MotionEnergySegmenter",
    "Proposal",
    "RobotStreamsConfig",
    "RobotStreamsSegmenter",
    "SegmentInput",
    "Segmenter",
    "VideoInfo",
    "build_segmenter",
    "probe_video",
]

_log = logging.getLogger("telerig.process.segment")

BoolArray = npt.NDArray[np.bool_]
#: The robot-stream segmenter works on a grid at this rate [Hz]: the file's 0.01 s resolution.
_GRID_HZ = 100.0
#: Larger recorded values are a faulty driver's, and the sample is left out: joint position [rad]
#: or [m], gripper opening (normalized 0..1; values a little outside are clipped), force [N].
_MAX_JOINT = 1e3
_MAX_OPENING = 10.0
_MAX_FORCE = 1e5


# --- configs (the rig file's process.segment.robot / .video) -------------------------------------


@SEGMENTERS.register
class RobotStreamsConfig(BaseModel):
    """Settings of :class:`RobotStreamsSegmenter` (``type: robot_streams``).

    Attributes:
        speed_on_m_s: End-effector speed above which the arm moves [m/s].
        speed_off_m_s: ... and below which it has stopped again (hysteresis) [m/s].
        joint_speed_on_rad_s: The same for a robot without an arm model, joint speed norm [rad/s].
        joint_speed_off_rad_s: Its stop threshold [rad/s].
        smooth_s: Speeds are averaged over this window first [s].
        min_pause_s: A stop shorter than this is part of the motion around it [s].
        min_motion_s: A motion shorter than this is jitter, not an action [s].
        min_idle_s: A stop at least this long is labelled ``idle`` [s].
        min_place_s: The final descent before a release must last this long to be a ``place`` [s].
        place_drop_m: ... and bring the end effector down at least this far [m].
        gripper_rate_per_s: Opening change rate that counts as the gripper moving [1/s].
        gripper_step: Smallest opening change of a grasp or release [1] (0 closed, 1 open).
        closed_opening: A grasp whose measured opening stays above this closed on an object [1].
        force_step_n: Force magnitude change within 0.1 s that counts as contact made or lost [N].
        contact_window_s: A contact change this close to a gripper event confirms it [s].
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    type: Literal["robot_streams"] = "robot_streams"
    speed_on_m_s: float = Field(default=0.02, gt=0, le=10)
    speed_off_m_s: float = Field(default=0.01, gt=0, le=10)
    joint_speed_on_rad_s: float = Field(default=0.05, gt=0, le=100)
    joint_speed_off_rad_s: float = Field(default=0.025, gt=0, le=100)
    smooth_s: float = Field(default=0.1, ge=0, le=10)
    min_pause_s: float = Field(default=0.3, ge=0, le=60)
    min_motion_s: float = Field(default=0.2, ge=0, le=60)
    min_idle_s: float = Field(default=0.5, ge=0, le=600)
    min_place_s: float = Field(default=0.3, ge=0, le=60)
    place_drop_m: float = Field(default=0.03, gt=0, le=10)
    gripper_rate_per_s: float = Field(default=0.3, gt=0, le=100)
    gripper_step: float = Field(default=0.15, gt=0, le=1)
    closed_opening: float = Field(default=0.05, ge=0, le=1)
    force_step_n: float = Field(default=1.5, gt=0, le=10_000)
    contact_window_s: float = Field(default=0.3, ge=0, le=10)

    @model_validator(mode="after")
    def _hysteresis_order(self) -> RobotStreamsConfig:
        if self.speed_off_m_s > self.speed_on_m_s:
            raise ValueError(f"speed_off_m_s {self.speed_off_m_s} is above speed_on_m_s {self.speed_on_m_s}")
        if self.joint_speed_off_rad_s > self.joint_speed_on_rad_s:
            raise ValueError("joint_speed_off_rad_s is above joint_speed_on_rad_s")
        return self

    def build(self) -> RobotStreamsSegmenter:
        """The segmenter."""
        return RobotStreamsSegmenter(self)


@SEGMENTERS.register
class MotionEnergyConfig(BaseModel):
    """Settings of :class:`MotionEnergySegmenter` (``type: motion_energy``).

    Attributes:
        width_px: Frames are downscaled to this width (grey, aspect kept) before differencing [px].
        threshold: Frame-difference energy above the video's floor that counts as activity
            [fraction of full scale per second].
        hand_grow: With the filter's hand boxes, only pixels inside a box grown by this fraction of
            its size on each side count (the hand's motion, not the room's) [1].
        off_fraction: Activity ends when energy falls below this fraction of the on level [1].
        smooth_s: Energy is averaged over this window first [s].
        min_gap_s: Still gaps shorter than this inside an activity are part of it [s].
        min_segment_s: Shorter active spans are dropped [s].
        pad_s: Each span grows by this on both sides (motion starts before it shows) [s].
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    type: Literal["motion_energy"] = "motion_energy"
    width_px: int = Field(default=64, ge=16, le=640)
    threshold: float = Field(default=0.06, gt=0, le=100)
    hand_grow: float = Field(default=0.5, ge=0, le=5)
    off_fraction: float = Field(default=0.6, gt=0, le=1)
    smooth_s: float = Field(default=0.2, ge=0, le=10)
    min_gap_s: float = Field(default=0.5, ge=0, le=600)
    min_segment_s: float = Field(default=0.5, ge=0, le=3600)
    pad_s: float = Field(default=0.1, ge=0, le=10)

    def build(self) -> MotionEnergySegmenter:
        """The segmenter."""
        return MotionEnergySegmenter(self)


# --- the interface -------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class VideoInfo:
    """What demuxing a video tells without decoding it.

    Attributes:
        path: The file.
        duration_s: First frame to the end of the last one [s].
        frame_times: Presentation times of every frame from the first [s], sorted. Shape (F,).
        keyframes: Presentation times of the keyframes [s], sorted. Shape (K,).
        fps: Median frame rate [Hz] (variable-rate recordings have one too).
        b_frames: Some frame is decoded after a later-shown one (its end cannot be cut by copy alone).
        width: Frame width [px].
        height: Frame height [px].
        start_pts: Presentation timestamp of the first frame, in ``time_base`` units (t = 0).
        time_base: Seconds per timestamp unit of the video stream.
    """

    path: Path
    duration_s: float
    frame_times: FloatArray
    keyframes: FloatArray
    fps: float
    b_frames: bool
    width: int
    height: int
    start_pts: int = 0
    time_base: float = 1e-6

    def pts(self, t: float) -> int:
        """The stream timestamp of time ``t`` [s] on the video's timeline."""
        return self.start_pts + round(t / self.time_base)


def probe_video(path: Path) -> VideoInfo:
    """Demux ``path`` (packets only, no decoding): frame and keyframe times, duration, rate.

    Raises:
        ProcessError: not a readable video, or it has no video frames (one line naming the file).
    """
    import av

    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                raise ProcessError(f"{path} has no video stream")
            stream = container.streams.video[0]
            tb = float(stream.time_base) if stream.time_base else 1e-6
            pts: list[int] = []
            keys: list[int] = []
            b_frames = False
            top = -(1 << 62)
            for packet in container.demux(stream):
                if packet.pts is None or packet.size == 0:
                    continue
                if packet.pts < top:
                    b_frames = True
                top = max(top, packet.pts)
                pts.append(packet.pts)
                if packet.is_keyframe:
                    keys.append(packet.pts)
            width, height = stream.codec_context.width, stream.codec_context.height
    except av.FFmpegError as exc:
        raise ProcessError(f"{path} is not a readable video: {exc}") from None
    except OSError as exc:
        raise ProcessError(f"cannot read {path}: {exc.strerror or exc}") from None
    if not pts:
        raise ProcessError(f"{path} has no video frames")
    first = min(pts)
    times = (np.sort(np.asarray(pts, dtype=np.float64)) - first) * tb
    step = float(np.median(np.diff(times))) if times.size > 1 else 1 / 30
    step = step if step > 0 else 1 / 30
    keyframes = (np.sort(np.asarray(keys, dtype=np.float64)) - first) * tb
    return VideoInfo(
        Path(path), float(times[-1] + step), times, keyframes, 1.0 / step, b_frames, width, height, first, tb
    )


@dataclass(frozen=True, slots=True)
class HandTrack:
    """Hand boxes per sampled frame, as the filter stage recorded them (``samples.json``).

    Attributes:
        times_s: Sample times on the video's timeline [s], sorted. Shape (S,).
        boxes: Up to H hand boxes per sample, ``(x0, y0, x1, y1)`` as fractions of the frame's width
            and height; NaN rows where fewer hands were seen. Shape (S, H, 4).
        period_s: Time one sample stands for (the filter's ``1 / sample_hz``) [s].
    """

    times_s: FloatArray
    boxes: FloatArray
    period_s: float

    def mask(self, t: float, width: int, height: int, grow: float) -> npt.NDArray[np.bool_] | None:
        """Pixels of a ``width`` x ``height`` frame at time ``t`` inside a hand box of the nearest
        sample (each box grown by ``grow`` of its size on every side); ``None`` when no hand was
        seen within one sample period."""
        if self.times_s.size == 0:
            return None
        i = int(np.clip(np.searchsorted(self.times_s, t), 0, self.times_s.size - 1))
        if i > 0 and abs(self.times_s[i - 1] - t) < abs(self.times_s[i] - t):
            i -= 1
        if abs(self.times_s[i] - t) > self.period_s:
            return None
        out = np.zeros((height, width), dtype=bool)
        for x0, y0, x1, y1 in self.boxes[i]:
            if not np.all(np.isfinite((x0, y0, x1, y1))):
                continue
            gx, gy = (x1 - x0) * grow, (y1 - y0) * grow
            c0, c1 = int(max(0.0, x0 - gx) * width), math.ceil(min(1.0, x1 + gx) * width)
            r0, r1 = int(max(0.0, y0 - gy) * height), math.ceil(min(1.0, y1 + gy) * height)
            out[r0:r1, c0:c1] = True
        return out if out.any() else None


@dataclass(frozen=True, slots=True)
class SegmentInput:
    """What a segmenter reads for one video.

    Attributes:
        video: The video the proposals' times refer to (its first frame is t = 0).
        info: Its demuxed facts.
        kept: Spans of that video the filter kept (``[start_s, end_s]``), ``None`` if it did not run;
            activity outside them is not proposed.
        episode: The episode's recorded robot streams, for an episode item.
        video_offset_s: Episode time (from the manifest's start) of the video's first frame [s].
        hands: Hand boxes the filter recorded, when it did.
    """

    video: Path
    info: VideoInfo
    kept: tuple[tuple[float, float], ...] | None = None
    episode: EpisodeData | None = None
    video_offset_s: float = 0.0
    hands: HandTrack | None = None


@dataclass(frozen=True, slots=True)
class Proposal:
    """One proposed action on the video's timeline.

    Attributes:
        label: What happens.
        start_s: Start [s].
        end_s: End [s].
        confidence: 0..1.
        actor: Robot id (or hand) that did it, where known.
    """

    label: str
    start_s: float
    end_s: float
    confidence: float
    actor: str | None = None


@runtime_checkable
class Segmenter(Protocol):
    """A temporal action segmenter (see the module docstring for how to add one)."""

    name: str
    """Registered type name; proposals carry ``source: machine:<name>@<version>``."""
    version: str
    """Bump when proposals would change (re-runs redo segmentation then)."""

    def segment(self, inp: SegmentInput, progress: Callable[[float], None]) -> list[Proposal]:
        """Proposals for ``inp.video``, sorted by start; ``[]`` when nothing happens in it.

        Raises:
            ProcessError: the input cannot be segmented (one line saying why).
        """
        ...


def build_segmenter(config: Any) -> Segmenter:
    """The segmenter a validated config (from :data:`telerig.registry.SEGMENTERS`) describes: its
    ``build()``.

    Raises:
        ProcessError: the config names no segmenter telerig can build, or what it built is not one.
    """
    build = getattr(config, "build", None)
    if not callable(build):
        raise ProcessError(
            f"segmenter config {type(config).__name__} has no build(); it cannot make a segmenter"
        )
    built = build()
    if not isinstance(built, Segmenter):
        raise ProcessError(
            f"{type(config).__name__}.build() returned {type(built).__name__}, not a Segmenter"
        )
    return built


# --- shared span helpers -------------------------------------------------------------------------


def _runs(mask: BoolArray) -> list[tuple[int, int]]:
    """``[start, end)`` index ranges where ``mask`` is True."""
    if mask.size == 0:
        return []
    padded = np.concatenate(([False], mask, [False]))
    edges = np.flatnonzero(padded[1:] != padded[:-1])
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2], strict=True)]


def _hysteresis(value: FloatArray, on: float, off: float) -> BoolArray:
    """True from where ``value`` rises above ``on`` until it falls below ``off`` (``off <= on``)."""
    out = np.zeros(value.shape, dtype=bool)
    state = False
    for i, v in enumerate(value):
        state = v > on if not state else v >= off
        out[i] = state
    return out


def _close_gaps(mask: BoolArray, max_gap: int) -> BoolArray:
    """``mask`` with False runs of at most ``max_gap`` samples between True runs set True."""
    out = mask.copy()
    for a, b in _runs(~mask):
        if a > 0 and b < mask.size and b - a <= max_gap:
            out[a:b] = True
    return out


def _drop_short(mask: BoolArray, min_len: int) -> BoolArray:
    """``mask`` with True runs shorter than ``min_len`` samples set False."""
    out = mask.copy()
    for a, b in _runs(mask):
        if b - a < min_len:
            out[a:b] = False
    return out


def _smooth(value: FloatArray, n: int) -> FloatArray:
    """Centred moving average over ``n`` samples (edges averaged over what exists)."""
    if n <= 1 or value.size == 0:
        return value
    kernel = np.ones(n)
    num = np.convolve(value, kernel, mode="same")
    den = np.convolve(np.ones_like(value), kernel, mode="same")
    out: FloatArray = num / den
    return out


def _in_spans(times: FloatArray, spans: Sequence[tuple[float, float]] | None) -> BoolArray:
    if spans is None:
        return np.ones(times.shape, dtype=bool)
    inside = np.zeros(times.shape, dtype=bool)
    for a, b in spans:
        inside |= (times >= a) & (times < b)
    return inside


# --- robot streams -------------------------------------------------------------------------------


@dataclass(slots=True)
class _Event:
    """A gripper event on the grid: ``kind`` grasp or release over samples ``[a, b)``."""

    kind: str
    a: int
    b: int
    confidence: float


@dataclass(slots=True)
class _RobotTrack:
    """One robot's signals on the grid."""

    speed: FloatArray
    """End-effector speed [m/s] (or joint speed norm [rad/s] without a kinematic model)."""
    height: FloatArray | None
    """End-effector height [m] (NaN before the first sample); ``None`` without FK."""
    on: float
    off: float
    events: list[_Event] = field(default_factory=list)


class RobotStreamsSegmenter:
    """Actions of a teleoperated robot from its recorded streams (see the module docstring).

    How: every stream is held onto a 100 Hz grid over the episode. The gripper's opening (measured,
    else commanded) falling by at least ``gripper_step`` at more than ``gripper_rate_per_s`` is a
    grasp, rising a release. Between those, end-effector speed (forward kinematics of the robot
    model, ``speed_on_m_s``/``speed_off_m_s`` hysteresis; pauses shorter than ``min_pause_s`` are
    part of the motion) splits motion from idle, and the gripper state names the motion: holding
    -> ``transport`` (its last descent before a release -> ``place``), after a release ->
    ``retreat``, before a grasp -> ``reach``, otherwise ``move``. A wrench change of more than
    ``force_step_n`` within ``contact_window_s`` of a gripper event (contact made or lost) raises
    its confidence; a grasp whose measured opening stopped short of closed (an object between the
    fingers) does too. An opening before the episode's first grasp is the gripper leaving its
    initial state, not a release, unless a contact change confirms it let go of something.
    """

    name = "robot_streams"
    version = "1"

    def __init__(self, config: RobotStreamsConfig | None = None) -> None:
        self.config = config or RobotStreamsConfig()

    def segment(self, inp: SegmentInput, progress: Callable[[float], None]) -> list[Proposal]:
        """Proposals per robot of ``inp.episode`` (``actor`` = robot id), on the video's timeline.

        Raises:
            ProcessError: the input has no episode, or no robot recorded a joint state or gripper.
        """
        episode = inp.episode
        if episode is None:
            raise ProcessError(
                f"{inp.video}: the robot_streams segmenter needs an episode's recorded streams"
            )
        robots = [r for r in episode.robots.values() if _usable(r)]
        if not robots:
            raise ProcessError(
                f"{episode.path}: no robot recorded a joint state or gripper; segment its video instead "
                "(process.segment.video)"
            )
        n = max(2, math.ceil(episode.duration_s * _GRID_HZ) + 1)
        grid = np.arange(n) / _GRID_HZ  # episode time [s]
        out: list[Proposal] = []
        for k, robot in enumerate(robots):
            track = self._track(episode, robot, grid)
            for p in self._label(track, grid, robot.robot):
                start = p.start_s - inp.video_offset_s
                end = min(p.end_s - inp.video_offset_s, inp.info.duration_s)
                start = max(start, 0.0)
                if end - start >= 0.05:
                    out.append(Proposal(p.label, start, end, p.confidence, p.actor))
            progress((k + 1) / len(robots))
        out.sort(key=lambda p: (p.start_s, p.actor or ""))
        return out

    # -- signals

    def _track(self, episode: EpisodeData, robot: RobotData, grid: FloatArray) -> _RobotTrack:
        cfg = self.config
        state = robot.streams.get(JOINT_STATE)
        speed = np.zeros(grid.shape)
        height: FloatArray | None = None
        on, off = cfg.speed_on_m_s, cfg.speed_off_m_s
        ok = _rows_ok(state.fields.get("positions"), _MAX_JOINT) if state is not None else None
        if state is not None and ok is not None and ok.sum() >= 2:
            t = episode.seconds(state.time_ns[ok])
            q = state.fields["positions"][ok]
            positions = _ee_positions(robot, q)
            if positions is not None:
                values = np.linalg.norm(_derivative(positions, t), axis=1)
                height = np.interp(grid, t, positions[:, 2], left=np.nan, right=np.nan)
            else:  # no kinematic model: joint-space speed, in rad/s
                values = np.linalg.norm(_derivative(q, t), axis=1)
                on, off = cfg.joint_speed_on_rad_s, cfg.joint_speed_off_rad_s
            values = _smooth(np.nan_to_num(values), max(1, round(cfg.smooth_s * _GRID_HZ)))
            speed = np.interp(grid, t, values, left=0.0, right=0.0)
        track = _RobotTrack(speed, height, on, off)
        track.events = self._gripper_events(episode, robot, grid)
        return track

    def _gripper_events(self, episode: EpisodeData, robot: RobotData, grid: FloatArray) -> list[_Event]:
        cfg = self.config
        measured = robot.streams.get(GRIPPER_STATE)
        stream = (
            measured
            if measured is not None and measured.time_ns.size >= 2
            else robot.streams.get(GRIPPER_SENT)
        )
        if stream is None or stream.time_ns.size < 2 or "opening" not in stream.fields:
            return []
        ok = _rows_ok(stream.fields["opening"], _MAX_OPENING)
        if ok is None or ok.sum() < 2:
            return []
        t = episode.seconds(stream.time_ns[ok])
        opening = np.clip(stream.fields["opening"][ok], 0.0, 1.0)
        # Linear between samples: a gripper moves continuously, and a gap in the stream (a loaded
        # host) then spreads the change over the gap instead of stepping at its end.
        held = np.interp(grid, t, opening)
        rate = _smooth(np.gradient(held, 1 / _GRID_HZ), max(1, round(0.05 * _GRID_HZ)))
        closing = _close_gaps(rate < -cfg.gripper_rate_per_s, round(0.1 * _GRID_HZ))
        opening_ = _close_gaps(rate > cfg.gripper_rate_per_s, round(0.1 * _GRID_HZ))
        contact = _contact_changes(episode, robot, grid, cfg.force_step_n)
        window = round(cfg.contact_window_s * _GRID_HZ)
        events: list[_Event] = []
        for kind, mask in (("grasp", closing), ("release", opening_)):
            for a, b in _runs(mask):
                step = held[max(a - 1, 0)] - held[min(b, held.size - 1)]
                if abs(step) < cfg.gripper_step:
                    continue
                conf = 0.6
                if contact is not None and np.any(contact[max(a - window, 0) : b + window]):
                    conf += 0.2
                if (
                    kind == "grasp"
                    and measured is stream
                    and held[min(b, held.size - 1)] > cfg.closed_opening
                ):
                    conf += 0.2  # stopped short of closed: something is between the fingers
                if kind == "release":
                    conf += 0.1
                events.append(_Event(kind, a, b, min(conf, 1.0)))
        events = _merge_events(events, round(cfg.min_pause_s * _GRID_HZ))
        commanded = robot.streams.get(GRIPPER_SENT) if measured is stream else None
        first = _first_grasp(events)
        kept: list[_Event] = []
        for e in events:
            asked = _commanded(episode, commanded, grid, e, cfg.gripper_step)
            if asked is False:
                continue  # the gripper moved without being told to: pushed, or catching up on a reset
            if e.kind == "release" and (first is None or e.a < first) and asked is None:
                continue  # before any grasp and no command says so: the gripper leaving its initial state
            kept.append(e)
        return kept

    # -- labels

    def _label(self, track: _RobotTrack, grid: FloatArray, actor: str) -> list[Proposal]:
        cfg = self.config
        moving = _hysteresis(track.speed, track.on, track.off)
        moving = _close_gaps(moving, round(cfg.min_pause_s * _GRID_HZ))
        moving = _drop_short(moving, max(1, round(cfg.min_motion_s * _GRID_HZ)))
        busy = np.zeros(grid.shape, dtype=bool)
        for e in track.events:
            busy[e.a : e.b] = True
        # What the gripper holds at each sample: closed after a grasp until the next release.
        holding = np.zeros(grid.shape, dtype=bool)
        last_release = np.full(grid.shape, -1, dtype=np.int64)
        state, released_at = False, -1
        events = iter(track.events)
        nxt = next(events, None)
        for i in range(grid.size):
            while nxt is not None and i >= nxt.b:
                state = nxt.kind == "grasp"
                released_at = nxt.b if nxt.kind == "release" else -1
                nxt = next(events, None)
            holding[i] = state
            last_release[i] = released_at
        out: list[Proposal] = [
            Proposal(e.kind, float(grid[e.a]), float(grid[min(e.b, grid.size - 1)]), e.confidence, actor)
            for e in track.events
        ]
        for a, b in _runs(~busy):
            for c, d in _runs(moving[a:b]):
                out.extend(self._motion(track, grid, a + c, a + d, holding, last_release, actor))
            for c, d in _runs(~moving[a:b]):
                if (d - c) / _GRID_HZ >= cfg.min_idle_s:
                    still = track.speed[a + c : a + d] < track.off
                    conf = 0.5 + 0.45 * float(np.mean(still))
                    out.append(
                        Proposal(
                            "idle", float(grid[a + c]), float(grid[min(a + d, grid.size - 1)]), conf, actor
                        )
                    )
        out.sort(key=lambda p: p.start_s)
        return out

    def _motion(
        self,
        track: _RobotTrack,
        grid: FloatArray,
        a: int,
        b: int,
        holding: BoolArray,
        last_release: npt.NDArray[np.int64],
        actor: str,
    ) -> list[Proposal]:
        clear = track.speed[a:b] > track.on
        conf = 0.5 + 0.45 * float(np.mean(clear))
        end = min(b, grid.size - 1)
        if holding[a]:
            release_next = any(e.kind == "release" and e.a >= b - 1 for e in track.events)
            min_len = round(self.config.min_place_s * _GRID_HZ)
            split = _last_descent(track.height, a, b, min_len, self.config.place_drop_m)
            if release_next and split is not None and _next_event(track.events, b) == "release":
                return [
                    Proposal("transport", float(grid[a]), float(grid[split]), conf, actor),
                    Proposal("place", float(grid[split]), float(grid[end]), conf, actor),
                ]
            return [Proposal("transport", float(grid[a]), float(grid[end]), conf, actor)]
        if last_release[a] >= 0 and a - last_release[a] <= round(self.config.min_idle_s * _GRID_HZ):
            label = "retreat"
        elif _next_event(track.events, b) == "grasp":
            label = "reach"
        else:
            label = "move"
        return [Proposal(label, float(grid[a]), float(grid[end]), conf, actor)]


def _usable(robot: RobotData) -> bool:
    return any(
        s in robot.streams and robot.streams[s].time_ns.size >= 2
        for s in (JOINT_STATE, GRIPPER_STATE, GRIPPER_SENT)
    )


def _merge_events(events: list[_Event], max_gap: int) -> list[_Event]:
    """Events sorted by start, where one of the same kind follows another within ``max_gap``
    samples joined into one (a close interrupted by a stalled stream is one grasp)."""
    out: list[_Event] = []
    for e in sorted(events, key=lambda e: e.a):
        last = out[-1] if out else None
        if last is not None and last.kind == e.kind and e.a - last.b <= max_gap:
            last.b = max(last.b, e.b)
            last.confidence = max(last.confidence, e.confidence)
        else:
            out.append(e)
    return out


def _commanded(
    episode: EpisodeData, commanded: StreamData | None, grid: FloatArray, event: _Event, step: float
) -> bool | None:
    """Whether the commands sent moved the gripper the way ``event`` did, in the second before it
    or during it (held from each command: a command stands until the next); ``None`` when no
    command was recorded by then."""
    if commanded is None or commanded.time_ns.size == 0 or "opening" not in commanded.fields:
        return None
    ok = _rows_ok(commanded.fields["opening"], _MAX_OPENING)
    if ok is None or not ok.any():
        return None
    t = episode.seconds(commanded.time_ns[ok])
    before, after = grid[event.a] - 1.0, grid[min(event.b, grid.size - 1)]
    if t[0] > after:
        return None
    values = commanded.fields["opening"][ok]
    level = _hold(np.array([before, after]), t, values)
    change = float(level[1] - level[0])
    return change >= step if event.kind == "release" else -change >= step


def _first_grasp(events: Sequence[_Event]) -> int | None:
    return next((e.a for e in events if e.kind == "grasp"), None)


def _next_event(events: Sequence[_Event], after: int) -> str | None:
    """Kind of the first gripper event starting at or after sample ``after - 1``."""
    for e in events:
        if e.a >= after - 1:
            return e.kind
    return None


def _last_descent(height: FloatArray | None, a: int, b: int, min_len: int, drop_m: float) -> int | None:
    """Start of the motion's final descent in ``[a, b)``: from the last height peak before the arm
    comes down at least ``drop_m`` to where it ends (a net drop, so a jerky, stalling descent on a
    loaded host still counts). ``None`` when it is shorter than ``min_len`` samples, leaves no
    ``min_len`` for a transport before it, or there is none."""
    if height is None or b - a < 2 * min_len:
        return None
    z = _smooth(height[a:b], max(1, round(0.1 * _GRID_HZ)))
    if not np.all(np.isfinite(z)):
        return None
    above = np.flatnonzero(z >= z[-1] + drop_m)
    if above.size == 0:
        return None
    c = int(above[-1])
    while c > 0 and z[c - 1] >= z[c]:  # back up the slope to where the descent began
        c -= 1
    if (b - a) - c < min_len or c < min_len:
        return None
    return a + c


def _derivative(values: FloatArray, t: FloatArray) -> FloatArray:
    """d values / dt along axis 0, zero where time does not increase."""
    if values.shape[0] < 2:
        return np.zeros_like(values)
    dt = np.diff(t)
    if np.all(dt > 0):
        out: FloatArray = np.gradient(values, t, axis=0)
        return out
    keep = np.concatenate(([True], dt > 0))
    grad = np.gradient(values[keep], t[keep], axis=0) if keep.sum() >= 2 else np.zeros_like(values[keep])
    index = np.cumsum(keep) - 1
    result: FloatArray = grad[index]
    return result


def _hold(grid: FloatArray, t: FloatArray, values: FloatArray) -> FloatArray:
    """Zero-order hold of samples ``(t, values)`` onto ``grid`` (the first value before the first sample)."""
    index = np.clip(np.searchsorted(t, grid, side="right") - 1, 0, t.size - 1)
    out: FloatArray = values[index]
    return out


def _contact_changes(
    episode: EpisodeData, robot: RobotData, grid: FloatArray, step_n: float
) -> BoolArray | None:
    """Grid samples where the measured force magnitude changed by more than ``step_n`` within 0.1 s;
    ``None`` for a robot without a wrench stream."""
    wrench = robot.streams.get(WRENCH)
    if wrench is None or wrench.time_ns.size < 2 or "force" not in wrench.fields:
        return None
    ok = _rows_ok(wrench.fields["force"], _MAX_FORCE)
    if ok is None or ok.sum() < 2:
        return None
    t = episode.seconds(wrench.time_ns[ok])
    force = np.linalg.norm(wrench.fields["force"][ok], axis=1)
    on_grid = _hold(grid, t, _smooth(force, 3))
    lag = max(1, round(0.1 * _GRID_HZ))
    change = np.zeros(grid.shape, dtype=bool)
    change[lag:] = np.abs(on_grid[lag:] - on_grid[:-lag]) > step_n
    return change


def _rows_ok(values: FloatArray | None, limit: float) -> BoolArray | None:
    """Samples (rows) whose every value is finite and within +-``limit``: a faulty driver's NaN,
    infinities and absurd values are left out, not interpolated through or summed into energy.
    ``None`` when there is no such field."""
    if values is None or values.shape[0] == 0:
        return None
    flat = values.reshape(values.shape[0], -1)
    with np.errstate(invalid="ignore"):
        ok: BoolArray = np.all(np.isfinite(flat) & (np.abs(flat) <= limit), axis=1)
    return ok


def _ee_positions(robot: RobotData, q: FloatArray) -> FloatArray | None:
    """End-effector positions [m] in the robot base frame per ``joint_state`` sample (positions
    ``q``, shape (S, n)), by the arm model's forward kinematics; ``None`` for a robot without an arm
    model (or unmatched joints)."""
    from telerig.qa.robots import match_joints
    from telerig.robots.models import ARM_MODELS

    model = robot.info.model
    if model is None or model not in ARM_MODELS:
        return None
    kin = _arm_kinematics(model)
    if kin is None:
        return None
    import mujoco

    mj_model, qadr, site, joints = kin
    index = match_joints(robot.names.get(JOINT_STATE, ()), joints)
    columns = [(i, j) for i, j in enumerate(index) if j >= 0]
    if len(columns) < len(joints):
        return None
    data = mujoco.MjData(mj_model)
    out = np.empty((q.shape[0], 3))
    for k in range(q.shape[0]):
        for i, j in columns:
            data.qpos[qadr[j]] = q[k, i]
        mujoco.mj_kinematics(mj_model, data)
        out[k] = data.site_xpos[site]
    return out


@functools.lru_cache(maxsize=4)
def _arm_kinematics(model: str) -> tuple[Any, tuple[int, ...], int, tuple[str, ...]] | None:
    """(MjModel, qpos address per arm joint, ee site id, arm joints) of an arm model, cached."""
    from telerig.robots.models.arm import build_arm_kinematics

    try:
        arm = build_arm_kinematics(model)
    except Exception as exc:  # a missing model package: segment from joint speeds instead
        _log.warning("no kinematics for %s (%s); using joint speeds", model, exc)
        return None
    qadr = tuple(int(arm.model.joint(name).qposadr[0]) for name in arm.arm_joints)
    return arm.model, qadr, int(arm.model.site(arm.ee_site).id), arm.arm_joints


# --- motion energy -------------------------------------------------------------------------------


class MotionEnergySegmenter:
    """Active spans of a plain video from motion energy (see the module docstring).

    Energy is the mean absolute difference of consecutive frames downscaled to ``width_px`` grey, per
    second (fraction of full scale per second, so it does not depend on the frame rate); where the
    filter stage recorded hand boxes, only pixels in and around the hand seen nearest in time count
    (no hand: no energy), so a turning head or a passer-by is not an action.
    The threshold adapts to the video's own floor (sensor noise, compression flicker): ``threshold``
    plus twice its 5th percentile, the percentile capped at ``threshold`` so a video busy from start
    to end still has its activity found. Frames outside the filter's kept spans count as still.
    """

    name = "motion_energy"
    version = "1"

    def __init__(self, config: MotionEnergyConfig | None = None) -> None:
        self.config = config or MotionEnergyConfig()

    def segment(self, inp: SegmentInput, progress: Callable[[float], None]) -> list[Proposal]:
        """``manipulation`` proposals of ``inp.video``; ``[]`` when nothing moves.

        Raises:
            ProcessError: the video does not decode.
        """
        times, energy = self._frame_energy(inp, progress)
        threshold = self.config.threshold
        progress(1.0)
        if times.size < 2:
            return []
        energy = np.where(_in_spans(times, inp.kept), energy, 0.0)
        return self._spans(times, energy, threshold, inp.info.duration_s)

    def _frame_energy(
        self, inp: SegmentInput, progress: Callable[[float], None]
    ) -> tuple[FloatArray, FloatArray]:
        import av

        width = self.config.width_px
        info = inp.info
        height = max(2, round(width * info.height / max(info.width, 1)) // 2 * 2)
        times: list[float] = []
        energy: list[float] = []
        prev: FloatArray | None = None
        prev_t = 0.0
        first: float | None = None
        total = max(info.frame_times.size, 1)
        kept = inp.kept
        try:
            with av.open(str(inp.video)) as container:
                stream = container.streams.video[0]
                stream.thread_type = "AUTO"
                for n, frame in enumerate(container.decode(stream)):
                    if frame.pts is None:
                        continue
                    t_abs = float(frame.pts * stream.time_base)
                    first = t_abs if first is None else first
                    t = t_abs - first
                    if kept is not None and not any(a - 0.1 <= t < b + 0.1 for a, b in kept):
                        prev = None  # outside the kept spans: not decoded into pixels, a gap
                        continue
                    image = frame.reformat(width=width, height=height, format="gray", interpolation="AREA")
                    cur = image.to_ndarray().astype(np.float32)
                    if prev is not None and t > prev_t:
                        change = np.abs(cur - prev)
                        if inp.hands is not None:  # only where a hand is: not the room moving past
                            mask = inp.hands.mask(t, width, height, self.config.hand_grow)
                            change = change * mask if mask is not None else change * 0.0
                        diff = float(np.mean(change)) / 255.0
                        times.append(t)
                        energy.append(diff / (t - prev_t))
                    prev, prev_t = cur, t
                    if n % 30 == 0:
                        progress(min(0.99, n / total))
        except av.FFmpegError as exc:
            raise ProcessError(f"{inp.video} does not decode: {exc}") from None
        return np.asarray(times), np.asarray(energy)

    def _spans(
        self, times: FloatArray, energy: FloatArray, threshold: float, duration: float
    ) -> list[Proposal]:
        cfg = self.config
        step = float(np.median(np.diff(times))) if times.size > 1 else 1 / 30
        n_smooth = max(1, round(cfg.smooth_s / step))
        smooth = _smooth(energy, n_smooth)
        floor = min(float(np.percentile(smooth, 5)), threshold)
        on = threshold + 2.0 * floor
        active = _hysteresis(smooth, on, cfg.off_fraction * on)
        active = _close_gaps(active, round(cfg.min_gap_s / step))
        active = _drop_short(active, max(1, round(cfg.min_segment_s / step)))
        out: list[Proposal] = []
        for a, b in _runs(active):
            start = max(0.0, float(times[a]) - step - cfg.pad_s)
            end = min(duration, float(times[b - 1]) + cfg.pad_s)
            mean = float(np.mean(smooth[a:b]))
            conf = 0.5 + 0.5 * math.tanh(mean / on - 1.0)
            if end - start >= 0.05:
                out.append(Proposal("manipulation", start, end, conf))
        return out
