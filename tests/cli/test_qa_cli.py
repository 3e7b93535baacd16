"""``telerig qa`` on real demo episodes (recorded once for the session by ``telerig run``), on a crafted
failing episode, after a threshold change (--recheck moves episodes to failures and back), and on
hostile input."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

from telerig.cli.main import main
from telerig.config import shipped_rig_path
from telerig.store.episodes import FAILURE_FILE, EpisodeStore
from telerig.store.index import EpisodeIndex
from telerig.store.manifest_extra import EpisodeExtra
from telerig.store.qa_file import QA_FILE, read_qa

pytestmark = [pytest.mark.sim, pytest.mark.broker, pytest.mark.slow]

#: Gates whose verdict on a demo episode does not depend on how loaded the host is (sync and teleop
#: faults do: a starved 2-core machine drops camera frames and trips the watchdog).
_STEADY_GATES = "[joint_limits, calibration_drift, idle, self_collision]"
_LENIENT = f"qa:\n  after_commit: false\n  gates: {_STEADY_GATES}\n  idle_max_fraction: 1.0\n"
#: Every demo episode has idle frames (the start ramp) and some sent-vs-measured offset.
_TIGHT = (
    f"qa:\n  after_commit: false\n  gates: {_STEADY_GATES}\n  idle_max_fraction: 0.0\n  drift_rad: 1.0e-9\n"
)


def _rig(directory: Path, name: str, qa: str) -> Path:
    path = directory / f"{name}.yaml"
    path.write_text(shipped_rig_path("demo").read_text() + "\n" + qa)
    return path


@pytest.fixture(scope="module")
def recorded(demo_recording_unchecked: Path) -> Path:
    """Two 4 s demo episodes recorded by ``telerig run`` with the gates off after commit (the session's
    one demo recording, shared with the export and quality-gate tests)."""
    assert len(EpisodeStore(demo_recording_unchecked).list()) == 2
    return demo_recording_unchecked


@pytest.fixture
def root(recorded: Path, tmp_path: Path) -> Path:
    """A private copy of the recorded data root."""
    return Path(shutil.copytree(recorded, tmp_path / "data"))


def _where(root: Path) -> dict[str, str]:
    return {s.id: s.partition for s in EpisodeStore(root).list(include_failures=True)}


def test_run_with_gates_off_leaves_episodes_unchecked(recorded: Path) -> None:
    store = EpisodeStore(recorded)
    assert all(read_qa(s.path) is None for s in store.list(include_failures=True))


def test_qa_checks_every_unchecked_demo_episode(root: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["qa", "--data-root", str(root)]) == 0
    out = capsys.readouterr().out
    for gate in ("joint_limits", "self_collision", "sync", "idle"):
        assert gate in out
    store = EpisodeStore(root)
    with EpisodeIndex.open(root) as index:
        for summary in store.list(include_failures=True):
            record = read_qa(summary.path)
            assert record is not None
            # The partition follows the verdict; the index holds every verdict and the status.
            assert summary.partition == ("episodes" if record.passed else "failures")
            assert (summary.path / FAILURE_FILE).is_file() == (not record.passed)
            row = index.get(summary.id)
            assert row.status == ("complete" if record.passed else "failed_qa")
            assert row.quality == record.score_total
            assert {v.gate for v in index.verdicts(summary.id)} == {v.gate for v in record.verdicts}
            assert len(record.verdicts) == 8
    assert main(["qa", "--data-root", str(root)]) == 0
    assert "no committed episodes to check" in capsys.readouterr().out


def test_recheck_moves_episodes_to_failures_and_back(root: Path, capsys: pytest.CaptureFixture[str]) -> None:
    lenient, tight = _rig(root.parent, "lenient", _LENIENT), _rig(root.parent, "tight", _TIGHT)
    ids = sorted(_where(root))

    assert main(["qa", "--recheck", "--rig", str(lenient), "--data-root", str(root)]) == 0
    assert _where(root) == dict.fromkeys(ids, "episodes")

    assert main(["qa", "--recheck", "--rig", str(tight), "--data-root", str(root)]) == 0
    assert _where(root) == dict.fromkeys(ids, "failures")
    store = EpisodeStore(root)
    for episode in ids:
        failure = store.failure(episode)
        assert failure is not None
        assert any(r.startswith("idle: ") for r in failure.reasons)
        assert any(r.startswith("calibration_drift: ") for r in failure.reasons)
    with EpisodeIndex.open(root) as index:
        assert {r.id for r in index.list_episodes(status="failed_qa")} == set(ids)
        assert {r.id for r in index.list_episodes(gate="idle", gate_passed=False)} == set(ids)
    out = capsys.readouterr().out
    assert "→ failures" in out
    assert "2 checked, 0 passed, 2 rejected" in out
    assert main(["qa", "--recheck", "--fail-on-reject", "--rig", str(tight), "--data-root", str(root)]) == 3

    assert main(["qa", "--recheck", "--rig", str(lenient), "--data-root", str(root)]) == 0
    assert _where(root) == dict.fromkeys(ids, "episodes")
    assert not any((root / "episodes" / e / FAILURE_FILE).exists() for e in ids)
    with EpisodeIndex.open(root) as index:
        assert index.list_episodes(status="failed_qa") == []
        assert {r.id for r in index.list_episodes(gate="idle", gate_passed=True)} == set(ids)
    # The index is a cache: rebuilt from the partitions and qa.json it says the same.
    with EpisodeIndex.open(root / "rebuilt.sqlite") as rebuilt:
        rebuilt.rebuild(EpisodeStore(root))
        assert {r.id for r in rebuilt.list_episodes(gate_passed=True)} == set(ids)


def _crafted_failure(root: Path) -> str:
    """A copy of a real demo episode whose manifest says three of its control ticks raised."""
    store = EpisodeStore(root)
    source = store.list()[0]
    original = store.get(source.id)
    extra = EpisodeExtra.of(original).model_copy(update={"tick_faults": {"arm0": 3}}).to_json()
    draft = store.begin(rig=original.rig, task=original.task, operator=original.operator, extra=extra)
    shutil.copy(source.path / "episode.mcap", draft.mcap_path)
    draft.commit(extra)
    return draft.id


def test_a_crafted_failing_episode_is_rejected_with_its_reason(
    root: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    lenient = _rig(root.parent, "faults", "qa:\n  gates: [teleop_faults, joint_limits]\n")
    episode = _crafted_failure(root)

    assert main(["qa", episode[:-2], "--rig", str(lenient), "--data-root", str(root)]) == 0

    out = capsys.readouterr().out
    assert f"{episode} → failures" in out
    assert "FAIL" in out
    assert "teleop_faults" in out
    failure = EpisodeStore(root).failure(episode)
    assert failure is not None
    assert any("arm0 3 control tick(s) raised" in r for r in failure.reasons)
    with EpisodeIndex.open(root) as index:
        row = index.get(episode)
        assert row.status == "failed_qa"
        assert row.reason is not None
        assert "control tick(s) raised" in row.reason
        verdicts = {v.gate: v for v in index.verdicts(episode)}
        assert verdicts["teleop_faults"].passed is False
        assert verdicts["joint_limits"].threshold == pytest.approx(0.05)


def test_a_garbage_qa_json_is_checked_again(root: Path, caplog: pytest.LogCaptureFixture) -> None:
    assert main(["qa", "--data-root", str(root)]) == 0
    summary = EpisodeStore(root).list(include_failures=True)[0]
    (summary.path / QA_FILE).write_bytes(b"\x00{not json" + os.urandom(100))

    assert main(["qa", "--data-root", str(root)]) == 0

    assert "is not a quality record" in caplog.text
    again = EpisodeStore(root).find(summary.id)
    record = read_qa(again.path)
    assert record is not None
    assert again.partition == ("episodes" if record.passed else "failures")


@pytest.mark.parametrize("hostile", ["../x", "../../etc/passwd", "ep-1/../../x", "/tmp", "ep-*"])
def test_an_episode_argument_that_is_a_path_is_one_line(
    root: Path, capsys: pytest.CaptureFixture[str], hostile: str
) -> None:
    before = _where(root)
    assert main(["qa", hostile, "--data-root", str(root)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "is not an episode id or id prefix" in err
    assert _where(root) == before


def test_an_unknown_episode_names_the_available_ones(root: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["qa", "ep-19990101", "--data-root", str(root)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "not found" in err
    assert "Available: ep-" in err


def test_a_missing_data_root_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["qa", "--data-root", str(tmp_path / "nowhere")]) == 2
    assert "does not exist" in capsys.readouterr().err
