"""Episode store: drafts commit atomically, failures are kept with a reason, listing and lookup."""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path

import pytest

from telerig.errors import RecordingError
from telerig.store.episodes import EpisodeDraft, EpisodeManifest, EpisodeStore

_T0 = 1_700_000_000_000_000_000  # 2023-11-14T22:13:20Z [ns]


def _begin(store: EpisodeStore, start_ns: int = _T0, task: str = "pick") -> EpisodeDraft:
    return store.begin(rig="demo", task=task, operator="alice", start_ns=start_ns)


def test_begin_creates_a_draft_in_incoming_only(tmp_path: Path) -> None:
    draft = _begin(EpisodeStore(tmp_path))
    assert re.fullmatch(r"ep-20231114-221320-[0-9a-f]{4}", draft.id)
    assert draft.dir == tmp_path / ".incoming" / draft.id
    assert draft.mcap_path == draft.dir / "episode.mcap"
    assert draft.camera_path("wrist") == draft.dir / "cameras" / "wrist.mp4"
    assert not (tmp_path / "episodes").exists()


def test_commit_moves_the_episode_with_a_manifest(tmp_path: Path) -> None:
    store = EpisodeStore(tmp_path)
    draft = _begin(store)
    draft.mcap_path.write_bytes(b"mcap bytes")
    draft.camera_path("wrist").write_bytes(b"video")
    assert list((tmp_path / "episodes").glob("*")) == []

    manifest = draft.commit(
        {"streams": {"vr0": {"count": 3}}, "camera_frames": {"wrist": 2}}, end_ns=_T0 + 2_500_000_000
    )

    final = tmp_path / "episodes" / draft.id
    assert draft.dir == final
    assert not (tmp_path / ".incoming" / draft.id).exists()
    on_disk = EpisodeManifest.model_validate_json((final / "manifest.json").read_bytes())
    assert on_disk == manifest
    assert manifest.status == "complete"
    assert (manifest.rig, manifest.task, manifest.operator) == ("demo", "pick", "alice")
    assert manifest.duration_s == pytest.approx(2.5)
    assert manifest.extra == {"streams": {"vr0": {"count": 3}}, "camera_frames": {"wrist": 2}}
    files = {f.path: f for f in manifest.files}
    assert set(files) == {"episode.mcap", "cameras/wrist.mp4"}
    assert files["cameras/wrist.mp4"].size == 5
    assert files["episode.mcap"].sha256 == hashlib.sha256(b"mcap bytes").hexdigest()


def test_manifest_is_plain_json(tmp_path: Path) -> None:
    draft = _begin(EpisodeStore(tmp_path))
    draft.commit()
    data = json.loads((tmp_path / "episodes" / draft.id / "manifest.json").read_text())
    assert data["id"] == draft.id
    assert data["status"] == "complete"


def test_abandon_keeps_the_draft_as_incomplete(tmp_path: Path) -> None:
    store = EpisodeStore(tmp_path)
    draft = _begin(store)
    draft.mcap_path.write_bytes(b"partial")
    manifest = draft.abandon("operator pressed stop early")
    assert manifest.status == "incomplete"
    assert manifest.reason == "operator pressed stop early"
    assert (tmp_path / "incomplete" / draft.id / "episode.mcap").read_bytes() == b"partial"
    assert store.list() == []


def test_draft_closed_by_an_exception_is_abandoned_with_it(tmp_path: Path) -> None:
    store = EpisodeStore(tmp_path)
    with pytest.raises(RuntimeError), _begin(store) as draft:
        raise RuntimeError("camera died")
    assert draft.state == "abandoned"
    assert store.get(draft.id, include_unfinished=True).reason == "RuntimeError: camera died"


def test_finished_draft_cannot_finish_again(tmp_path: Path) -> None:
    draft = _begin(EpisodeStore(tmp_path))
    draft.commit()
    with pytest.raises(RecordingError, match="already committed"):
        draft.abandon("late")


def test_non_json_extra_is_rejected_before_anything_moves(tmp_path: Path) -> None:
    draft = _begin(EpisodeStore(tmp_path))
    with pytest.raises(ValueError, match="manifest_extra"):
        draft.commit({"bad": {1, 2}})  # type: ignore[dict-item]
    assert draft.state == "open"
    assert draft.dir.parent.name == ".incoming"


def test_list_shows_committed_oldest_first_and_unfinished_on_request(tmp_path: Path) -> None:
    store = EpisodeStore(tmp_path)
    late = _begin(store, _T0 + 60_000_000_000, task="late")
    early = _begin(store, _T0, task="early")
    failed = _begin(store, _T0 + 30_000_000_000, task="failed")
    crashed = _begin(store, _T0 + 90_000_000_000, task="crashed")  # never finished: a crash
    late.commit()
    early.commit()
    failed.abandon("robot fault")

    assert [s.task for s in store.list()] == ["early", "late"]
    everything = store.list(include_unfinished=True)
    assert [(s.task, s.status) for s in everything] == [
        ("early", "complete"),
        ("failed", "incomplete"),
        ("late", "complete"),
        ("crashed", "interrupted"),
    ]
    assert everything[-1].path == crashed.dir


def test_get_by_id_and_unique_prefix(tmp_path: Path) -> None:
    store = EpisodeStore(tmp_path)
    draft = _begin(store)
    draft.commit({"k": 1})
    assert store.get(draft.id).extra == {"k": 1}
    assert store.get(draft.id[:-2]).id == draft.id
    assert store.episode_dir(draft.id) == tmp_path / "episodes" / draft.id


def test_get_unknown_names_what_exists(tmp_path: Path) -> None:
    store = EpisodeStore(tmp_path)
    draft = _begin(store)
    draft.commit()
    with pytest.raises(RecordingError, match=rf"'ep-nope' not found .* Available: {draft.id}"):
        store.get("ep-nope")


def test_get_in_empty_store_says_none(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match="Available: none"):
        EpisodeStore(tmp_path).get("ep-1")


def test_later_episodes_never_touch_earlier_ones(tmp_path: Path) -> None:
    store = EpisodeStore(tmp_path)
    first = _begin(store)
    first.mcap_path.write_bytes(b"one")
    first.commit()
    before = {p: p.read_bytes() for p in first.dir.rglob("*") if p.is_file()}
    for i in range(3):
        d = _begin(store, _T0)  # same second: ids still differ
        d.mcap_path.write_bytes(b"more")
        if i % 2:
            d.commit()
        else:
            d.abandon("test")
    assert {p: p.read_bytes() for p in first.dir.rglob("*") if p.is_file()} == before
    assert len(store.list(include_unfinished=True)) == 4


def test_bad_camera_name_is_rejected(tmp_path: Path) -> None:
    draft = _begin(EpisodeStore(tmp_path))
    with pytest.raises(ValueError, match="camera name"):
        draft.camera_path("../escape")


def test_begin_files_the_episode_under_a_given_id_once(tmp_path: Path) -> None:
    store = EpisodeStore(tmp_path)
    draft = store.begin(rig="r", task="t", operator="o", episode_id="ep-20261121-101500-ab12")
    assert draft.id == "ep-20261121-101500-ab12"
    draft.commit({})
    with pytest.raises(RecordingError, match="already in"):
        store.begin(rig="r", task="t", operator="o", episode_id="ep-20261121-101500-ab12")
    with pytest.raises(RecordingError, match="ep-YYYYMMDD-HHMMSS-xxxx"):
        store.begin(rig="r", task="t", operator="o", episode_id="../escape")
