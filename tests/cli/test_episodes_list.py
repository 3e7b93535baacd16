"""``telerig episodes list``: every filter and sort key on a real index holding several episodes, the
data-root path (manifests and qa.json read back), and one-line errors for bad filter values."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest

from telerig.cli.main import main
from telerig.qa.report import GateVerdict, QaReport
from telerig.store.episodes import EpisodeManifest, EpisodeStore, FileEntry
from telerig.store.index import EpisodeIndex
from telerig.store.manifest_extra import EpisodeExtra
from telerig.store.qa_file import QaRecord, write_qa

_DAY0 = 1_795_600_000_000_000_000  # 2026-11-25T09:46:40Z [ns]
_S = 1_000_000_000
_H = 3600 * _S

# id suffix, task, operator, robots, status, start offset [ns], duration [s], score, failed gate
_EPISODES = [
    ("a001", "pick", "ana", ["ur5e_robotiq85"], "complete", 0, 6.0, 0.91, None),
    ("a002", "pick", "bob", ["ur5e_robotiq85"], "complete", 1 * _H, 9.0, 0.55, "idle"),
    ("a003", "place", "ana", ["ur5e_robotiq85", "allegro_right"], "complete", 2 * _H, 5.0, 0.72, None),
    ("a004", "fold", "cai", ["g1"], "incomplete", 26 * _H, 3.0, None, None),
    ("a005", "pick", "ana", ["g1"], "complete", 50 * _H, 7.0, 0.33, "sync"),
]


def _id(suffix: str, offset_ns: int) -> str:
    stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime((_DAY0 + offset_ns) / 1e9))
    return f"ep-{stamp}-{suffix}"


def _report(episode_id: str, failed: str | None) -> QaReport:
    verdicts = tuple(
        GateVerdict(gate, gate != failed, 0.1, 0.5, "fraction", "synthetic", (1.0,) if gate == failed else ())
        for gate in ("sync", "idle")
    )
    return QaReport(episode_id, verdicts, 0.2)


@pytest.fixture
def index_file(tmp_path: Path) -> Path:
    """An index database with the five episodes above; all but the incomplete one checked by the gates."""
    path = tmp_path / "index.sqlite"
    with EpisodeIndex.open(path) as index:
        for suffix, task, operator, robots, status, offset, seconds, _score, failed in _EPISODES:
            start = _DAY0 + offset
            manifest = EpisodeManifest(
                id=_id(suffix, offset),
                rig="demo",
                task=task,
                operator=operator,
                status=status,  # type: ignore[arg-type]
                start_ns=start,
                end_ns=start + round(seconds * _S),
                duration_s=seconds,
                reason="operator discarded it" if status == "incomplete" else None,
                files=(FileEntry(path="episode.mcap", size=1_000_000, sha256="0" * 64),),
                extra=EpisodeExtra(robots=robots).to_json(),
            )
            index.upsert_episode(manifest, location=tmp_path / manifest.id)
            if status == "complete":
                record = QaRecord(
                    episode_id=manifest.id,
                    checked_ns=start,
                    thresholds_hash="t",
                    report=_report(manifest.id, failed).to_json(),
                    score={"total": _score},
                )
                index.record_qa(record, status="failed_qa" if failed else "complete")
    return path


def _ids(capsys: pytest.CaptureFixture[str], index_file: Path, *args: str) -> list[str]:
    assert main(["episodes", "list", "--index", str(index_file), "--json", *args]) == 0
    return [row["id"][-4:] for row in json.loads(capsys.readouterr().out)]


def test_default_lists_committed_episodes_oldest_first(
    index_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert _ids(capsys, index_file) == ["a001", "a002", "a003", "a005"]
    assert _ids(capsys, index_file, "--all") == ["a001", "a002", "a003", "a004", "a005"]


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (["--task", "pick"], ["a001", "a002", "a005"]),
        (["--operator", "ana"], ["a001", "a003", "a005"]),
        (["--robot", "allegro_right"], ["a003"]),
        (["--robot", "g1", "--all"], ["a004", "a005"]),
        (["--status", "failed_qa"], ["a002", "a005"]),
        (["--status", "complete,incomplete"], ["a001", "a003", "a004"]),
        (["--status", "complete", "--status", "incomplete"], ["a001", "a003", "a004"]),
        (["--gate", "failed"], ["a002", "a005"]),
        (["--gate", "passed"], ["a001", "a003"]),
        (["--gate", "idle=failed"], ["a002"]),
        (["--gate", "sync=passed"], ["a001", "a002", "a003"]),
        (["--min-score", "0.7"], ["a001", "a003"]),
        (["--max-score", "0.6", "--all"], ["a002", "a005"]),
        (["--min-score", "0.5", "--max-score", "0.8"], ["a002", "a003"]),
        (["--since", "2026-11-26", "--all"], ["a004", "a005"]),
        (["--until", "2026-11-25"], ["a001", "a002", "a003"]),
        (
            ["--since", "2026-11-25T10:00", "--until", "2026-11-26T14:00+02:00", "--all"],
            ["a002", "a003", "a004"],
        ),
        (["--task", "pick", "--operator", "ana", "--gate", "passed"], ["a001"]),
    ],
)
def test_filters(
    index_file: Path, capsys: pytest.CaptureFixture[str], args: list[str], expected: list[str]
) -> None:
    assert _ids(capsys, index_file, *args) == expected


@pytest.mark.parametrize(
    ("sort", "expected"),
    [
        ("-date", ["a005", "a003", "a002", "a001"]),
        ("-score", ["a001", "a003", "a002", "a005"]),
        ("duration", ["a003", "a001", "a005", "a002"]),
        ("task", ["a001", "a002", "a005", "a003"]),
        ("-operator", ["a002", "a005", "a003", "a001"]),  # ties: later id first
        ("status", ["a001", "a003", "a002", "a005"]),
    ],
)
def test_sort(index_file: Path, capsys: pytest.CaptureFixture[str], sort: str, expected: list[str]) -> None:
    assert _ids(capsys, index_file, f"--sort={sort}") == expected


def test_limit_takes_the_first_after_sorting(index_file: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert _ids(capsys, index_file, "--sort=-score", "--limit", "2") == ["a001", "a003"]


def test_table_shows_score_gates_and_robots(index_file: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["episodes", "list", "--index", str(index_file), "--task", "pick"]) == 0
    rows = {
        line.split("│")[1].strip()[-4:]: line
        for line in capsys.readouterr().out.splitlines()
        if "│ ep-" in line
    }
    assert set(rows) == {"a001", "a002", "a005"}
    assert "0.91" in rows["a001"]
    assert "passed" in rows["a001"]
    assert "failed: idle" in rows["a002"]
    assert "failed_qa" in rows["a002"]
    assert "g1" in rows["a005"]
    assert "2026-11-27" in rows["a005"]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--status", "done"], "--status 'done' is not an episode status. Available: complete"),
        (["--gate", "wobble"], "'wobble' is not a quality gate. Available: fall"),
        (["--gate", "idle=maybe"], "the result after '=' must be passed or failed"),
        (["--min-score", "1.5"], "--min-score '1.5' is not a score: give a number in [0, 1]"),
        (["--max-score", "high"], "--max-score 'high' is not a score"),
        (["--min-score", "0.8", "--max-score", "0.2"], "--min-score 0.8 is above --max-score 0.2"),
        (["--since", "yesterday"], "--since 'yesterday' is not a date: give YYYY-MM-DD"),
        (["--until", "2026-13-01"], "--until '2026-13-01' is not a date"),
        (["--sort", "colour"], "--sort 'colour' is not a sort key. Available: date, duration"),
        (["--limit", "0"], "--limit '0' is not a count"),
    ],
)
def test_bad_filter_value_is_one_line_error(
    index_file: Path, capsys: pytest.CaptureFixture[str], args: list[str], message: str
) -> None:
    assert main(["episodes", "list", "--index", str(index_file), *args]) == 2
    captured = capsys.readouterr()
    err = captured.err.strip()
    assert len(err.splitlines()) == 1, err
    assert message in err
    assert captured.out == ""


def test_data_root_is_read_from_manifests_and_qa_files(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    store = EpisodeStore(tmp_path)
    ids = []
    for i, (task, failed) in enumerate([("pick", None), ("pick", "idle"), ("place", None)]):
        draft = store.begin(rig="demo", task=task, operator="ana", start_ns=_DAY0 + i * _H)
        draft.mcap_path.write_bytes(b"x")
        extra = EpisodeExtra(robots=["ur5e_robotiq85"]).to_json()
        manifest = draft.commit(extra, end_ns=_DAY0 + i * _H + 5 * _S)
        report = _report(manifest.id, failed).to_json()
        score = {"total": 0.5 + 0.1 * i}
        write_qa(
            draft.dir,
            QaRecord(episode_id=manifest.id, checked_ns=0, thresholds_hash="t", report=report, score=score),
        )
        ids.append(manifest.id)
    assert main(["episodes", "list", "--data-root", str(tmp_path), "--gate", "idle=failed", "--json"]) == 0
    (row,) = json.loads(capsys.readouterr().out)
    assert row["id"] == ids[1]
    assert row["score"] == pytest.approx(0.6)
    assert row["gates"] == {"idle": False, "sync": True}
    args = ["--data-root", str(tmp_path), "--min-score", "0.55", "--task", "place", "--json"]
    assert main(["episodes", "list", *args]) == 0
    assert [r["id"] for r in json.loads(capsys.readouterr().out)] == [ids[2]]
    assert not (tmp_path / "index.sqlite").exists()  # listing never writes an index into the data root
