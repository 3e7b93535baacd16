"""Input discovery: episodes (both committed partitions, by id, prefix and query), video folders
(recursive, hostile names, link loops, unreadable files), and the hash cache."""

from __future__ import annotations

import hashlib
import os
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from core_kit import make_episode, make_video

from telerig.errors import ProcessError
from telerig.process.items import HashCache, discover, parse_query
from telerig.store.episodes import EpisodeStore


def test_data_root_gives_committed_and_failed_episodes(tmp_path: Path) -> None:
    root = tmp_path / "data"
    kept = make_episode(root, task="pick")
    rejected = make_episode(root, task="place")
    EpisodeStore(root).move_to_failures(rejected, ["too dark"])
    found = discover(str(root))
    assert [i.id for i in found.items] == sorted([kept, rejected])
    item = next(i for i in found.items if i.id == kept)
    assert item.kind == "episode"
    assert item.videos == (root / "episodes" / kept / "cameras" / "front.mp4",)
    assert item.meta["fps"] == 10.0
    assert item.meta["device_id"] == "station-7"
    assert item.meta["date"].startswith("2026-09-21")
    assert found.data_root == root
    # Queries over the data root: by task, partition, id prefix and the episode's own directory.
    assert [i.id for i in discover("task=place", data_root=root).items] == [rejected]
    assert [i.id for i in discover("partition=episodes", data_root=root).items] == [kept]
    assert [i.id for i in discover(kept, data_root=root).items] == [kept]
    assert [i.id for i in discover(str(root / "episodes" / kept)).items] == [kept]


def test_episode_source_hash_follows_the_manifest_hashes(tmp_path: Path) -> None:
    root = tmp_path / "data"
    make_episode(root)
    first = discover(str(root)).items[0]
    manifest = EpisodeStore(root).get(first.id)
    assert {f.path for f in manifest.files} >= {"cameras/front.mp4", "episode.mcap"}
    assert len(first.source_hash) == 64
    assert discover(str(root)).items[0].source_hash == first.source_hash


@pytest.mark.parametrize(
    ("target", "message"),
    [
        ("ep-20990101-000000-beef", "not found"),
        ("task=", "expected KEY=VALUE"),
        ("colour=red", "expected KEY=VALUE"),
        ("partition=incoming", "use episodes or failures"),
    ],
)
def test_bad_queries_are_one_line_errors(tmp_path: Path, target: str, message: str) -> None:
    root = tmp_path / "data"
    make_episode(root)
    with pytest.raises(ProcessError, match=message) as info:
        discover(target, data_root=root)
    assert "\n" not in str(info.value)


def test_unknown_path_without_data_root_names_the_fix(tmp_path: Path) -> None:
    with pytest.raises(ProcessError, match="not a file, folder, data root or episode") as info:
        discover(str(tmp_path / "nope"))
    assert "--data-root" in str(info.value)
    with pytest.raises(ProcessError, match="is not a data root"):
        discover("ep-x", data_root=tmp_path)


def test_video_folder_is_searched_recursively_and_hashed(tmp_path: Path) -> None:
    folder = tmp_path / "footage"
    a = make_video(folder / "a.mp4")
    b = make_video(folder / "phone" / "day1" / "B.MOV", shade=50)
    (folder / "notes.txt").write_text("not a video")
    (folder / ".hidden.mp4").write_bytes(b"x")
    found = discover(str(folder))
    assert [i.videos[0] for i in found.items] == sorted([a, b])
    assert all(i.kind == "video" and i.episode_dir is None for i in found.items)
    item = next(i for i in found.items if i.videos[0] == a)
    assert item.source_hash == hashlib.sha256(a.read_bytes()).hexdigest()
    assert item.id.startswith("video-")
    assert not found.skipped


def test_hostile_folder_contents_are_skipped_with_reasons(tmp_path: Path) -> None:
    folder = tmp_path / "footage"
    make_video(folder / "good.mp4")
    (folder / "garbage.mp4").write_bytes(os.urandom(4096))  # not decodable: a stage will say so
    (folder / "loop").mkdir()
    (folder / "loop" / "back").symlink_to(folder, target_is_directory=True)
    (folder / "dangling.mkv").symlink_to(folder / "missing.mkv")
    long_name = "v" * 240 + ".mp4"
    make_video(folder / long_name)
    (folder / "\udcff-undecodable.mp4").write_bytes(b"\x00" * 100)
    locked = folder / "locked.mp4"
    locked.write_bytes(b"\x00" * 100)
    locked.chmod(0)
    deep = folder
    for _ in range(70):
        deep = deep / "d"
    deep.mkdir(parents=True)
    try:
        found = discover(str(folder))
    finally:
        locked.chmod(0o644)
    names = sorted(i.videos[0].name for i in found.items)
    assert "good.mp4" in names
    assert "garbage.mp4" in names
    assert long_name in names
    reasons = {Path(s.path).name: s.reason for s in found.skipped}
    assert "cannot read" in reasons["dangling.mkv"]
    if os.geteuid() != 0:  # root reads mode-000 files
        assert "cannot read" in reasons["locked.mp4"]
    assert any("deeper than" in r for r in reasons.values())
    assert all("\n" not in s.reason and len(s.path) <= 203 for s in found.skipped)


def test_hash_cache_skips_rehash_until_the_file_changes(tmp_path: Path) -> None:
    video = make_video(tmp_path / "v" / "a.mp4")
    cache_dir = tmp_path / "processed" / ".cache"
    first = discover(str(video), cache_dir=cache_dir).items[0]
    assert (cache_dir / "hashes.json").is_file()
    cache = HashCache.open(cache_dir)
    key = os.path.abspath(video)
    # A cached digest is trusted while size and mtime match (proved by planting a different one).
    cache.entries[key]["sha256"] = "f" * 64
    cache.dirty = True
    cache.save()
    assert discover(str(video), cache_dir=cache_dir).items[0].source_hash == "f" * 64
    with video.open("ab") as f:
        f.write(b"\0")
    again = discover(str(video), cache_dir=cache_dir).items[0]
    assert again.source_hash == hashlib.sha256(video.read_bytes()).hexdigest() != first.source_hash


def test_damaged_hash_cache_is_ignored(tmp_path: Path) -> None:
    video = make_video(tmp_path / "a.mp4")
    cache_dir = tmp_path / ".cache"
    cache_dir.mkdir()
    (cache_dir / "hashes.json").write_bytes(b"[" * 50000)
    assert discover(str(video), cache_dir=cache_dir).items[0].source_hash == (
        hashlib.sha256(video.read_bytes()).hexdigest()
    )


def test_parse_query_takes_ids_and_fields() -> None:
    q = parse_query("ep-1, task=pick operator=ann id=ep-2")
    assert q.ids == ("ep-1", "ep-2")
    assert (q.task, q.operator) == ("pick", "ann")
