"""One PNG per episode: joint trajectories (requested / sent / measured), grippers, IK residuals and the
quality gates' event markers, on one time axis in seconds from the episode start."""

from __future__ import annotations

import importlib
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from telerig.bus.catalogue import (
    GRIPPER_REQUESTED,
    GRIPPER_SENT,
    GRIPPER_STATE,
    JOINT_REQUESTED,
    JOINT_SENT,
    JOINT_STATE,
)
from telerig.bus.topics import Topic
from telerig.errors import DependencyError, RecordingError
from telerig.ir.mcap_log import read_residuals
from telerig.ir.types import FloatArray
from telerig.qa.report import GateVerdict, QaReport
from telerig.record.align import StreamData, load_streams
from telerig.store.episodes import EpisodeManifest
from telerig.store.qa_file import read_qa

__all__ = ["DEFAULT_WIDTH_PX", "ROW_HEIGHT_PX", "PlotSummary", "plot_episode", "plot_size"]

#: Default image width [px].
DEFAULT_WIDTH_PX = 1600
#: Default height of one row of subplots [px]; the image is this times the rows plus a header.
ROW_HEIGHT_PX = 210
_HEADER_PX = 120
_DPI = 100
#: Line styles: what was asked for, what the safety chain let through, what the robot did.
_SERIES = {
    "requested": {"color": "tab:orange", "linestyle": "--", "linewidth": 1.0},
    "sent": {"color": "tab:blue", "linestyle": "-", "linewidth": 1.2},
    "measured": {"color": "tab:green", "linestyle": ":", "linewidth": 1.6},
}
_JOINT_STREAMS = {"requested": JOINT_REQUESTED, "sent": JOINT_SENT, "measured": JOINT_STATE}
_GRIPPER_STREAMS = {"requested": GRIPPER_REQUESTED, "sent": GRIPPER_SENT, "measured": GRIPPER_STATE}
_RESIDUAL_SUFFIX = "_error_m"
#: Residual curves take colours none of the trajectory series or gate markers use.
_RESIDUAL_COLORS = ("tab:purple", "tab:brown", "tab:pink", "tab:olive", "tab:cyan", "black")
#: Gate markers: red for a failed gate, grey for a passed one; each gate its own line style.
_FAILED_STYLES = ("-", "--", ":", "-.")
_PASSED_STYLES = ("-.", ":", "--", "-")


@dataclass(frozen=True, slots=True)
class PlotSummary:
    """What :func:`plot_episode` drew.

    Attributes:
        path: The PNG written.
        width_px: Image width [px].
        height_px: Image height [px].
        panels: Subplot titles, in reading order (row by row).
        series: The curves of each subplot (``requested``, ``sent``, ``measured`` or a residual's
            name), aligned with ``panels``.
        gate_events: ``(gate, time [s from the episode start], failed)`` of every marker drawn.
    """

    path: Path
    width_px: int
    height_px: int
    panels: tuple[str, ...]
    series: tuple[tuple[str, ...], ...] = field(default=())
    gate_events: tuple[tuple[str, float, bool], ...] = field(default=())


@dataclass(frozen=True, slots=True)
class _Panel:
    title: str
    ylabel: str
    series: list[tuple[str, FloatArray, FloatArray]]  # (kind or label, time [s], values)


def plot_size(panels: int, *, width_px: int = DEFAULT_WIDTH_PX) -> tuple[int, int, int, int]:
    """``(columns, rows, width [px], height [px])`` of the figure for ``panels`` subplots."""
    columns = 1 if panels <= 4 else 2 if panels <= 12 else 3
    rows = max(1, math.ceil(panels / columns))
    return columns, rows, width_px, _HEADER_PX + rows * ROW_HEIGHT_PX


