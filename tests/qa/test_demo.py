"""The gates on real episodes of the shipped demo rig (scripted operator, simulated UR5e + camera)."""

from __future__ import annotations

from pathlib import Path

import pytest
from pydantic import JsonValue

from telerig.config.qa import QaThresholds
from telerig.qa import QaReport, evaluate
from telerig.store.episodes import EpisodeManifest
from telerig.store.manifest_extra import EpisodeExtra

pytestmark = pytest.mark.sim

DEFAULT = QaThresholds()


def _episodes(root: Path) -> list[Path]:
    """Committed episodes of a data root, accepted or moved to failures by the gates after commit."""
    return sorted(
        p for part in ("episodes", "failures") if (root / part).is_dir() for p in (root / part).iterdir()
    )


@pytest.fixture(scope="module")
def demo_reports(demo_recording: Path) -> list[tuple[Path, QaReport]]:
    episodes = _episodes(demo_recording)
    assert episodes, f"the demo recorded no episode in {demo_recording}"
    return [(e, evaluate(e, DEFAULT)) for e in episodes]


@pytest.mark.parametrize(
    "gate", ["self_collision", "joint_limits", "calibration_drift", "idle", "force_spike"]
)
def test_demo_episode_passes(demo_reports: list[tuple[Path, QaReport]], gate: str) -> None:
    for _, report in demo_reports:
        verdict = report.verdict(gate)
        assert verdict is not None
        assert verdict.passed is True, verdict


def test_demo_fixed_arm_cannot_fall(demo_reports: list[tuple[Path, QaReport]]) -> None:
    for _, report in demo_reports:
        verdict = report.verdict("fall")
        assert verdict is not None
        assert verdict.passed is None
        assert "nothing can fall" in verdict.detail


def test_demo_sync_verdict_follows_the_recorded_stream_statistics(
    demo_reports: list[tuple[Path, QaReport]],
) -> None:
    # A loaded host can make the demo lose camera frames or pause a stream: the gate must then say
    # so (it is not clean), and pass when the recorder saw nothing wrong.
    for path, report in demo_reports:
        extra = EpisodeExtra.of(EpisodeManifest.model_validate_json((path / "manifest.json").read_bytes()))
        # Requested commands carry their input's stamp: their seq gaps are skipped inputs, not losses.
        measured = [
            s
            for s in extra.streams
            if _f(s.get("expected_hz")) > 0 and not str(s.get("name")).endswith("_requested")
        ]
        losses = [_loss(s) for s in measured]
        gaps = [_f(s.get("max_gap_ms")) for s in measured]
        verdict = report.verdict("sync")
        assert verdict is not None
        assert verdict.value is not None
        assert verdict.value >= max(losses) - 1e-9
        if max(losses) <= DEFAULT.max_missing_fraction and max(gaps) <= DEFAULT.max_gap_ms:
            assert verdict.passed is True or "camera frames" in verdict.detail, verdict
        else:
            assert verdict.passed is False


def test_demo_report_is_fast_enough_to_run_after_every_commit(demo_recording: Path) -> None:
    import time

    episode = _episodes(demo_recording)[0]
    evaluate(episode, DEFAULT)  # robot models built and cached
    start = time.perf_counter()
    report = evaluate(episode, DEFAULT)
    took = time.perf_counter() - start
    duration = EpisodeManifest.model_validate_json((episode / "manifest.json").read_bytes()).duration_s
    assert duration is not None
    print(
        f"gates: {took:.3f} s for a {duration:.1f} s episode "
        f"({took / duration * 60:.1f} s per episode-minute)"
    )
    assert report.verdicts


def _f(value: JsonValue) -> float:
    return float(value) if isinstance(value, int | float) else 0.0


def _loss(s: dict[str, JsonValue]) -> float:
    messages, drops = _f(s.get("messages")), _f(s.get("drops"))
    rate = 1.0 - _f(s.get("measured_hz")) / _f(s.get("expected_hz"))
    return max(drops / (messages + drops) if messages + drops else 1.0, rate)
