"""Episode quality score: each component moves the total the right way, and degenerate episodes score
a finite number in [0, 1]."""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from pydantic import ValidationError

from telerig.config.qa import QaThresholds, ScoreWeights
from telerig.errors import RecordingError
from telerig.ir import wire
from telerig.ir.mcap_log import McapLog
from telerig.ir.types import JointCommand, JointState, RetargetResidual, Stamp
from telerig.qa.episode import load_episode
from telerig.qa.report import QaReport
from telerig.qa.score import COMPONENTS, QualityScore, normalized_jerk, score, task_medians
from telerig.store.episodes import EpisodeStore
from telerig.store.index import EpisodeIndex

RIG = "telerig/v1/test"
SENT = f"{RIG}/arm0/joint_command_sent"
STATE = f"{RIG}/arm0/joint_state"
RESIDUAL = f"{RIG}/arm0/residual"
T0 = 1_700_000_000_000_000_000
NAMES = ("j1", "j2", "j3")
Path_ = Callable[[np.ndarray], np.ndarray]  # time [s] (S,) -> positions (S, 3)


def _report(idle_fraction: float) -> QaReport:
    return QaReport("ep-20231114-221320-0000", (), idle_fraction)


def _reach(t: np.ndarray, duration_s: float = 6.0, reaches: int = 3) -> np.ndarray:
    """Back-to-back minimum-jerk reaches of 0.5 rad on every joint (smooth)."""
    period = duration_s / reaches
    tau = np.clip((t % period) / period, 0, 1)
    profile = 10 * tau**3 - 15 * tau**4 + 6 * tau**5
    x = 0.5 * (np.floor(t / period) + profile)
    return np.stack([x, -x, 0.5 * x], axis=1)


def _shaky(t: np.ndarray) -> np.ndarray:
    """The same reaches with a 3 Hz, 1 cm-ish wobble on top (jerkier)."""
    return _reach(t) + 0.02 * np.sin(2 * np.pi * 3.0 * t)[:, None]


def _episode(
    root: Path,
    path: Path_ | None = _reach,
    *,
    duration_s: float = 6.0,
    rate_hz: float = 100.0,
    samples: int | None = None,
    outcome: str | None = None,
    offset_rad: float = 0.0,
    residual_m: float | None = None,
    residual_json: bool = False,
    more: Callable[[McapLog], None] | None = None,
    write_mcap: bool = True,
) -> Path:
    """A committed episode whose arm0 is sent ``path`` and measured at ``path + offset_rad``."""
    store = EpisodeStore(root)
    draft = store.begin(rig="test", task="pick", operator="op", start_ns=T0)
    if write_mcap:
        n = samples if samples is not None else round(duration_s * rate_hz)
        t = np.arange(n) / rate_hz
        q = path(t) if path is not None and n else np.zeros((n, 3))
        with McapLog(draft.mcap_path) as log:
            for i in range(n):
                ns = T0 + round(t[i] * 1e9)
                stamp = Stamp("arm0", i, ns, ns)
                cmd = JointCommand(stamp, NAMES, q[i])
                state = JointState(stamp, NAMES, q[i] + offset_rad, np.zeros(3))
                log.write(SENT, wire.encode(cmd), log_time_ns=ns, publish_time_ns=ns)
                log.write(STATE, wire.encode(state), log_time_ns=ns, publish_time_ns=ns)
                if residual_m is not None and residual_json:  # as recorded before issue 18
                    record = {"capture_ns": ns, "flagged": False, "position_error_m": residual_m}
                    log.write_json(RESIDUAL, json.dumps(record).encode(), log_time_ns=ns)
                elif residual_m is not None:
                    residual = RetargetResidual(stamp, False, ("position_error_m",), (residual_m,))
                    log.write(RESIDUAL, wire.encode(residual), log_time_ns=ns, publish_time_ns=ns)
            if more is not None:
                more(log)
    extra = {} if outcome is None else {"outcome": outcome}
    draft.commit(extra, end_ns=T0 + round(duration_s * 1e9))
    return draft.dir


def _check_finite(result: QualityScore) -> None:
    assert 0.0 <= result.total <= 1.0
    json.dumps(result.to_json(), allow_nan=False)  # raises on NaN / inf anywhere
    for c in result.components:
        assert c.score is None or 0.0 <= c.score <= 1.0
        assert c.raw is None or math.isfinite(c.raw)


# --- smoothness ----------------------------------------------------------------------------------


