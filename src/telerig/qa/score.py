"""Episode quality score in [0, 1]: smoothness, completion time, idle time, tracking error, success.

Every component has a raw value in its own unit and a sub-score in [0, 1] (1 is best); the total
is their weighted mean (:class:`~telerig.config.qa.ScoreWeights`, the rig's ``qa.score_weights``)
over the components that could be measured. A component without data (no success label, no task
median, no motion recorded) is reported with ``score=None`` and gives its weight to the others; an
episode where nothing could be measured scores 0. Training weights or filters episodes by the total.

Components (raw value → sub-score; each sub-score is monotonic in its raw value):

* **smoothness**: the speed-normalized rms jerk of the sent joint commands (see
  :func:`normalized_jerk`) [1/s²] → ``1 / (1 + jerk / JERK_REF)``.
* **completion_time**: duration / the task's median duration [1] → ``1`` up to the median, then
  ``median / duration`` (twice the median scores 0.5).
* **idle**: the fraction of idle frames, by the idle gate's definition (:mod:`telerig.qa.gates`)
  [1] → ``1 - idle``.
* **tracking**: the mean IK residual (worst ``*_error_m`` task of each recorded ``residual``
  message) [m] → ``1 / (1 + e / TRACKING_REF_M)``; where no residual is recorded, the mean over
  time of the rms over joints of |sent - measured| joint position [rad] →
  ``1 / (1 + e / TRACKING_REF_RAD)``.
* **success**: the success/failure label (the episode's ``label.json``, else manifest
  ``extra.outcome``): success 1, failure 0.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import numpy.typing as npt
from pydantic import JsonValue, ValidationError

from telerig.bus.catalogue import JOINT_SENT, JOINT_STATE
from telerig.bus.topics import node_of, stream_of
from telerig.config.qa import ScoreWeights
from telerig.errors import RecordingError
from telerig.ir.mcap_log import read_residuals
from telerig.ir.types import FloatArray
from telerig.qa.report import QaReport
from telerig.record.align import StreamData, load_streams
from telerig.store.episodes import EpisodeManifest
from telerig.store.index import EpisodeRecord
from telerig.store.label_file import episode_outcome

__all__ = [
    "COMPONENTS",
    "JERK_REF",
    "JERK_SIGMA_S",
    "RESAMPLE_HZ",
    "TRACKING_REF_M",
    "TRACKING_REF_RAD",
    "ComponentName",
    "QualityScore",
    "ScoreComponent",
    "normalized_jerk",
    "score",
    "task_medians",
]

ComponentName = Literal["smoothness", "completion_time", "idle", "tracking", "success"]
COMPONENTS: tuple[ComponentName, ...] = ("smoothness", "completion_time", "idle", "tracking", "success")

#: Rate of the uniform grid the joint path is resampled on before differentiating [Hz]. Jerk by
#: finite differences of the raw, jittery control-tick samples grows with the rate (the demo's sent
#: commands: 550 1/s² on a 25 Hz grid, 8200 on 100 Hz); on a fixed grid after the low-pass below
#: the value barely depends on the grid (same demo: 274 at 50 Hz, 292 at 100 Hz, 296 at 500 Hz).
RESAMPLE_HZ = 100.0
#: Standard deviation of the Gaussian low-pass applied before differentiating [s]; its -3 dB
#: point is 4.4 Hz, above voluntary human arm motion (< 4 Hz), so what is left is the operator's
#: and the safety chain's motion, not the control loop's timing jitter.
JERK_SIGMA_S = 0.03
#: Normalized jerk that scores 0.5 [1/s²]. A chain of minimum-jerk reaches of duration t gives
#: sqrt(720) / t² (107 for 0.5 s reaches); the scripted demo operator through the safety chain
#: gives about 300 on a loaded machine.
JERK_REF = 300.0
#: IK residual that scores 0.5 [m]: the retargeters' default flag threshold (residual_threshold_m).
TRACKING_REF_M = 0.05
#: |sent - measured| joint error that scores 0.5 [rad]: the safety chain's measured-position
#: tolerance (the calibration-drift gate's default, 2.9 deg).
TRACKING_REF_RAD = 0.05
#: Joint path length per second under which a robot is considered still [rad/s]: its jerk is then
#: noise over no motion, so it counts as perfectly smooth (the idle component reports stillness).
_STILL_RAD_S = 1e-6
#: A joint position beyond this is corrupt, not motion [rad] or [m]; such samples are dropped
#: (their jerk would overflow float64).
_MAX_POSITION = 1e9


@dataclass(frozen=True, slots=True)
class ScoreComponent:
    """One component of the quality score.

    Attributes:
        name: Which component (:data:`ComponentName`).
        raw: The measured value in ``unit``; ``None`` when it could not be measured.
        unit: Unit of ``raw`` (``1/s^2``, ``ratio``, ``fraction``, ``m``, ``rad``, ``label``).
        score: Sub-score in [0, 1], 1 best; ``None`` when not measured (its weight goes to the others).
        weight: Its weight in the total (as configured; only ratios matter).
        detail: How it was measured, or why not (one line).
    """

    name: ComponentName
    raw: float | None
    unit: str
    score: float | None
    weight: float
    detail: str

    def to_json(self) -> dict[str, JsonValue]:
        """JSON values (``None`` as null)."""
        return {
            "raw": self.raw,
            "unit": self.unit,
            "score": self.score,
            "weight": self.weight,
            "detail": self.detail,
        }


@dataclass(frozen=True, slots=True)
class QualityScore:
    """The quality score of one episode.

    Attributes:
        episode_id: The episode.
        total: Weighted mean of the measured components' sub-scores, in [0, 1]; 0 when none was.
        components: Every component, in :data:`COMPONENTS` order.
    """

    episode_id: str
    total: float
    components: tuple[ScoreComponent, ...]

    def component(self, name: ComponentName) -> ScoreComponent:
        """The component ``name``."""
        for c in self.components:
            if c.name == name:
                return c
        raise KeyError(f"score component {name!r} does not exist. Available: {', '.join(COMPONENTS)}")

    def to_json(self) -> dict[str, JsonValue]:
        """``{"episode": id, "total": t, "components": {name: {...}}}`` for qa.json, manifests and exports."""
        return {
            "episode": self.episode_id,
            "total": self.total,
            "components": {c.name: c.to_json() for c in self.components},
        }


def score(
    episode_dir: Path,
    report: QaReport | None,
    *,
    task_median_s: float | None,
    weights: ScoreWeights | None = None,
    streams: Mapping[str, StreamData] | None = None,
    residual_errors: Sequence[float] | None = None,
) -> QualityScore:
    """Score a recorded episode.

    Args:
        episode_dir: The episode directory (``manifest.json``, ``episode.mcap``).
        report: The quality gates' report of the episode (:func:`telerig.qa.gates.evaluate`), whose
            ``idle_fraction`` is the idle component; ``None`` leaves that component unmeasured.
        task_median_s: Median duration of the task's episodes [s] (:func:`task_medians`); ``None``
            leaves the completion-time component unmeasured.
        weights: Component weights; the defaults of :class:`~telerig.config.qa.ScoreWeights` when
            ``None`` (pass the rig's ``qa.score_weights``).
        streams: The episode's streams by topic if already read, its joint streams at least
            (:func:`telerig.record.align.load_streams`, or the gates' read:
            :attr:`telerig.qa.episode.EpisodeData.streams`); read from ``episode.mcap`` when ``None``.
        residual_errors: The worst ``*_error_m`` metric of each recorded residual [m] if already
            read (:attr:`telerig.qa.episode.EpisodeData.residual_errors`); read from
            ``episode.mcap`` when ``None``.

    Raises:
        RecordingError: The manifest cannot be read (one line naming the file).
    """
    w = weights if weights is not None else ScoreWeights()
    manifest = _manifest(episode_dir)
    mcap = episode_dir / "episode.mcap"
    if streams is None:
        streams = load_streams(mcap) if mcap.is_file() else {}
    components = (
        _smoothness(streams, w.smoothness),
        _completion_time(manifest.duration_s, task_median_s, w.completion_time),
        _idle(report, w.idle),
        _tracking(mcap, streams, w.tracking, residual_errors),
        _success(episode_dir, manifest, w.success),
    )
    measured = [c for c in components if c.score is not None and c.weight > 0]
    total_weight = sum(c.weight for c in measured)
    total = sum(c.weight * (c.score or 0.0) for c in measured) / total_weight if total_weight > 0 else 0.0
    return QualityScore(manifest.id, _unit(total), components)


def task_medians(records: Iterable[EpisodeRecord]) -> dict[str, float]:
    """Median duration [s] of each task's complete episodes (of any length > 0), by task."""
    durations: dict[str, list[float]] = {}
    for r in records:
        if r.status == "complete" and r.duration_s is not None and r.duration_s > 0:
            durations.setdefault(r.task, []).append(r.duration_s)
    return {task: statistics.median(d) for task, d in durations.items()}


# --- smoothness ----------------------------------------------------------------------------------


def normalized_jerk(time_ns: npt.NDArray[np.int64], positions: FloatArray) -> tuple[float, float] | None:
    """Speed-normalized rms jerk of a joint path, and its path length.

    The path (samples with a non-finite or absurd, > 1e9, position dropped) is resampled linearly
    onto a uniform :data:`RESAMPLE_HZ` grid, smoothed with a Gaussian of :data:`JERK_SIGMA_S`, and
    differentiated by finite differences. With T the grid's duration, q⃛ the jerk and q̇ the velocity::

        J = sqrt( (1/T) ∫ |q⃛(t)|² dt ) / ( (1/T) ∫ |q̇(t)| dt )        [1/s²]

    i.e. the integrated squared jerk normalized by duration (mean over time) and by amplitude
    (divided by the mean joint-space speed, so scaling the path scales both alike). Unlike the
    dimensionless jerk T⁵/A² ∫|q⃛|² (which grows as N⁴ with N sub-movements) it does not grow with
    the episode's length: a chain of minimum-jerk movements of duration t each gives sqrt(720)/t².

    Args:
        time_ns: Sample times [ns], non-decreasing. Shape (S,).
        positions: Joint positions [rad] or [m]. Shape (S, n).

    Returns:
        ``(J [1/s²], path length [rad])``; J is 0 for a still path (length below 1e-6 rad per
        second); ``None`` when the path spans fewer than 4 grid points or has no joints.
    """
    q = np.asarray(positions, dtype=np.float64)
    if q.ndim != 2 or q.shape[1] == 0 or len(time_ns) != len(q):
        return None
    finite = np.all(np.abs(q) <= _MAX_POSITION, axis=1)  # False for NaN and inf too
    t_ns, q = np.asarray(time_ns, dtype=np.int64)[finite], q[finite]
    if len(t_ns) < 2:
        return None
    t_ns, last = np.unique(t_ns[::-1], return_index=True)  # the last sample of a repeated stamp
    q = q[::-1][last]
    t = (t_ns - t_ns[0]) / 1e9
    dt = 1.0 / RESAMPLE_HZ
    grid = np.arange(0.0, t[-1] + dt / 2, dt)
    if len(grid) < 4:
        return None
    path = np.stack([np.interp(grid, t, q[:, j]) for j in range(q.shape[1])], axis=1)
    path = _gaussian(path, JERK_SIGMA_S / dt)
    duration = (len(grid) - 1) * dt
    length = float(np.sum(np.linalg.norm(np.diff(path, axis=0), axis=1)))
    if length < _STILL_RAD_S * duration:
        return 0.0, length
    jerk = np.diff(path, n=3, axis=0) / dt**3
    mean_sq_jerk = float(np.sum(jerk**2)) * dt / duration
    return math.sqrt(mean_sq_jerk) / (length / duration), length


def _gaussian(x: FloatArray, sigma_samples: float) -> FloatArray:
    """``x`` (S, n) smoothed along axis 0 by a Gaussian of ``sigma_samples``, ends held (edge pad)."""
    radius = max(1, math.ceil(4 * sigma_samples))
    kernel = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma_samples) ** 2)
    kernel /= kernel.sum()
    padded = np.pad(x, ((radius, radius), (0, 0)), mode="edge")
    return np.stack([np.convolve(padded[:, j], kernel, mode="valid") for j in range(x.shape[1])], axis=1)


