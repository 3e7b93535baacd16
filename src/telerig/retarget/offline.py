"""Offline humanoid retargeting of a whole recording: zero-phase low-pass on keypoints, IK per frame, flags.

The recording is a BVH file or an episode MCAP (a file, or an episode folder holding
``episode.mcap``) with one ``BodySkeleton`` stream. The keypoint trajectories (shoulders, elbows,
wrists, hips) are low-passed with a zero-phase Butterworth filter before IK, not the joint
trajectories after it: the IK then sees the smooth motion the robot should make, the residual
measures whether the robot can make it (rather than whether it can follow tracker jitter), and the
joints it returns stay consistent with the targets and inside the joint limits (a filter run
over joint angles can ring past a limit and breaks the hand-target correspondence).
"""

from __future__ import annotations

import importlib
import json
import logging
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy import signal  # type: ignore[import-untyped]  # no stubs installed

from telerig.errors import DependencyError, DeviceError, RecordingError
from telerig.ir.types import BodySkeleton, FloatArray
from telerig.retarget.humanoid import (
    KEYPOINTS,
    HumanoidIK,
    HumanoidTargets,
    KeypointMap,
    SkeletonProfile,
    humanoid_targets,
)

__all__ = [
    "DEFAULT_CUTOFF_HZ",
    "DEFAULT_ORDER",
    "ProgressCallback",
    "RecordingRetarget",
    "RetargetSummary",
    "load_skeletons",
    "lowpass",
    "retarget_recording",
]

_log = logging.getLogger(__name__)

#: Default low-pass cutoff [Hz]: human arm motion has little power above it, tracker jitter does.
DEFAULT_CUTOFF_HZ = 5.0
#: Default Butterworth order (the forward-backward pass doubles the attenuation slope).
DEFAULT_ORDER = 4
_SETTLE_ITERATIONS = 60  # QP sub-steps that bring home to the first frame
_SETTLE_DT = 2.0  # [s] of motion allowed for that

#: ``progress(done, total)``: frames retargeted so far and in all.
ProgressCallback = Callable[[int, int], None]


def lowpass(
    x: FloatArray, rate_hz: float, cutoff_hz: float = DEFAULT_CUTOFF_HZ, order: int = DEFAULT_ORDER
) -> FloatArray:
    """Zero-phase Butterworth low-pass of uniformly sampled signals along axis 0.

    ``scipy.signal.butter`` (second-order sections) run forward and backward with ``sosfiltfilt``:
    no phase shift, magnitude response squared (-6 dB at ``cutoff_hz``).

    Args:
        x: Samples, shape (F, ...), finite.
        rate_hz: Sample rate [Hz].
        cutoff_hz: Cutoff frequency [Hz], in (0, rate_hz / 2).
        order: Filter order, 1..10.

    Raises:
        ValueError: the cutoff is not below the Nyquist frequency, the order is out of range, or
            there are fewer than 2 samples.
    """
    x = np.asarray(x, dtype=np.float64)
    if not 1 <= order <= 10:
        raise ValueError(f"order must be in 1..10, got {order}")
    if not 0 < cutoff_hz < rate_hz / 2:
        raise ValueError(
            f"cutoff_hz must be in (0, {rate_hz / 2:.4g}) Hz, half the {rate_hz:.4g} Hz sample rate; "
            f"got {cutoff_hz:g}"
        )
    if x.shape[0] < 2:
        raise ValueError(f"need at least 2 samples to filter, got {x.shape[0]}")
    sos = signal.butter(order, cutoff_hz, btype="low", fs=rate_hz, output="sos")
    # Short recordings: pad with as much of the signal as there is (scipy's default needs more).
    padlen = min(3 * (2 * len(sos) + 1), x.shape[0] - 1)
    out: FloatArray = signal.sosfiltfilt(sos, x, axis=0, padlen=padlen)
    return out


