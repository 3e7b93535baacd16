"""Episode index: the same suite over SQLite and a real PostgreSQL 15 on 127.0.0.1."""

from __future__ import annotations

import shutil
import threading
from collections.abc import Iterator, Mapping
from pathlib import Path

import pytest
import sqlalchemy as sa

from telerig.config import load_rig
from telerig.errors import ConfigError, RecordingError
from telerig.store import index as index_module
from telerig.store.episodes import EpisodeManifest, EpisodeStore, FileEntry
from telerig.store.fingerprint import rig_fingerprint
from telerig.store.index import SCHEMA_VERSION, EpisodeIndex
from telerig.store.manifest_extra import EpisodeExtra, FingerprintRecord

_T0 = 1_700_000_000_000_000_000  # 2023-11-14T22:13:20Z [ns]
_S = 1_000_000_000  # 1 s [ns]


@pytest.fixture(params=["sqlite", "postgresql"])
def index_url(request: pytest.FixtureRequest, tmp_path: Path) -> str:
    """An empty index database: an SQLite file under tmp_path, or a fresh PostgreSQL database."""
    if request.param == "sqlite":
        return str(tmp_path / "root")
    return str(request.getfixturevalue("postgres_url"))


@pytest.fixture
def index(index_url: str) -> Iterator[EpisodeIndex]:
    """An open index on :func:`index_url`, closed at teardown."""
    with EpisodeIndex.open(index_url) as opened:
        yield opened


def _manifest(
    n: int,
    *,
    task: str = "pick",
    operator: str = "alice",
    status: str = "complete",
    extra: Mapping[str, object] | None = None,
    size: int = 100,
) -> EpisodeManifest:
    start = _T0 + n * 60 * _S
    return EpisodeManifest.model_validate(
        {
            "id": f"ep-20231114-2213{n:02d}-{n:04x}",
            "rig": "demo",
            "task": task,
            "operator": operator,
            "status": status,
            "start_ns": start,
            "end_ns": None if status == "recording" else start + 2 * _S,
            "duration_s": None if status == "recording" else 2.0,
            "reason": "disk full" if status == "incomplete" else None,
            "files": [FileEntry(path="episode.mcap", size=size, sha256="0" * 64)],
            "extra": extra or {},
        }
    )


def test_open_creates_the_schema_and_reopens(index_url: str) -> None:
    with EpisodeIndex.open(index_url) as first:
        assert first.schema_version == SCHEMA_VERSION
        first.upsert_episode(_manifest(1))
    with EpisodeIndex.open(index_url) as again:
        assert again.schema_version == SCHEMA_VERSION
        assert again.count_episodes() == 1


def test_upsert_takes_fields_from_the_manifest(index: EpisodeIndex, tmp_path: Path) -> None:
    # The extra section as the runtime writes it (issue 11 finding 8: this test once built it by hand
    # under keys the runtime never wrote, and the fingerprint column stayed NULL for real episodes).
    fingerprint = rig_fingerprint(load_rig("demo"))
    extra = EpisodeExtra(
        robots=["ur5e", "panda"],
        session_id="s-1",
        fingerprint=FingerprintRecord(digest=fingerprint.digest, components=dict(fingerprint.components)),
        quality=0.75,
    ).to_json()
    record = index.upsert_episode(_manifest(1, extra=extra, size=1234), location=tmp_path / "ep")

    assert (record.task, record.operator, record.rig, record.status) == ("pick", "alice", "demo", "complete")
    assert record.robots == ("ur5e", "panda")
    assert (record.session, record.fingerprint, record.quality) == ("s-1", fingerprint.digest, 0.75)
    assert (record.start_ns, record.end_ns, record.duration_s) == (_T0 + 60 * _S, _T0 + 62 * _S, 2.0)
    assert record.size_bytes == 1234
    assert record.location == str((tmp_path / "ep").resolve())
    assert index.get(record.id) == record
    assert [o.id for o in index.operators()] == ["alice"]
    assert [s.id for s in index.sessions()] == ["s-1"]


def test_upsert_twice_is_idempotent(index: EpisodeIndex) -> None:
    first = index.upsert_episode(_manifest(1), location="s3://bucket/ep1")
    second = index.upsert_episode(_manifest(1), location="s3://bucket/ep1")
    assert second == first
    assert index.count_episodes() == 1


