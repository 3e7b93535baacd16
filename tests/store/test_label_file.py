"""label.json: the success/failure label set after recording, read by the index (rebuild), the
exports and the quality score before the manifest's mark."""

from __future__ import annotations

from pathlib import Path

import pytest

from telerig.errors import RecordingError
from telerig.store.episodes import EpisodeStore
from telerig.store.index import EpisodeIndex
from telerig.store.label_file import LabelRecord, episode_outcome, read_label, write_label


def _episode(root: Path, outcome: str | None = None) -> tuple[EpisodeStore, str]:
    store = EpisodeStore(root)
    with store.begin(rig="demo", task="pick", operator="alice") as draft:
        draft.mcap_path.write_bytes(b"x")
        draft.commit({} if outcome is None else {"outcome": outcome})
    return store, draft.id


def test_a_label_wins_over_the_recorded_mark_in_the_index(tmp_path: Path) -> None:
    store, episode_id = _episode(tmp_path, outcome="success")
    directory = store.episode_dir(episode_id)
    manifest = store.get(episode_id)
    assert read_label(directory) is None
    assert episode_outcome(directory, manifest) == "success"
    write_label(directory, LabelRecord(episode_id=episode_id, outcome="failure", by="otto"))
    assert read_label(directory) == LabelRecord.model_validate_json((directory / "label.json").read_bytes())
    assert episode_outcome(directory, manifest) == "failure"
    assert not (directory / "label.json.tmp").exists()
    with EpisodeIndex.open("sqlite://") as index:
        index.rebuild(store)
        assert index.get(episode_id).outcome == "failure"
        assert [r.id for r in index.list_episodes(outcome="failure")] == [episode_id]
        assert index.list_episodes(outcome="success") == []


def test_a_label_follows_the_episode_to_failures(tmp_path: Path) -> None:
    store, episode_id = _episode(tmp_path)
    store.move_to_failures(episode_id, ["test"])
    moved = store.episode_dir(episode_id)
    write_label(moved, LabelRecord(episode_id=episode_id, outcome="success", by="otto"))
    store.restore_from_failures(episode_id)
    label = read_label(store.episode_dir(episode_id))
    assert label is not None
    assert label.outcome == "success"


def test_a_foreign_or_broken_label_is_one_line(tmp_path: Path) -> None:
    store, episode_id = _episode(tmp_path)
    directory = store.episode_dir(episode_id)
    (directory / "label.json").write_text('{"episode_id": "ep-20200101-000000-0000", "outcome": "success"}')
    with pytest.raises(RecordingError, match="belongs to episode"):
        read_label(directory)
    (directory / "label.json").write_text('{"episode_id": "x", "outcome": "maybe"}')
    with pytest.raises(RecordingError, match="is not a label"):
        read_label(directory)
    with pytest.raises(ValueError, match="written into"):
        write_label(directory, LabelRecord(episode_id="ep-20200101-000000-0000", outcome="success"))