def load_skeletons(path: Path | str, *, source_id: str | None = None) -> list[BodySkeleton]:
    """The ``BodySkeleton`` frames of a recording, in capture-time order.

    Args:
        path: A ``.bvh`` file (operator axes via the default mount, scale detected), an MCAP log,
            or an episode folder holding ``episode.mcap``.
        source_id: The skeleton stream's ``stamp.source_id`` when an MCAP holds several.

    Raises:
        RecordingError: the file is missing or unreadable, holds no skeleton, or several streams
            and no ``source_id`` (the message lists them).
    """
    path = Path(path)
    if path.is_dir():
        path = path / "episode.mcap"
    if not path.exists():
        raise RecordingError(f"recording not found: {path}")
    if path.suffix.lower() == ".bvh":
        from telerig.devices.mocap.device import BvhPlayer

        try:
            return BvhPlayer(path, id="offline").frames()
        except DeviceError as exc:
            raise RecordingError(str(exc)) from None
    from telerig.ir.mcap_log import read_log

    streams: dict[str, list[BodySkeleton]] = {}
    for entry in read_log(path):
        if isinstance(entry.sample, BodySkeleton):
            streams.setdefault(entry.sample.stamp.source_id, []).append(entry.sample)
    if not streams:
        raise RecordingError(f"{path} holds no BodySkeleton samples")
    if source_id is None:
        if len(streams) > 1:
            raise RecordingError(
                f"{path} holds {len(streams)} skeleton streams; choose one with source_id: "
                f"{', '.join(sorted(streams))}"
            )
        source_id = next(iter(streams))
    if source_id not in streams:
        raise RecordingError(
            f"no skeleton stream {source_id!r} in {path}. Available: {', '.join(sorted(streams))}"
        )
    return sorted(streams[source_id], key=lambda s: s.stamp.capture_ns)


@dataclass(frozen=True, slots=True)
class RetargetSummary:
    """What an offline retargeting run produced.

    Attributes:
        source: The recording.
        frames: Frames retargeted.
        flagged: Frames whose wrist error exceeds the threshold.
        max_wrist_error_m: Largest wrist error over the recording [m].
        mean_wrist_error_m: Mean over frames of the larger wrist error [m].
        duration_s: Capture-time span of the recording [s].
        rate_hz: Median frame rate [Hz].
        cutoff_hz: Low-pass cutoff [Hz]; None when not filtered.
        order: Butterworth order.
        threshold_m: Wrist error threshold for the flags [m].
        profile: Skeleton naming profile used.
    """

    source: str
    frames: int
    flagged: int
    max_wrist_error_m: float
    mean_wrist_error_m: float
    duration_s: float
    rate_hz: float
    cutoff_hz: float | None
    order: int
    threshold_m: float
    profile: str


@dataclass(frozen=True, slots=True)
class RecordingRetarget:
    """Joint trajectory of a retargeted recording.

    Attributes:
        t_ns: Capture time of each frame, common clock [ns]. Shape (F,).
        joint_names: Upper-body joints, the columns of ``q``.
        q: Joint positions [rad]. Shape (F, n).
        wrist_errors: Right and left wrist error per frame [m]. Shape (F, 2).
        flagged: Frames whose larger wrist error exceeds the threshold. Shape (F,).
        summary: Counts and extremes.
        files: Files written (the ``.npz``, then the ``.png`` when plotted).
    """

    t_ns: np.ndarray
    joint_names: tuple[str, ...]
    q: FloatArray
    wrist_errors: FloatArray
    flagged: np.ndarray
    summary: RetargetSummary
    files: tuple[Path, ...] = ()