def test_upsert_with_a_change_updates_only_updated_ns(index: EpisodeIndex) -> None:
    first = index.upsert_episode(_manifest(1))
    second = index.upsert_episode(_manifest(1, task="place"))
    assert second.task == "place"
    assert second.created_ns == first.created_ns
    assert second.updated_ns > first.updated_ns


def test_upsert_without_location_or_quality_keeps_the_stored_ones(index: EpisodeIndex) -> None:
    index.upsert_episode(_manifest(1), location="s3://bucket/ep1")
    index.set_quality(_manifest(1).id, 0.4)
    record = index.upsert_episode(_manifest(1))
    assert (record.location, record.quality) == ("s3://bucket/ep1", 0.4)


def test_recording_manifest_is_indexed_as_interrupted(index: EpisodeIndex) -> None:
    assert index.upsert_episode(_manifest(1, status="recording")).status == "interrupted"


def test_list_filters(index: EpisodeIndex) -> None:
    index.upsert_episodes(
        [
            _manifest(1, task="pick", operator="alice"),
            _manifest(2, task="place", operator="alice", extra={"session_id": "s-2"}),
            _manifest(3, task="pick", operator="bob", status="incomplete"),
            _manifest(4, task="pick", operator="bob", status="recording"),
        ]
    )
    ids = {n: _manifest(n).id for n in range(1, 5)}

    def listed(**filters: object) -> list[str]:
        return [r.id for r in index.list_episodes(**filters)]  # type: ignore[arg-type]

    assert listed() == [ids[1], ids[2], ids[3], ids[4]]
    assert listed(task="pick") == [ids[1], ids[3], ids[4]]
    assert listed(operator="bob", task="pick") == [ids[3], ids[4]]
    assert listed(status="complete") == [ids[1], ids[2]]
    assert listed(status=["incomplete", "interrupted"]) == [ids[3], ids[4]]
    assert listed(session="s-2") == [ids[2]]
    assert listed(since_ns=_manifest(2).start_ns) == [ids[2], ids[3], ids[4]]
    assert listed(since_ns=_manifest(2).start_ns, until_ns=_manifest(4).start_ns) == [ids[2], ids[3]]
    assert listed(rig="other") == []


def test_list_order_limit_and_offset(index: EpisodeIndex) -> None:
    index.upsert_episodes([_manifest(n, size=10 * n) for n in range(1, 6)])
    ids = [_manifest(n).id for n in range(1, 6)]
    assert [r.id for r in index.list_episodes(order="-start", limit=2)] == [ids[4], ids[3]]
    assert [r.id for r in index.list_episodes(order="start", limit=2, offset=2)] == [ids[2], ids[3]]
    assert [r.id for r in index.list_episodes(order="-size", limit=1)] == [ids[4]]


def test_unscored_quality_sorts_last_both_ways(index: EpisodeIndex) -> None:
    index.upsert_episodes(
        [_manifest(1, extra={"quality": 0.2}), _manifest(2), _manifest(3, extra={"quality": 0.9})]
    )
    ids = [_manifest(n).id for n in (1, 2, 3)]
    assert [r.id for r in index.list_episodes(order="quality")] == [ids[0], ids[2], ids[1]]
    assert [r.id for r in index.list_episodes(order="-quality")] == [ids[2], ids[0], ids[1]]


def test_list_rejects_an_unknown_order_naming_the_available_ones(index: EpisodeIndex) -> None:
    available = "Available: duration, operator, quality, size, start, status, task, updated"
    with pytest.raises(ValueError, match=available):
        index.list_episodes(order="name")  # type: ignore[arg-type]


def test_get_by_unique_prefix(index: EpisodeIndex) -> None:
    index.upsert_episodes([_manifest(1), _manifest(2)])
    assert index.get("ep-20231114-221301").id == _manifest(1).id


def test_get_with_an_ambiguous_prefix_lists_candidates(index: EpisodeIndex) -> None:
    index.upsert_episodes([_manifest(1), _manifest(2)])
    with pytest.raises(RecordingError, match="ambiguous: ep-20231114-221301-0001, ep-20231114-221302-0002"):
        index.get("ep-2023")