def test_jerkier_path_scores_lower(tmp_path: Path) -> None:
    smooth = score(_episode(tmp_path / "a", _reach), None, task_median_s=6.0)
    shaky = score(_episode(tmp_path / "b", _shaky), None, task_median_s=6.0)
    assert shaky.component("smoothness").raw > 2 * smooth.component("smoothness").raw  # type: ignore[operator]
    assert shaky.component("smoothness").score < smooth.component("smoothness").score  # type: ignore[operator]
    assert shaky.total < smooth.total


def test_normalized_jerk_of_minimum_jerk_reaches_is_sqrt720_over_t_squared() -> None:
    t = np.arange(600) / 100.0
    ns = (T0 + t * 1e9).astype(np.int64)
    jerk, length = normalized_jerk(ns, _reach(t, 6.0, reaches=3)) or (0.0, 0.0)
    # 2 s reaches: sqrt(720) / 4 = 6.7 1/s²; the 30 ms low-pass takes a little off.
    assert jerk == pytest.approx(math.sqrt(720) / 2.0**2, rel=0.1)
    assert length == pytest.approx(1.5 * math.sqrt(1 + 1 + 0.25), rel=0.01)


def test_normalized_jerk_is_independent_of_amplitude_duration_and_rate() -> None:
    def jerk(duration_s: float, reaches: int, scale: float, rate_hz: float) -> float:
        t = np.arange(round(duration_s * rate_hz)) / rate_hz
        ns = (T0 + t * 1e9).astype(np.int64)
        result = normalized_jerk(ns, scale * _reach(t, duration_s, reaches))
        assert result is not None
        return result[0]

    base = jerk(6.0, 3, 1.0, 100.0)
    assert jerk(6.0, 3, 5.0, 100.0) == pytest.approx(base, rel=1e-6)  # 5x the amplitude
    assert jerk(24.0, 12, 1.0, 100.0) == pytest.approx(base, rel=0.02)  # 4x as long, same reaches
    assert jerk(6.0, 3, 1.0, 500.0) == pytest.approx(base, rel=0.05)  # a 500 Hz control loop


@settings(max_examples=60, deadline=None)
@given(
    arrays(
        np.float64, st.tuples(st.integers(0, 40), st.integers(0, 3)), elements=st.floats(allow_infinity=True)
    ),
    st.integers(1, 30_000_000),
)
def test_normalized_jerk_is_finite_or_none_on_any_input(q: np.ndarray, step_ns: int) -> None:
    ns = T0 + np.arange(len(q), dtype=np.int64) * step_ns
    result = normalized_jerk(ns, q)
    if result is not None:
        assert all(math.isfinite(v) and v >= 0 for v in result)


# --- completion time, success, idle, tracking ----------------------------------------------------


def test_longer_than_the_task_median_scores_lower(tmp_path: Path) -> None:
    episode = _episode(tmp_path, duration_s=6.0)
    on_time = score(episode, None, task_median_s=6.0)
    slow = score(episode, None, task_median_s=3.0)
    assert on_time.component("completion_time").score == 1.0
    assert slow.component("completion_time").raw == pytest.approx(2.0)
    assert slow.component("completion_time").score == pytest.approx(0.5)
    assert slow.total < on_time.total


def test_failure_label_scores_lower_than_none_and_success(tmp_path: Path) -> None:
    totals = {
        label: score(_episode(tmp_path / str(label), outcome=label), None, task_median_s=6.0).total
        for label in ("success", None, "failure")
    }
    assert totals["success"] > totals[None] > totals["failure"]


def test_more_idle_time_scores_lower(tmp_path: Path) -> None:
    episode = _episode(tmp_path)
    busy = score(episode, _report(0.1), task_median_s=6.0)
    idle = score(episode, _report(0.8), task_median_s=6.0)
    assert busy.component("idle").score == pytest.approx(0.9)
    assert idle.total < busy.total


def test_joint_tracking_error_scores_lower_where_no_residual_is_recorded(tmp_path: Path) -> None:
    exact = score(_episode(tmp_path / "a"), None, task_median_s=6.0)
    off = score(_episode(tmp_path / "b", offset_rad=0.3), None, task_median_s=6.0)
    assert exact.component("tracking").raw == pytest.approx(0.0, abs=1e-12)
    assert off.component("tracking").unit == "rad"
    assert off.component("tracking").raw == pytest.approx(0.3)
    assert off.total < exact.total