def retarget_recording(
    source: Path | str,
    output: Path | str | None = None,
    *,
    cutoff_hz: float | None = DEFAULT_CUTOFF_HZ,
    order: int = DEFAULT_ORDER,
    source_id: str | None = None,
    profile: str | SkeletonProfile | None = None,
    ik: HumanoidIK | None = None,
    iterations: int = 4,
    plot: bool | None = None,
    progress: ProgressCallback | None = None,
) -> RecordingRetarget:
    """Retarget a whole recording onto the humanoid's upper body.

    Steps: load the skeleton frames (:func:`load_skeletons`); extract the keypoints; resample them
    onto a uniform grid at the median frame rate, low-pass them (:func:`lowpass`) and sample them
    back at the frame times; build targets per frame; solve the IK per frame, warm-started from the
    previous frame with the joint speed limit over the frame interval (the first frame settles from
    home); flag frames whose wrist error exceeds the IK's threshold.

    Args:
        source: A BVH file, an MCAP log or an episode folder.
        output: Folder to write ``humanoid_retarget.npz`` (and ``humanoid_retarget.png``) into;
            nothing is written when None.
        cutoff_hz: Low-pass cutoff [Hz]; None skips filtering.
        order: Butterworth order.
        source_id: The skeleton stream when an MCAP holds several.
        profile: Skeleton naming (detected when None).
        ik: The IK (its threshold sets the flags); a default :class:`HumanoidIK` when None.
        iterations: QP sub-steps per frame.
        plot: Write the plot: True requires matplotlib, None plots when it is installed, False never.
        progress: Called with ``(done, total)`` frames after each frame.

    Raises:
        RecordingError: the recording cannot be read or holds no usable skeleton stream.
        ValueError: a skeleton lacks a required joint (one line naming them) or the cutoff is not
            below half the frame rate.
        DependencyError: ``plot=True`` and matplotlib is not installed.
    """
    if plot is True:
        _require_matplotlib()
    frames = load_skeletons(source, source_id=source_id)
    ik = ik if ik is not None else HumanoidIK()
    keymap = KeypointMap(profile)
    t_ns = np.array([f.stamp.capture_ns for f in frames], dtype=np.int64)
    t_ns, unique = np.unique(t_ns, return_index=True)  # drop repeated frames
    points = np.stack([keymap(frames[i]) for i in unique])  # (F, K, 3)
    n_frames = points.shape[0]
    t = (t_ns - t_ns[0]) / 1e9
    rate = 1.0 / float(np.median(np.diff(t))) if n_frames > 1 else 0.0
    if cutoff_hz is not None and n_frames > 1:
        points = _filter_keypoints(points, t, rate, cutoff_hz, order)

    q = np.empty((n_frames, len(ik.joint_names)))
    errors = np.empty((n_frames, 2))
    flagged = np.zeros(n_frames, dtype=bool)
    previous: HumanoidTargets | None = None
    q_prev = np.array(ik.home)
    for k in range(n_frames):
        targets = humanoid_targets(points[k], ik.geometry, waist_range=ik.waist_range, previous=previous)
        if k == 0:
            result = ik.solve(targets, q_prev, _SETTLE_DT, iterations=_SETTLE_ITERATIONS)
        else:
            result = ik.solve(targets, q_prev, max(t[k] - t[k - 1], 1e-6), iterations=iterations)
        q[k], errors[k], flagged[k] = result.q, result.wrist_errors, result.flagged
        q_prev, previous = result.q, targets
        if progress is not None:
            progress(k + 1, n_frames)

    worst = errors.max(axis=1)
    assert keymap.profile is not None
    summary = RetargetSummary(
        source=str(source),
        frames=n_frames,
        flagged=int(flagged.sum()),
        max_wrist_error_m=float(worst.max()),
        mean_wrist_error_m=float(worst.mean()),
        duration_s=float(t[-1]),
        rate_hz=rate,
        cutoff_hz=cutoff_hz,
        order=order,
        threshold_m=ik.residual_threshold_m,
        profile=keymap.profile.name,
    )
    out = RecordingRetarget(t_ns, ik.joint_names, q, errors, flagged, summary)
    files: tuple[Path, ...] = ()
    if output is not None:
        files = _write(out, Path(output), plot=plot)
    _log.info(
        "retargeted %d frames of %s: %d flagged, max wrist error %.1f mm",
        n_frames,
        source,
        summary.flagged,
        summary.max_wrist_error_m * 1e3,
    )
    return RecordingRetarget(t_ns, ik.joint_names, q, errors, flagged, summary, files)