def _smoothness(streams: Mapping[str, StreamData], weight: float) -> ScoreComponent:
    sources = _by_stream(streams, JOINT_SENT) or _by_stream(streams, JOINT_STATE)
    measured: list[tuple[str, float, float]] = []
    for topic, data in sources.items():
        positions = data.fields.get("positions")
        result = None if positions is None else normalized_jerk(data.time_ns, positions)
        if result is not None:
            measured.append((topic, *result))
    if not measured:
        why = "no joint path of 4 or more 10 ms steps" if sources else "no joint commands or states recorded"
        return ScoreComponent("smoothness", None, "1/s^2", None, weight, why)
    # Robots weigh by how far they moved: one held still (jerk of noise over no motion) barely counts.
    total_length = sum(length for _, _, length in measured)
    raw = sum(j * length for _, j, length in measured) / total_length if total_length > 0 else 0.0
    names = ", ".join(node_of(t) + "/" + stream_of(t) for t, _, _ in measured)
    detail = (
        f"speed-normalized rms jerk of {names}, {RESAMPLE_HZ:g} Hz grid, {JERK_SIGMA_S * 1e3:g} ms low-pass"
    )
    return ScoreComponent("smoothness", raw, "1/s^2", _unit(1.0 / (1.0 + raw / JERK_REF)), weight, detail)


