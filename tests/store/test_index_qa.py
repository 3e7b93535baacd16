"""Index schemas 2 and 3: gate verdicts, the failed_qa status, the outcome label and the migrations
(SQLite and PostgreSQL)."""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import sqlalchemy as sa

from telerig.errors import RecordingError
from telerig.store import index as index_module
from telerig.store.episodes import EpisodeManifest, EpisodeStore, FileEntry
from telerig.store.index import SCHEMA_VERSION, EpisodeIndex
from telerig.store.qa_file import QA_FILE, QaRecord, read_qa, write_qa

_T0 = 1_700_000_000_000_000_000  # 2023-11-14T22:13:20Z [ns]
_S = 1_000_000_000


@pytest.fixture(params=["sqlite", "postgresql"])
def index_url(request: pytest.FixtureRequest, tmp_path: Path) -> str:
    if request.param == "sqlite":
        return str(tmp_path / "root")
    return str(request.getfixturevalue("postgres_url"))


@pytest.fixture
def index(index_url: str) -> Iterator[EpisodeIndex]:
    with EpisodeIndex.open(index_url) as opened:
        yield opened


def _manifest(n: int) -> EpisodeManifest:
    start = _T0 + n * 60 * _S
    return EpisodeManifest(
        id=f"ep-20231114-2213{n:02d}-{n:04x}",
        rig="demo",
        task="pick",
        operator="alice",
        status="complete",
        start_ns=start,
        end_ns=start + 2 * _S,
        duration_s=2.0,
        files=(FileEntry(path="episode.mcap", size=10, sha256="0" * 64),),
    )


def _verdict(gate: str, passed: bool | None, value: float | None, threshold: float) -> dict[str, object]:
    return {
        "gate": gate,
        "passed": passed,
        "value": value,
        "threshold": threshold,
        "unit": "fraction",
        "detail": f"{gate} {value} vs {threshold}",
        "events": [1.25],
    }


def _record(episode_id: str, *, idle: float = 0.2, limits_ok: bool = True, score: float = 0.8) -> QaRecord:
    verdicts = [
        _verdict("joint_limits", limits_ok, 0.01 if limits_ok else 0.2, 0.05),
        _verdict("idle", idle <= 0.6, idle, 0.6),
        _verdict("fall", None, None, 0.5),
    ]
    return QaRecord.model_validate(
        {
            "episode_id": episode_id,
            "checked_ns": time.time_ns(),
            "thresholds_hash": "abc123",
            "report": {"format": 1, "episode_id": episode_id, "idle_fraction": idle, "verdicts": verdicts},
            "score": {"episode": episode_id, "total": score, "components": {}},
        }
    )


def test_a_fresh_index_is_at_schema_5(index: EpisodeIndex) -> None:
    assert SCHEMA_VERSION == 5
    assert index.schema_version == 5


def test_record_qa_stores_every_verdict_status_and_score(index: EpisodeIndex, tmp_path: Path) -> None:
    m = _manifest(1)
    index.upsert_episode(m, location=tmp_path / "episodes" / m.id)
    failures = tmp_path / "failures" / m.id
    record = _record(m.id, idle=0.9)

    row = index.record_qa(record, status="failed_qa", reason="; ".join(record.reasons), location=failures)

    assert row.status == "failed_qa"
    assert row.quality == pytest.approx(0.8)
    assert row.location == str(failures.resolve())
    assert row.reason == "idle: idle 0.9 vs 0.6"
    stored = {v.gate: v for v in index.verdicts(m.id)}
    assert set(stored) == {"joint_limits", "idle", "fall"}
    assert stored["idle"].passed is False
    assert stored["idle"].value == pytest.approx(0.9)
    assert stored["idle"].threshold == pytest.approx(0.6)
    assert stored["idle"].unit == "fraction"
    assert stored["idle"].thresholds_hash == "abc123"
    assert stored["fall"].passed is None
    assert stored["fall"].value is None


def test_record_qa_replaces_the_previous_verdicts(index: EpisodeIndex) -> None:
    m = _manifest(1)
    index.upsert_episode(m)
    index.record_qa(_record(m.id, idle=0.9), status="failed_qa")
    row = index.record_qa(_record(m.id, idle=0.1, score=0.9), status="complete")
    assert row.status == "complete"
    assert row.quality == pytest.approx(0.9)
    assert {v.gate: v.passed for v in index.verdicts(m.id)}["idle"] is True
    assert len(index.verdicts(m.id)) == 3


