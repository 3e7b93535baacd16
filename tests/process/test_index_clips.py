"""The index's processed_clips table (schema version 4): a version-3 database migrates, and a
processed root's rows are replaced as a whole."""

from __future__ import annotations

from pathlib import Path

import sqlalchemy as sa

from telerig.store.index import SCHEMA_VERSION, EpisodeIndex, ProcessedClipRecord


def _clip(n: int, *, source: str = "ep-1", scene: str = "kitchen") -> ProcessedClipRecord:
    return ProcessedClipRecord(
        id=f"00000000-0000-4000-8000-{n:012d}", processed_root="", source_id=source,
        source_kind="episode", source_path="/data/episodes/ep-1", source_hash="a" * 64,
        path=f"dataset/{scene}/{n}.mp4", scene=scene, label="grasp", start_s=float(n), end_s=n + 1.5,
        duration_s=1.5, fps=30.0, device_id="station-7", date="2026-09-21T00:00:00+00:00",
    )  # fmt: skip


def test_version_3_index_migrates_to_processed_clips(tmp_path: Path) -> None:
    url = tmp_path / "index.sqlite"
    with EpisodeIndex.open(url) as fresh:
        assert fresh.schema_version == SCHEMA_VERSION == 5
        engine = fresh._engine
        with engine.begin() as conn:  # make it the version-3 database an older telerig left
            conn.execute(sa.text("DROP TABLE processed_clips"))
            conn.execute(sa.text("ALTER TABLE episodes DROP COLUMN instructions"))  # version 5
            conn.execute(sa.text("UPDATE schema_version SET version = 3 WHERE version = 5"))
    with EpisodeIndex.open(url) as migrated:
        assert migrated.schema_version == 5
        assert migrated.processed_clips() == []
        assert migrated.replace_processed_clips(tmp_path / "processed", [_clip(1)]) == 1


def test_replace_processed_clips_replaces_a_roots_rows(tmp_path: Path) -> None:
    with EpisodeIndex.open(tmp_path / "index.sqlite") as index:
        index.replace_processed_clips(tmp_path / "a", [_clip(1), _clip(2, scene="lab")])
        index.replace_processed_clips(tmp_path / "b", [_clip(3, source="video-abc")])
        index.replace_processed_clips(tmp_path / "a", [_clip(2, scene="lab"), _clip(4)])
        rows = index.processed_clips()
        assert [(r.id[-1], Path(r.processed_root).name) for r in rows] == [("2", "a"), ("4", "a"), ("3", "b")]
        assert [r.id[-1] for r in index.processed_clips(scene="lab")] == ["2"]
        assert [r.id[-1] for r in index.processed_clips(source_id="video-abc")] == ["3"]
        assert rows[0].fps == 30.0
        assert rows[0].date == "2026-09-21T00:00:00+00:00"