@pytest.mark.parametrize("old_json", [False, True], ids=["typed", "json_before_issue_18"])
def test_ik_residual_is_the_tracking_error_when_recorded(tmp_path: Path, old_json: bool) -> None:
    a = _episode(tmp_path / "a", residual_m=0.001, offset_rad=0.3, residual_json=old_json)
    small = score(a, None, task_median_s=6.0)
    large = score(_episode(tmp_path / "b", residual_m=0.2, residual_json=old_json), None, task_median_s=6.0)
    assert small.component("tracking").unit == "m"
    assert small.component("tracking").raw == pytest.approx(0.001)  # the joint offset is not used
    assert large.total < small.total


def test_garbage_residuals_are_left_out_of_tracking(tmp_path: Path) -> None:
    # NaN, inf, 1e308 and negative errors, a residual without *_error_m metrics, the old JSON's
    # garbage (an array, a string error, unparsable bytes) are left out; the good ticks (0.004 m,
    # typed and old JSON) are the tracking error. (Other IR types and undecodable bytes on the
    # topic: the recorder rejects them, tests/record; read_residuals drops them, tests/ir.)
    ns = T0 + 10**9
    bad = [
        RetargetResidual(Stamp("arm0", 10_000 + i, ns + i, ns + i), True, names, values)
        for i, (names, values) in enumerate(
            [
                (("position_error_m",), (math.nan,)),
                (("position_error_m",), (math.inf,)),
                (("position_error_m", "orientation_error_rad"), (1e308, 0.1)),
                (("position_error_m",), (-0.5,)),
                (("ik_time_s",), (0.001,)),
                ((), ()),
            ]
        )
    ]

    def garbage(log: McapLog) -> None:
        for r in bad:
            log.write(RESIDUAL, wire.encode(r), log_time_ns=ns, publish_time_ns=ns)
        for doc in (b"[1, 2]", b'{"position_error_m": "0.3"}', b"not json", b'{"position_error_m": 0.004}'):
            log.write_json(f"{RIG}/arm1/residual", doc, log_time_ns=ns)  # a topic has one encoding

    episode = _episode(tmp_path / "a", residual_m=0.004, more=garbage)
    tracking = score(episode, None, task_median_s=6.0).component("tracking")
    assert tracking.unit == "m"
    assert tracking.raw == pytest.approx(0.004)
    assert "over 601 ticks" in tracking.detail  # 600 typed + 1 old JSON object with an error


# --- weights, degenerate input ------------------------------------------------------------------


def test_weights_come_from_the_rig_qa_config_and_unmeasured_components_give_theirs_away(
    tmp_path: Path,
) -> None:
    weights = QaThresholds.model_validate({"score_weights": {"smoothness": 0, "idle": 0, "tracking": 0}})
    result = score(
        _episode(tmp_path, outcome="failure"), None, task_median_s=3.0, weights=weights.score_weights
    )
    # completion 0.5 (twice the median) weighs 0.15, failure 0 weighs 0.25.
    assert result.total == pytest.approx(0.15 * 0.5 / 0.4)
    only_time = ScoreWeights(smoothness=0, completion_time=1, idle=0, tracking=0, success=0)
    assert (
        score(tmp_path / "episodes" / result.episode_id, None, task_median_s=None, weights=only_time).total
        == 0.0
    )
    with pytest.raises(ValidationError, match="all 0"):
        ScoreWeights(smoothness=0, completion_time=0, idle=0, tracking=0, success=0)


@pytest.mark.parametrize(
    ("name", "kwargs"),
    [
        ("zero-length", {"duration_s": 0.0, "samples": 0}),
        ("single sample", {"samples": 1}),
        ("constant signal", {"path": lambda t: np.ones((len(t), 3))}),
        ("two samples", {"samples": 2}),
        ("no mcap", {"write_mcap": False}),
    ],
)
def test_degenerate_episode_scores_a_finite_number_in_0_1(
    tmp_path: Path, name: str, kwargs: dict[str, object]
) -> None:
    episode = _episode(tmp_path, **kwargs)  # type: ignore[arg-type]
    for report in (None, _report(float("nan")), _report(1.0)):
        for median in (None, 0.0, float("nan"), 6.0):
            result = score(episode, report, task_median_s=median)
            _check_finite(result)
            assert [c.name for c in result.components] == list(COMPONENTS)


def test_constant_signal_is_perfectly_smooth(tmp_path: Path) -> None:
    result = score(_episode(tmp_path, lambda t: np.ones((len(t), 3))), None, task_median_s=None)
    assert result.component("smoothness").raw == 0.0
    assert result.component("smoothness").score == 1.0