# --- completion time, idle, success --------------------------------------------------------------


def _completion_time(duration_s: float | None, median_s: float | None, weight: float) -> ScoreComponent:
    if median_s is None or not math.isfinite(median_s) or median_s <= 0:
        return ScoreComponent(
            "completion_time", None, "ratio", None, weight, "no median duration for the task"
        )
    if duration_s is None or not math.isfinite(duration_s) or duration_s <= 0:
        return ScoreComponent("completion_time", None, "ratio", None, weight, "the episode has no duration")
    ratio = duration_s / median_s
    detail = f"{duration_s:.2f} s against the task's median {median_s:.2f} s"
    return ScoreComponent("completion_time", ratio, "ratio", _unit(min(1.0, 1.0 / ratio)), weight, detail)


def _idle(report: QaReport | None, weight: float) -> ScoreComponent:
    if report is None:
        return ScoreComponent("idle", None, "fraction", None, weight, "no quality-gate report")
    idle = report.idle_fraction
    if not math.isfinite(idle):
        return ScoreComponent(
            "idle", None, "fraction", None, weight, "the gate report's idle fraction is not a number"
        )
    idle = _unit(idle)
    return ScoreComponent(
        "idle", idle, "fraction", 1.0 - idle, weight, "idle frames, quality-gate definition"
    )