def test_record_qa_keeps_an_uploaded_location(index: EpisodeIndex, tmp_path: Path) -> None:
    m = _manifest(1)
    index.upsert_episode(m, location="s3://bucket/eps/" + m.id)
    row = index.record_qa(_record(m.id), status="complete", location=tmp_path / "episodes" / m.id)
    assert row.location == "s3://bucket/eps/" + m.id


def test_record_qa_of_an_unindexed_episode_is_refused(index: EpisodeIndex) -> None:
    with pytest.raises(RecordingError, match="is not in the index"):
        index.record_qa(_record(_manifest(1).id), status="complete")


def test_list_filters_by_gate_and_verdict(index: EpisodeIndex) -> None:
    ok, idle, limits, unchecked = (_manifest(n) for n in range(1, 5))
    for m in (ok, idle, limits, unchecked):
        index.upsert_episode(m)
    index.record_qa(_record(ok.id), status="complete")
    index.record_qa(_record(idle.id, idle=0.9), status="failed_qa")
    index.record_qa(_record(limits.id, limits_ok=False), status="failed_qa")

    def ids(**kw: object) -> list[str]:
        return [r.id for r in index.list_episodes(**kw)]  # type: ignore[arg-type]

    assert ids(gate="idle", gate_passed=False) == [idle.id]
    assert ids(gate="idle", gate_passed=True) == [ok.id, limits.id]
    assert ids(gate="idle") == [ok.id, idle.id, limits.id]
    assert ids(gate_passed=False) == [idle.id, limits.id]
    assert ids(gate_passed=True) == [ok.id]
    assert ids(status="failed_qa") == [idle.id, limits.id]
    assert ids(gate="fall", gate_passed=False) == []


def test_rebuild_reads_partitions_and_qa_files(index: EpisodeIndex, tmp_path: Path) -> None:
    store = EpisodeStore(tmp_path / "data")
    ids = []
    for n in range(2):
        draft = store.begin(rig="demo", task="pick", operator="alice", start_ns=_T0 + n * _S)
        draft.mcap_path.write_bytes(b"x")
        draft.commit()
        ids.append(draft.id)
    kept, failed = ids
    write_qa(store.episode_dir(kept), _record(kept, score=0.7))
    write_qa(store.episode_dir(failed), _record(failed, idle=0.95, score=0.3))
    store.move_to_failures(failed, _record(failed, idle=0.95).reasons)

    index.rebuild(store)

    assert index.get(kept).status == "complete"
    assert index.get(kept).quality == pytest.approx(0.7)
    row = index.get(failed)
    assert row.status == "failed_qa"
    assert row.reason == "idle: idle 0.95 vs 0.6"
    assert row.location == str((tmp_path / "data" / "failures" / failed).resolve())
    assert [r.id for r in index.list_episodes(gate="idle", gate_passed=False)] == [failed]

    store.restore_from_failures(failed)
    write_qa(store.episode_dir(failed), _record(failed, idle=0.1, score=0.9))
    index.rebuild(store)
    assert index.get(failed).status == "complete"
    assert index.list_episodes(gate_passed=False) == []


def test_rebuild_removes_the_verdicts_of_a_vanished_episode(index: EpisodeIndex, tmp_path: Path) -> None:
    store = EpisodeStore(tmp_path / "data")
    draft = store.begin(rig="demo", task="pick", operator="alice", start_ns=_T0)
    draft.commit()
    write_qa(draft.dir, _record(draft.id))
    index.rebuild(store)
    assert len(index.verdicts(draft.id)) == 3
    import shutil

    shutil.rmtree(draft.dir)
    assert index.rebuild(store).removed == 1
    assert index.verdicts(draft.id) == []


