"""Episode index: the robot and quality filters and the task/operator/status sort keys, on SQLite and a
real PostgreSQL on 127.0.0.1 (the robot filter is dialect-specific JSON)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from telerig.store.episodes import EpisodeManifest, FileEntry
from telerig.store.index import EpisodeIndex, EpisodeRecord
from telerig.store.manifest_extra import EpisodeExtra

_T0 = 1_700_000_000_000_000_000
_S = 1_000_000_000


@pytest.fixture(params=["sqlite", "postgresql"])
def index(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[EpisodeIndex]:
    url = (
        str(tmp_path / "root") if request.param == "sqlite" else str(request.getfixturevalue("postgres_url"))
    )
    with EpisodeIndex.open(url) as opened:
        for n, (task, operator, robots, quality) in enumerate(
            [
                ("pick", "bob", ["ur5e_robotiq85"], 0.9),
                ("place", "alice", ["ur5e_robotiq85", "allegro_right"], 0.4),
                ("fold", "carol", ["g1"], None),
                ("pick", "alice", ["ur5e"], 0.6),  # a prefix of another robot's name
            ]
        ):
            extra = EpisodeExtra(robots=robots, quality=quality).to_json()
            start = _T0 + n * 60 * _S
            manifest = EpisodeManifest(
                id=f"ep-20231114-2213{n:02d}-{n:04x}",
                rig="demo",
                task=task,
                operator=operator,
                status="complete",
                start_ns=start,
                end_ns=start + _S,
                duration_s=1.0,
                files=(FileEntry(path="episode.mcap", size=1, sha256="0" * 64),),
                extra=extra,
            )
            opened.upsert_episode(manifest)
        yield opened


def _tasks(records: list[EpisodeRecord]) -> list[str]:
    return [r.task for r in records]


def test_robot_filter_matches_a_whole_name_in_the_robots_list(index: EpisodeIndex) -> None:
    assert _tasks(index.list_episodes(robot="ur5e_robotiq85")) == ["pick", "place"]
    assert _tasks(index.list_episodes(robot="allegro_right")) == ["place"]
    assert _tasks(index.list_episodes(robot="ur5e")) == ["pick"]
    assert index.list_episodes(robot="ur5") == []


def test_quality_range_keeps_scored_episodes_within_it(index: EpisodeIndex) -> None:
    assert _tasks(index.list_episodes(min_quality=0.5)) == ["pick", "pick"]
    assert _tasks(index.list_episodes(max_quality=0.6)) == ["place", "pick"]
    assert _tasks(index.list_episodes(min_quality=0.5, max_quality=0.6)) == ["pick"]
    with pytest.raises(ValueError, match=r"quality must be in \[0, 1\]"):
        index.list_episodes(min_quality=1.5)


def test_sort_by_task_operator_and_status(index: EpisodeIndex) -> None:
    assert _tasks(index.list_episodes(order="task")) == ["fold", "pick", "pick", "place"]
    assert [r.operator for r in index.list_episodes(order="-operator")] == ["carol", "bob", "alice", "alice"]
    assert len(index.list_episodes(order="status")) == 4