def _success(episode_dir: Path, manifest: EpisodeManifest, weight: float) -> ScoreComponent:
    try:
        outcome = episode_outcome(episode_dir, manifest)  # label.json first, then the recording's mark
    except RecordingError as exc:
        return ScoreComponent("success", None, "label", None, weight, str(exc))
    if outcome is None:
        return ScoreComponent("success", None, "label", None, weight, "no success/failure label")
    value = 1.0 if outcome == "success" else 0.0
    return ScoreComponent("success", value, "label", value, weight, f"labelled {outcome}")


# --- tracking ------------------------------------------------------------------------------------


def _tracking(
    mcap: Path, streams: Mapping[str, StreamData], weight: float, residuals: Sequence[float] | None
) -> ScoreComponent:
    if residuals is None:
        residuals = _residual_errors(mcap) if mcap.is_file() else []
    if residuals:
        raw = float(np.mean(residuals))
        detail = f"mean IK residual (worst *_error_m task) over {len(residuals)} ticks"
        return ScoreComponent("tracking", raw, "m", _unit(1.0 / (1.0 + raw / TRACKING_REF_M)), weight, detail)
    errors: list[FloatArray] = []
    states = _by_stream(streams, JOINT_STATE)
    for topic, sent in _by_stream(streams, JOINT_SENT).items():
        state = states.get(topic.removesuffix(JOINT_SENT) + JOINT_STATE)
        if state is not None:
            errors.append(_joint_error(sent, state))
    samples = np.concatenate(errors) if errors else np.zeros(0)
    if samples.size == 0:
        why = "no IK residual, and no joint commands with measured joint states over the same time"
        return ScoreComponent("tracking", None, "rad", None, weight, why)
    raw = float(np.mean(samples))
    detail = f"mean rms |sent - measured| joint error over {samples.size} states (no IK residual recorded)"
    return ScoreComponent("tracking", raw, "rad", _unit(1.0 / (1.0 + raw / TRACKING_REF_RAD)), weight, detail)