def _filter_keypoints(
    points: FloatArray, t: FloatArray, rate: float, cutoff_hz: float, order: int
) -> FloatArray:
    """Low-pass every keypoint coordinate on a uniform grid; keypoints with any NaN become all-NaN."""
    grid = np.arange(0.0, t[-1] + 0.5 / rate, 1.0 / rate)
    out = np.full_like(points, np.nan)
    for k in range(len(KEYPOINTS)):
        if not np.all(np.isfinite(points[:, k])):
            continue  # an optional keypoint seen in some frames only: treated as absent
        uniform = np.stack([np.interp(grid, t, points[:, k, c]) for c in range(3)], axis=1)
        smooth = lowpass(uniform, rate, cutoff_hz, order)
        out[:, k] = np.stack([np.interp(t, grid, smooth[:, c]) for c in range(3)], axis=1)
    return out


def _require_matplotlib() -> Any:
    """The ``matplotlib.pyplot`` module, drawing off-screen (Agg)."""
    try:
        matplotlib = importlib.import_module("matplotlib")
    except ImportError:
        raise DependencyError(
            "matplotlib is not installed (needed for the retargeting plot). "
            "Install it with: pip install matplotlib"
        ) from None
    matplotlib.use("Agg")
    return importlib.import_module("matplotlib.pyplot")


def _write(result: RecordingRetarget, folder: Path, *, plot: bool | None) -> tuple[Path, ...]:
    folder.mkdir(parents=True, exist_ok=True)
    npz = folder / "humanoid_retarget.npz"
    np.savez_compressed(
        npz,
        t_ns=result.t_ns,
        joint_names=np.array(result.joint_names),
        q=result.q,
        wrist_errors=result.wrist_errors,
        flagged=result.flagged,
        summary=np.array(json.dumps(asdict(result.summary))),
    )
    files = [npz]
    if plot is not False:
        try:
            files.append(_plot(result, folder / "humanoid_retarget.png"))
        except DependencyError:
            if plot:
                raise
            _log.info("matplotlib is not installed: no plot written (pip install matplotlib)")
    return tuple(files)


def _plot(result: RecordingRetarget, path: Path) -> Path:
    plt = _require_matplotlib()

    t = (result.t_ns - result.t_ns[0]) / 1e9
    fig, (top, bottom) = plt.subplots(2, 1, sharex=True, figsize=(10, 7))
    for j, name in enumerate(result.joint_names):
        top.plot(t, result.q[:, j], label=name, linewidth=1)
    top.set_ylabel("joint [rad]")
    top.legend(fontsize=6, ncol=3)
    bottom.plot(t, result.wrist_errors[:, 0] * 1e3, label="right wrist")
    bottom.plot(t, result.wrist_errors[:, 1] * 1e3, label="left wrist")
    bottom.axhline(result.summary.threshold_m * 1e3, color="r", linestyle="--", label="threshold")
    half = 0.5 / max(result.summary.rate_hz, 1e-9)  # half a frame [s]
    for k in np.flatnonzero(result.flagged):
        bottom.axvspan(
            t[k] - half,
            t[k] + half,
            color="r",
            alpha=0.15,
            linewidth=0,
        )
    bottom.set_ylabel("wrist error [mm]")
    bottom.set_xlabel("time [s]")
    bottom.legend(fontsize=8)
    fig.suptitle(
        f"{Path(result.summary.source).name}: {result.summary.frames} frames, "
        f"{result.summary.flagged} flagged, max {result.summary.max_wrist_error_m * 1e3:.1f} mm"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