def test_rebuild_skips_a_garbage_qa_json_with_a_warning(
    index: EpisodeIndex, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    store = EpisodeStore(tmp_path / "data")
    draft = store.begin(rig="demo", task="pick", operator="alice", start_ns=_T0)
    draft.commit()
    (draft.dir / QA_FILE).write_bytes(b'{"format": 1, "episode_id": "ep-\x00' + os.urandom(32))
    assert index.rebuild(store).indexed == 1
    assert index.verdicts(draft.id) == []
    assert "is not a quality record" in caplog.text


# -- qa.json ----------------------------------------------------------------------------------


def test_qa_json_round_trips(tmp_path: Path) -> None:
    directory = tmp_path / "ep-20231114-221301-0001"
    directory.mkdir()
    record = _record(directory.name, idle=0.9)
    write_qa(directory, record)
    again = read_qa(directory)
    assert again == record
    assert again is not None
    assert again.passed is False
    assert again.reasons == ("idle: idle 0.9 vs 0.6",)
    assert not (directory / (QA_FILE + ".tmp")).exists()


_HEAD = b'{"format": 1, "episode_id": "E", "checked_ns": 1, "thresholds_hash": "h", '


@pytest.mark.parametrize(
    "content",
    [
        b"\xff\xfe garbage",
        b"[]",
        b'{"format": 1}',
        _HEAD.replace(b'"format": 1', b'"format": 7') + b'"report": {"verdicts": []}}',
        _HEAD + b'"report": {"verdicts": 3}}',
        _HEAD + b'"report": {"verdicts": []}, "score": {"total": 7}}',
    ],
)
def test_a_garbage_qa_json_is_one_line(tmp_path: Path, content: bytes) -> None:
    directory = tmp_path / "E"
    directory.mkdir()
    (directory / QA_FILE).write_bytes(content)
    with pytest.raises(RecordingError, match="is not a quality record") as info:
        read_qa(directory)
    assert "\n" not in str(info.value)


def test_a_qa_json_of_another_episode_is_refused(tmp_path: Path) -> None:
    directory = tmp_path / "ep-20231114-221301-0001"
    directory.mkdir()
    write_qa(directory, _record("ep-20231114-221302-0002"))
    with pytest.raises(RecordingError, match="belongs to episode"):
        read_qa(directory)


# -- migration --------------------------------------------------------------------------------


def _create_v1(url: str) -> None:
    """A version-1 index as telerig wrote it before issue 13 (no gate_verdicts table), with one episode."""
    engine = index_module._create_engine(index_module._database_url(url))
    try:
        with engine.begin() as conn:
            for table in index_module._metadata.sorted_tables:
                if table.name not in ("gate_verdicts", "processed_clips"):  # added by versions 2 and 4
                    table.create(conn)
            conn.execute(sa.text("ALTER TABLE episodes DROP COLUMN outcome"))  # added by version 3
            conn.execute(sa.text("ALTER TABLE episodes DROP COLUMN instructions"))  # added by version 5
            conn.execute(sa.text("INSERT INTO schema_version (version, applied_ns) VALUES (1, 0)"))
            conn.execute(sa.text("INSERT INTO operators (id, created_ns, updated_ns) VALUES ('alice', 0, 0)"))
            conn.execute(
                sa.text(
                    "INSERT INTO episodes (id, task, operator, rig, robots, start_ns, size_bytes, status,"
                    " created_ns, updated_ns) VALUES"
                    " ('ep-20231114-221301-0001', 'pick', 'alice', 'demo', '[]', 1, 10, 'complete', 0, 0)"
                )
            )
    finally:
        engine.dispose()


def test_a_version_1_index_migrates_to_5_keeping_its_episodes(index_url: str) -> None:
    _create_v1(index_url)
    with EpisodeIndex.open(index_url) as migrated:
        assert migrated.schema_version == 5
        assert [r.id for r in migrated.list_episodes()] == ["ep-20231114-221301-0001"]
        tables = set(sa.inspect(migrated._engine).get_table_names())
        assert "gate_verdicts" in tables
        assert "processed_clips" in tables
        assert "outcome" in {c["name"] for c in sa.inspect(migrated._engine).get_columns("episodes")}
        assert migrated.set_outcome("ep-20231114-221301-0001", "success").outcome == "success"
        assert [r.id for r in migrated.list_episodes(outcome="failure")] == []
        row = migrated.record_qa(_record("ep-20231114-221301-0001", idle=0.9), status="failed_qa")
        assert row.status == "failed_qa"
        assert len(migrated.verdicts("ep-20231114-221301-0001")) == 3
    with EpisodeIndex.open(index_url) as again:  # migrating is done once
        assert again.schema_version == 5
        assert len(again.verdicts()) == 3