def plot_episode(
    episode_dir: Path,
    out: Path,
    *,
    report: QaReport | None = None,
    width_px: int = DEFAULT_WIDTH_PX,
    streams: Mapping[str, StreamData] | None = None,
) -> PlotSummary:
    """Write a PNG of an episode's robot trajectories.

    One subplot per joint of every robot (requested vs sent vs measured position [rad] or [m],
    matched by joint name), one per gripper (opening: requested, sent, and measured where a
    ``gripper_state`` stream is recorded), one for the IK residuals (every ``*_error_m`` metric
    [m]) when recorded. Every subplot shares one time axis [s from the episode start]; the legend
    is drawn once. Gate events (:attr:`~telerig.qa.report.GateVerdict.events`) are vertical lines:
    red for a failed gate, grey for one that passed, labelled once at the top.

    Args:
        episode_dir: The episode directory (``manifest.json``, ``episode.mcap``, ``qa.json``).
        out: The PNG to write (its directory is created).
        report: The quality gates' report; read from the episode's ``qa.json`` when ``None``
            (no markers when it has none).
        width_px: Image width [px]; the height follows from the number of subplots (:func:`plot_size`).
        streams: The episode's streams if already loaded (:func:`~telerig.record.align.load_streams`).

    Raises:
        DependencyError: matplotlib is not installed (``pip install 'telerig[plot]'``).
        RecordingError: the episode cannot be read or has no joint, gripper or residual stream.
    """
    if width_px < 200 or width_px > 20_000:
        raise ValueError(f"width_px must be within 200..20000 px, got {width_px}")
    plt = _pyplot()
    manifest = _manifest(episode_dir)
    mcap = episode_dir / "episode.mcap"
    if streams is None:
        if not mcap.is_file():
            raise RecordingError(
                f"episode {manifest.id} has no episode.mcap in {episode_dir}; nothing to plot"
            )
        streams = load_streams(mcap)
    if report is None:
        qa = read_qa(episode_dir)
        report = None if qa is None else QaReport.from_json(qa.report)
    panels = _joint_panels(streams, manifest.start_ns) + _gripper_panels(streams, manifest.start_ns)
    residual = _residual_panel(mcap, manifest.start_ns) if mcap.is_file() else None
    if residual is not None:
        panels.append(residual)
    if not panels:
        raise RecordingError(
            f"episode {manifest.id} recorded no joint, gripper or residual stream; nothing to plot"
        )
    columns, rows, width, height = plot_size(len(panels), width_px=width_px)
    fig, axes = plt.subplots(
        rows,
        columns,
        sharex=True,
        squeeze=False,
        figsize=(width / _DPI, height / _DPI),
        dpi=_DPI,
        layout="constrained",
    )
    try:
        events = _draw(fig, axes, panels, report, manifest)
        out.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(out, dpi=_DPI, format="png")
    finally:
        plt.close(fig)
    return PlotSummary(
        out,
        width,
        height,
        tuple(p.title for p in panels),
        tuple(tuple(label for label, _, _ in p.series) for p in panels),
        events,
    )