def test_missing_manifest_is_one_line_error(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match=r"cannot read .*manifest\.json"):
        score(tmp_path, None, task_median_s=None)


def test_task_medians_use_complete_episodes_per_task(tmp_path: Path) -> None:
    store = EpisodeStore(tmp_path)
    with EpisodeIndex.open(tmp_path) as index:
        for i, (task, seconds) in enumerate([("pick", 4), ("pick", 6), ("pick", 20), ("place", 3)]):
            draft = store.begin(rig="test", task=task, operator="op", start_ns=T0 + i * 10**11)
            index.upsert_episode(draft.commit(end_ns=T0 + i * 10**11 + seconds * 10**9))
        draft = store.begin(rig="test", task="pick", operator="op", start_ns=T0 + 9 * 10**11)
        index.upsert_episode(draft.abandon("operator discarded it", end_ns=T0 + 9 * 10**11 + 10**9))
        medians = task_medians(index.list_episodes())
    assert medians == {"pick": pytest.approx(6.0), "place": pytest.approx(3.0)}


# --- one read of the log for the gates and the score ----------------------------------------------


@pytest.mark.parametrize(
    "kwargs",
    [
        {},
        {"path": _shaky, "offset_rad": 0.3},
        {"residual_m": 0.004},
        {"residual_m": 0.2, "residual_json": True},
        {"samples": 2},
    ],
    ids=["reach", "shaky_offset", "residual", "residual_old_json", "two_samples"],
)
def test_the_score_from_the_gates_read_equals_the_score_from_the_file(
    tmp_path: Path, kwargs: dict[str, object]
) -> None:
    # check_episode scores from the gates' one read of the log (load_episode) instead of reading
    # it again: every component must come out as from the file itself.
    path = _episode(tmp_path, **kwargs)  # type: ignore[arg-type]
    loaded = load_episode(path)
    from_file = score(path, _report(0.1), task_median_s=5.0)
    shared = score(
        path,
        _report(0.1),
        task_median_s=5.0,
        streams=loaded.streams,
        residual_errors=loaded.residual_errors,
    )
    assert shared.to_json() == from_file.to_json()


def test_garbage_residuals_are_left_out_of_the_gates_read_too(tmp_path: Path) -> None:
    ns = T0 + 10**9

    def garbage(log: McapLog) -> None:
        for i, value in enumerate((math.nan, math.inf, 1e308, -0.5)):
            r = RetargetResidual(
                Stamp("arm0", 10_000 + i, ns + i, ns + i), True, ("position_error_m",), (value,)
            )
            log.write(RESIDUAL, wire.encode(r), log_time_ns=ns, publish_time_ns=ns)
        for doc in (b"[1, 2]", b'{"position_error_m": "0.3"}', b"not json", b'{"position_error_m": 0.004}'):
            log.write_json(f"{RIG}/arm1/residual", doc, log_time_ns=ns)

    path = _episode(tmp_path, residual_m=0.004, more=garbage)
    loaded = load_episode(path)
    assert loaded.residual_errors == pytest.approx([0.004] * 601)  # 600 typed + 1 old JSON object
    tracking = score(
        path, None, task_median_s=6.0, streams=loaded.streams, residual_errors=loaded.residual_errors
    ).component("tracking")
    assert tracking.raw == pytest.approx(0.004)
    assert "over 601 ticks" in tracking.detail


@pytest.mark.parametrize(
    ("names", "values", "worst"),
    [
        (("position_error_m", "orientation_error_rad"), (0.01, 3.0), 0.01),
        (("right_wrist_error_m", "left_wrist_error_m", "ik_time_s"), (0.02, 0.05, 9.0), 0.05),
        (("position_error_m", "vector_error_m"), (math.nan, 0.003), 0.003),
        (("position_error_m",), (math.inf,), None),
        (("position_error_m", "vector_error_m"), (-1.0, 2e9), None),
        (("position_error_m",), (1e9,), 1e9),
        (("ik_time_s",), (0.001,), None),
        ((), (), None),
    ],
)
def test_worst_error_is_the_largest_sane_error_metric(
    names: tuple[str, ...], values: tuple[float, ...], worst: float | None
) -> None:
    residual = RetargetResidual(Stamp("arm0", 1, T0, T0), False, names, values)
    assert residual.worst_error_m() == worst
