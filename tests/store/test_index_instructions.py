"""Index schema 5: each episode's operator instruction count from its manifest (issue 17), and the
migration from version 4 (SQLite and PostgreSQL)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
import sqlalchemy as sa
from pydantic import JsonValue

from telerig.store import index as index_module
from telerig.store.episodes import EpisodeManifest, FileEntry
from telerig.store.index import EpisodeIndex

_T0 = 1_700_000_000_000_000_000  # [ns]
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


def _manifest(n: int, instructions: JsonValue = None) -> EpisodeManifest:
    start = _T0 + n * 60 * _S
    extra: dict[str, JsonValue] = {} if instructions is None else {"instructions": instructions}
    return EpisodeManifest(
        id=f"ep-20231114-2213{n:02d}-{n:04x}",
        rig="tiago_wbc",
        task="reach",
        operator="alice",
        status="complete",
        start_ns=start,
        end_ns=start + 2 * _S,
        duration_s=2.0,
        files=(FileEntry(path="episode.mcap", size=10, sha256="0" * 64),),
        extra=extra,
    )


def test_the_manifest_instruction_total_is_indexed(index: EpisodeIndex) -> None:
    counts: JsonValue = {"total": 5, "by_group": {"plan": 2, "mode": 3}, "reaches": 1, "reach_eta": 1.5}
    assert index.upsert_episode(_manifest(1, counts)).instructions == 5
    assert index.upsert_episode(_manifest(2)).instructions is None  # not counted (older episodes)
    assert [r.instructions for r in index.list_episodes()] == [5, None]


@pytest.mark.parametrize("total", [-1, 10**7, True, "5", 2.5, None])
def test_a_garbage_total_is_not_indexed(index: EpisodeIndex, total: JsonValue) -> None:
    assert index.upsert_episode(_manifest(3, {"total": total})).instructions is None


def test_a_version_4_index_migrates_to_5(index_url: str) -> None:
    engine = index_module._create_engine(index_module._database_url(index_url))
    try:
        with engine.begin() as conn:
            for table in index_module._metadata.sorted_tables:
                table.create(conn)
            conn.execute(sa.text("ALTER TABLE episodes DROP COLUMN instructions"))
            conn.execute(sa.text("INSERT INTO schema_version (version, applied_ns) VALUES (4, 0)"))
    finally:
        engine.dispose()
    with EpisodeIndex.open(index_url) as migrated:
        assert migrated.schema_version == 5
        columns = {c["name"] for c in sa.inspect(migrated._engine).get_columns("episodes")}
        assert "instructions" in columns
        assert migrated.upsert_episode(_manifest(4, {"total": 7})).instructions == 7