def _draw(
    fig: Any, axes: Any, panels: Sequence[_Panel], report: QaReport | None, manifest: EpisodeManifest
) -> tuple[tuple[str, float, bool], ...]:
    flat = list(axes.flat)
    handles: dict[str, Any] = {}
    for ax, panel in zip(flat, panels, strict=False):
        for i, (label, t, y) in enumerate(panel.series):
            style = _SERIES.get(label) or {
                "linewidth": 1.0,
                "color": _RESIDUAL_COLORS[i % len(_RESIDUAL_COLORS)],
            }
            (line,) = ax.plot(t, y, label=label, **style)
            handles.setdefault(label, line)
        ax.set_title(panel.title, fontsize=9)
        ax.set_ylabel(panel.ylabel, fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(True, linewidth=0.3, alpha=0.5)
    for ax in flat[len(panels) :]:
        ax.set_visible(False)
    columns = axes.shape[1]
    for k in range(columns):  # the bottom visible subplot of each column carries the time axis
        column = [ax for i, ax in enumerate(flat[: len(panels)]) if i % columns == k]
        if column:
            column[-1].set_xlabel("time [s from episode start]", fontsize=8)
            column[-1].xaxis.set_tick_params(labelbottom=True)
    events = _gate_markers(flat[: len(panels)], report, handles)
    duration = f"{manifest.duration_s:.1f} s" if manifest.duration_s is not None else "interrupted"
    fig.suptitle(
        f"{manifest.id}  {manifest.task!r}  ({manifest.operator}, {duration})", fontsize=11, x=0.01, ha="left"
    )
    fig.legend(
        list(handles.values()),
        list(handles),
        loc="outside upper right",
        ncol=min(len(handles), 6),
        fontsize=8,
    )
    return events


def _gate_markers(
    axes: Sequence[Any], report: QaReport | None, handles: dict[str, Any]
) -> tuple[tuple[str, float, bool], ...]:
    if report is None:
        return ()
    drawn: list[tuple[str, float, bool]] = []
    styles = {
        True: iter(_FAILED_STYLES * len(report.verdicts)),
        False: iter(_PASSED_STYLES * len(report.verdicts)),
    }
    for verdict in report.verdicts:
        if verdict.passed is None or not verdict.events:
            continue
        failed = verdict.passed is False
        color = "red" if failed else "grey"
        style = next(styles[failed])  # one line style per gate, so two failed gates tell apart
        for t in verdict.events:
            for ax in axes:
                line = ax.axvline(t, color=color, linewidth=0.9, alpha=0.7, linestyle=style, zorder=0.5)
            drawn.append((verdict.gate, t, failed))
        handles.setdefault(_marker_label(verdict), line)
        axes[0].annotate(
            verdict.gate,
            xy=(verdict.events[0], 1.0),
            xycoords=("data", "axes fraction"),
            fontsize=7,
            color=color,
            rotation=90,
            va="top",
            ha="right",
        )
    return tuple(drawn)


def _marker_label(verdict: GateVerdict) -> str:
    return f"gate {verdict.gate} {'failed' if verdict.passed is False else 'passed'}"


# --- panels --------------------------------------------------------------------------------------


def _joint_panels(streams: Mapping[str, StreamData], start_ns: int) -> list[_Panel]:
    panels: list[_Panel] = []
    for robot, by_kind in _robots(streams, _JOINT_STREAMS).items():
        names: list[str] = []
        for kind in ("measured", "sent", "requested"):  # measured order first: every joint the robot has
            data = by_kind.get(kind)
            names.extend(n for n in (data.names if data is not None else ()) if n not in names)
        for joint in names:
            series = []
            for kind in ("requested", "sent", "measured"):
                data = by_kind.get(kind)
                if data is None or joint not in data.names or "positions" not in data.fields:
                    continue
                j = data.names.index(joint)
                series.append((kind, _seconds(data.time_ns, start_ns), data.fields["positions"][:, j]))
            if series:
                panels.append(_Panel(f"{robot} / {joint}", "position [rad | m]", series))
    return panels


def _gripper_panels(streams: Mapping[str, StreamData], start_ns: int) -> list[_Panel]:
    panels: list[_Panel] = []
    for robot, by_kind in _robots(streams, _GRIPPER_STREAMS).items():
        series = [
            (kind, _seconds(data.time_ns, start_ns), data.fields["opening"])
            for kind in ("requested", "sent", "measured")
            if (data := by_kind.get(kind)) is not None and "opening" in data.fields
        ]
        if series:
            panels.append(_Panel(f"{robot} / gripper", "opening [0..1]", series))
    return panels


def _residual_panel(mcap: Path, start_ns: int) -> _Panel | None:
    """Every ``*_error_m`` metric of the robots' residuals (typed, or the JSON of earlier episodes:
    :func:`~telerig.ir.mcap_log.read_residuals`) over time; non-finite values are left out."""
    values: dict[str, tuple[list[float], list[float]]] = {}
    for topic, residual, _ in read_residuals(mcap):
        t_s = (residual.stamp.capture_ns - start_ns) / 1e9
        robot = _parse(topic)[0]
        for key, v in zip(residual.names, residual.values, strict=True):
            if key.endswith(_RESIDUAL_SUFFIX) and math.isfinite(v):
                ts, ys = values.setdefault(f"{robot} {key.removesuffix(_RESIDUAL_SUFFIX)}", ([], []))
                ts.append(t_s)
                ys.append(v)
    if not values:
        return None
    series = []
    for label in sorted(values):
        t, y = values[label]
        order = np.argsort(t, kind="stable")
        series.append((label, np.asarray(t)[order], np.asarray(y)[order]))
    return _Panel("IK residual", "error [m]", series)


def _robots(streams: Mapping[str, StreamData], kinds: Mapping[str, str]) -> dict[str, dict[str, StreamData]]:
    """Robot node -> kind -> its stream, for the streams named in ``kinds`` (kind -> stream name)."""
    by_stream = {name: kind for kind, name in kinds.items()}
    out: dict[str, dict[str, StreamData]] = {}
    for topic, data in streams.items():
        node, stream = _parse(topic)
        kind = by_stream.get(stream)
        if kind is not None and data.time_ns.size:
            out.setdefault(node, {})[kind] = data
    return dict(sorted(out.items()))


# --- helpers -------------------------------------------------------------------------------------


def _pyplot() -> Any:
    """``matplotlib.pyplot``, drawing off-screen (Agg)."""
    try:
        matplotlib = importlib.import_module("matplotlib")
    except ImportError:
        raise DependencyError(
            "matplotlib is not installed (needed for episode plots). "
            "Install it with: pip install 'telerig[plot]'"
        ) from None
    matplotlib.use("Agg")
    return importlib.import_module("matplotlib.pyplot")


def _manifest(episode_dir: Path) -> EpisodeManifest:
    path = episode_dir / "manifest.json"
    try:
        return EpisodeManifest.model_validate_json(path.read_bytes())
    except OSError as exc:
        raise RecordingError(f"cannot read {path}: {exc.strerror or exc}") from None
    except ValueError as exc:
        raise RecordingError(f"{path} is not a valid manifest: {str(exc).splitlines()[0]}") from None


def _seconds(time_ns: np.ndarray, start_ns: int) -> FloatArray:
    out: FloatArray = (time_ns - start_ns) / 1e9
    return out


def _parse(topic: str) -> tuple[str, str]:
    try:
        t = Topic.parse(topic)
    except ValueError:
        return topic, ""
    return t.node, t.stream