def test_get_missing_names_recent_episodes(index: EpisodeIndex) -> None:
    index.upsert_episode(_manifest(1))
    with pytest.raises(RecordingError, match=f"not in the index .*Recent: {_manifest(1).id}"):
        index.get("ep-1999")


def test_setters_change_one_field(index: EpisodeIndex) -> None:
    episode_id = index.upsert_episode(_manifest(1)).id
    assert index.set_status(episode_id, "repaired", reason="truncated at 1.2 s").status == "repaired"
    assert index.get(episode_id).reason == "truncated at 1.2 s"
    assert index.set_location(episode_id, "s3://bucket/x").location == "s3://bucket/x"
    assert index.set_quality(episode_id, 0.5).quality == 0.5
    assert index.set_quality(episode_id, None).quality is None


def test_setters_reject_an_unknown_episode(index: EpisodeIndex) -> None:
    with pytest.raises(RecordingError, match="upsert it"):
        index.set_status("ep-nope", "complete")


@pytest.mark.parametrize("quality", [-0.1, 1.5, float("nan")])
def test_set_quality_rejects_values_outside_0_1(index: EpisodeIndex, quality: float) -> None:
    episode_id = index.upsert_episode(_manifest(1)).id
    with pytest.raises(ValueError, match="quality must be"):
        index.set_quality(episode_id, quality)


def test_set_status_rejects_an_unknown_status(index: EpisodeIndex) -> None:
    episode_id = index.upsert_episode(_manifest(1)).id
    with pytest.raises(ValueError, match="Available: complete, incomplete, interrupted, repaired"):
        index.set_status(episode_id, "lost")  # type: ignore[arg-type]


def test_operator_device_session_upserts_keep_unset_fields(index: EpisodeIndex) -> None:
    index.upsert_operator("alice", name="Alice", extra={"hand": "right"})
    assert index.upsert_operator("alice").name == "Alice"
    index.upsert_device("quest-1", kind="vr", station="st-a", serial="Q123")
    device = index.upsert_device("quest-1", station="st-b")
    assert (device.kind, device.station, device.serial) == ("vr", "st-b", "Q123")
    index.upsert_session("s-1", rig="demo", operator="bob", start_ns=_T0, extra={"stations": ["a", "b"]})
    session = index.upsert_session("s-1", end_ns=_T0 + 60 * _S)
    assert (session.rig, session.operator, session.start_ns, session.end_ns) == (
        "demo",
        "bob",
        _T0,
        _T0 + 60 * _S,
    )
    assert session.extra == {"stations": ["a", "b"]}
    assert [o.id for o in index.operators()] == ["alice", "bob"]
    assert [d.id for d in index.devices(station="st-b")] == ["quest-1"]


def _filled_store(root: Path) -> tuple[EpisodeStore, list[str]]:
    store = EpisodeStore(root)
    ids = []
    for n in range(3):
        draft = store.begin(rig="demo", task="pick", operator="alice", start_ns=_T0 + n * _S)
        draft.mcap_path.write_bytes(b"x" * 10)
        if n == 0:
            draft.commit({"robots": ["ur5e"], "quality": 0.9}, end_ns=_T0 + 2 * _S)
        elif n == 1:
            draft.abandon("disk full", end_ns=_T0 + 3 * _S)
        ids.append(draft.id)  # n == 2 stays a draft: interrupted
    return store, ids


def test_rebuild_indexes_every_episode_on_disk(index: EpisodeIndex, tmp_path: Path) -> None:
    store, ids = _filled_store(tmp_path / "data")
    result = index.rebuild(store)
    assert (result.indexed, result.removed, result.skipped) == (3, 0, 0)
    records = {r.id: r for r in index.list_episodes()}
    assert [records[i].status for i in ids] == ["complete", "incomplete", "interrupted"]
    assert records[ids[0]].robots == ("ur5e",)
    assert records[ids[0]].quality == 0.9
    assert records[ids[1]].reason == "disk full"
    assert records[ids[2]].size_bytes == 10 + len(
        (tmp_path / "data/.incoming" / ids[2] / "manifest.json").read_bytes()
    )
    assert records[ids[0]].location == str((tmp_path / "data/episodes" / ids[0]).resolve())