def _residual_errors(mcap: Path) -> list[float]:
    """The worst ``*_error_m`` value of every recorded residual message [m] (typed or the JSON of
    earlier episodes, :func:`~telerig.ir.mcap_log.read_residuals`; NaN, inf and corrupt values left
    out: :meth:`~telerig.ir.types.RetargetResidual.worst_error_m`)."""
    errors = (residual.worst_error_m() for _, residual, _ in read_residuals(mcap))
    return [e for e in errors if e is not None]


def _joint_error(sent: StreamData, state: StreamData) -> FloatArray:
    """Rms over joints of |command in force - measured| at each measured state [rad]. Shape (M,)."""
    q_sent, q_meas = sent.fields.get("positions"), state.fields.get("positions")
    if q_sent is None or q_meas is None or q_sent.ndim != 2 or q_sent.shape[1:] != q_meas.shape[1:]:
        return np.zeros(0)
    if q_sent.shape[1] == 0 or len(sent.time_ns) == 0:
        return np.zeros(0)
    held = np.searchsorted(sent.time_ns, state.time_ns, side="right") - 1  # zero-order hold
    ok = held >= 0
    with np.errstate(over="ignore", invalid="ignore"):  # corrupt samples: left out below
        diff = q_meas[ok] - q_sent[held[ok]]
        rms = np.sqrt(np.mean(diff**2, axis=1))
    out: FloatArray = rms[rms <= _MAX_POSITION]
    return out


# --- helpers -------------------------------------------------------------------------------------


def _manifest(episode_dir: Path) -> EpisodeManifest:
    path = episode_dir / "manifest.json"
    try:
        return EpisodeManifest.model_validate_json(path.read_bytes())
    except OSError as exc:
        raise RecordingError(f"cannot read {path}: {exc.strerror or exc}") from None
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"]) or "document"
        raise RecordingError(f"{path} is not a valid manifest: {where}: {first['msg']}") from None


def _by_stream(streams: Mapping[str, StreamData], stream: str) -> dict[str, StreamData]:
    return {t: d for t, d in streams.items() if stream_of(t) == stream}


def _unit(x: float) -> float:
    """``x`` clipped to [0, 1]; NaN becomes 0."""
    return 0.0 if math.isnan(x) else min(1.0, max(0.0, float(x)))