def test_rebuild_removes_rows_whose_directory_is_gone_and_keeps_others(
    index: EpisodeIndex, tmp_path: Path
) -> None:
    store, ids = _filled_store(tmp_path / "data")
    index.rebuild(store)
    index.upsert_episode(_manifest(9), location="s3://bucket/ep9")  # uploaded, not local
    shutil.rmtree(tmp_path / "data/incomplete" / ids[1])

    result = index.rebuild(store)

    assert (result.indexed, result.removed) == (2, 1)
    assert {r.id for r in index.list_episodes()} == {ids[0], ids[2], _manifest(9).id}


def test_rebuild_is_idempotent(index: EpisodeIndex, tmp_path: Path) -> None:
    store, _ = _filled_store(tmp_path / "data")
    index.rebuild(store)
    before = index.list_episodes()
    index.rebuild(store)
    assert index.list_episodes() == before


def test_concurrent_stations_upsert_the_same_episodes(index_url: str) -> None:
    manifests = [_manifest(n, operator=f"op{n % 3}") for n in range(20)]
    errors: list[BaseException] = []

    def station(k: int) -> None:
        try:
            with EpisodeIndex.open(index_url) as own:
                for m in manifests[k:] + manifests[:k]:
                    own.upsert_episode(m, location=f"s3://bucket/{m.id}")
                own.upsert_operator("op0", name="shared")
        except BaseException as exc:  # reported below
            errors.append(exc)

    threads = [threading.Thread(target=station, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()

    assert errors == []
    with EpisodeIndex.open(index_url) as check:
        assert check.count_episodes() == 20
        assert [o.id for o in check.operators()] == ["op0", "op1", "op2"]


def test_a_newer_schema_is_refused(index_url: str) -> None:
    with EpisodeIndex.open(index_url) as opened:
        engine = opened._engine
        with engine.begin() as conn:
            conn.execute(sa.text("INSERT INTO schema_version (version, applied_ns) VALUES (99, 0)"))
    with pytest.raises(RecordingError, match="schema version 99, newer than this telerig supports"):
        EpisodeIndex.open(index_url)


def test_open_runs_pending_migrations(index_url: str, monkeypatch: pytest.MonkeyPatch) -> None:
    with EpisodeIndex.open(index_url) as opened:
        opened.upsert_episode(_manifest(1))

    def add_notes(conn: sa.Connection) -> None:
        conn.execute(sa.text("ALTER TABLE episodes ADD COLUMN notes TEXT"))

    monkeypatch.setattr(index_module, "SCHEMA_VERSION", SCHEMA_VERSION + 1)
    monkeypatch.setitem(index_module._MIGRATIONS, SCHEMA_VERSION + 1, add_notes)
    with EpisodeIndex.open(index_url) as migrated:
        assert migrated.schema_version == SCHEMA_VERSION + 1
        assert migrated.count_episodes() == 1
        columns = {c["name"] for c in sa.inspect(migrated._engine).get_columns("episodes")}
    assert "notes" in columns


def test_closed_index_refuses_calls(index_url: str) -> None:
    opened = EpisodeIndex.open(index_url)
    opened.close()
    opened.close()
    with pytest.raises(RecordingError, match="is closed"):
        opened.list_episodes()


# -- SQLite and URL handling (backend-specific) -----------------------------------------------


def test_a_data_root_gets_index_sqlite(tmp_path: Path) -> None:
    with EpisodeIndex.open(tmp_path / "root") as opened:
        assert opened.url.endswith("/root/index.sqlite")
    assert (tmp_path / "root" / "index.sqlite").is_file()


def test_an_sqlite_file_path_is_used_as_is(tmp_path: Path) -> None:
    EpisodeIndex.open(tmp_path / "custom.db").close()
    assert (tmp_path / "custom.db").is_file()


def test_an_unknown_url_scheme_names_the_supported_ones(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="postgresql://user:pass@host:port/db"):
        EpisodeIndex.open("mysql://u@h/db")


def test_an_unreachable_postgres_is_a_one_line_error() -> None:
    with pytest.raises(RecordingError, match=r"cannot open episode index postgresql\+psycopg://u:\*\*\*@127"):
        EpisodeIndex.open("postgresql://u:secret@127.0.0.1:1/db")
