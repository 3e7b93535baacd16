"""Failures partition: a committed episode moves to ``failures`` with its reasons and back, atomically,
and a process killed between the steps leaves it in one place that ``telerig repair`` finishes."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from telerig.errors import RecordingError
from telerig.store.episodes import FAILURE_FILE, EpisodeStore, MoveRecovery
from telerig.store.fingerprint import check_compatible, rig_fingerprint
from telerig.store.repair import cmd_repair

_T0 = 1_700_000_000_000_000_000  # 2023-11-14T22:13:20Z [ns]


def _committed(store: EpisodeStore, n: int = 0) -> str:
    draft = store.begin(rig="demo", task="pick", operator="alice", start_ns=_T0 + n * 1_000_000_000)
    draft.mcap_path.write_bytes(b"mcap bytes")
    draft.commit()
    return draft.id


def _places(root: Path, episode_id: str) -> list[str]:
    partitions = ("episodes", "failures", "incomplete", ".incoming")
    return [p for p in partitions if (root / p / episode_id).is_dir()]


def test_move_to_failures_keeps_files_and_writes_reasons(tmp_path: Path) -> None:
    store = EpisodeStore(tmp_path)
    episode = _committed(store)
    manifest_before = (tmp_path / "episodes" / episode / "manifest.json").read_bytes()

    path = store.move_to_failures(episode, ["joint_limits: 0.12 > 0.05", "idle: 0.8 > 0.6"])

    assert path == tmp_path / "failures" / episode
    assert _places(tmp_path, episode) == ["failures"]
    assert (path / "manifest.json").read_bytes() == manifest_before
    assert (path / "episode.mcap").read_bytes() == b"mcap bytes"
    failure = store.failure(episode)
    assert failure is not None
    assert failure.reasons == ("joint_limits: 0.12 > 0.05", "idle: 0.8 > 0.6")


def test_list_get_and_episode_dir_say_which_partition(tmp_path: Path) -> None:
    store = EpisodeStore(tmp_path)
    kept, failed = _committed(store, 0), _committed(store, 1)
    store.move_to_failures(failed, ["fall"])

    assert [s.id for s in store.list()] == [kept]
    both = {s.id: s.partition for s in store.list(include_failures=True)}
    assert both == {kept: "episodes", failed: "failures"}
    assert {s.id: s.partition for s in store.list(include_unfinished=True)} == both
    assert store.get(failed).id == failed
    assert store.episode_dir(failed) == tmp_path / "failures" / failed
    assert store.find(failed).partition == "failures"
    assert store.find(kept).partition == "episodes"


def test_restore_moves_it_back_without_reasons(tmp_path: Path) -> None:
    store = EpisodeStore(tmp_path)
    episode = _committed(store)
    store.move_to_failures(episode, ["fall"])

    path = store.restore_from_failures(episode)

    assert path == tmp_path / "episodes" / episode
    assert _places(tmp_path, episode) == ["episodes"]
    assert not (path / FAILURE_FILE).exists()
    assert store.failure(episode) is None


def test_moving_twice_updates_the_reasons_and_restoring_twice_is_a_no_op(tmp_path: Path) -> None:
    store = EpisodeStore(tmp_path)
    episode = _committed(store)
    store.move_to_failures(episode, ["fall"])
    store.move_to_failures(episode, ["idle"])
    failure = store.failure(episode)
    assert failure is not None
    assert failure.reasons == ("idle",)
    store.restore_from_failures(episode)
    store.restore_from_failures(episode)
    assert _places(tmp_path, episode) == ["episodes"]


def test_an_incomplete_episode_cannot_move(tmp_path: Path) -> None:
    store = EpisodeStore(tmp_path)
    draft = store.begin(rig="demo", task="pick", operator="alice", start_ns=_T0)
    draft.abandon("operator discarded it")
    with pytest.raises(RecordingError, match=r"is not in .*episodes"):
        store.move_to_failures(draft.id, ["fall"])
    with pytest.raises(RecordingError, match=r"is not in .*failures"):
        store.restore_from_failures(draft.id)


@pytest.mark.parametrize("hostile", ["../x", "ep-20231114-221320-0000/../../x", "/etc", "", "ep-*"])
def test_a_path_is_not_an_episode_id(tmp_path: Path, hostile: str) -> None:
    store = EpisodeStore(tmp_path)
    with pytest.raises(RecordingError, match="is not an episode id"):
        store.move_to_failures(hostile, ["fall"])
    with pytest.raises(RecordingError, match="is not an episode id"):
        store.restore_from_failures(hostile)
    assert not (tmp_path / "failures").exists()


def test_a_new_episode_never_reuses_the_id_of_a_failure(tmp_path: Path) -> None:
    store = EpisodeStore(tmp_path)
    episode = _committed(store)
    store.move_to_failures(episode, ["fall"])
    with pytest.raises(RecordingError, match="already in"):
        store.begin(rig="demo", task="pick", operator="alice", episode_id=episode)


def test_the_rig_check_sees_failures_too(tmp_path: Path) -> None:
    from telerig.config import load_rig

    store = EpisodeStore(tmp_path)
    demo = rig_fingerprint(load_rig("demo"))
    draft = store.begin(rig="demo", task="pick", operator="alice", extra={"fingerprint": demo.to_json()})
    draft.commit()
    store.move_to_failures(draft.id, ["fall"])
    with pytest.raises(RecordingError, match="rig differs"):
        check_compatible(store, rig_fingerprint(load_rig("gripper")))


# --- a process killed between the steps ---------------------------------------------------------

_KILL_AT_RENAME = textwrap.dedent(
    """
    import os, sys
    from telerig.store.episodes import EpisodeStore

    root, episode, what = sys.argv[1:4]
    real_rename = os.rename

    def die(src, dst):  # the process dies where the directory rename would be
        os._exit(137)

    os.rename = die
    store = EpisodeStore(root)
    if what == "move":
        store.move_to_failures(episode, ["idle: 0.9 > 0.6"])
    else:
        store.restore_from_failures(episode)
    os._exit(0)  # not reached
    """
)


def _killed(root: Path, episode: str, what: str) -> None:
    done = subprocess.run(
        [sys.executable, "-c", _KILL_AT_RENAME, str(root), episode, what],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 137, done.stderr


def test_a_move_killed_before_the_rename_leaves_one_copy_that_repair_finishes(tmp_path: Path) -> None:
    store = EpisodeStore(tmp_path)
    episode = _committed(store)
    _killed(tmp_path, episode, "move")

    assert _places(tmp_path, episode) == ["episodes"]  # exactly one place, files intact
    assert (tmp_path / "episodes" / episode / FAILURE_FILE).is_file()
    assert store.finish_interrupted_moves() == [MoveRecovery(id=episode, to="failures")]
    assert _places(tmp_path, episode) == ["failures"]
    failure = store.failure(episode)
    assert failure is not None
    assert failure.reasons == ("idle: 0.9 > 0.6",)
    assert store.finish_interrupted_moves() == []


def test_a_restore_killed_before_the_rename_is_finished_by_telerig_repair(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    store = EpisodeStore(tmp_path)
    episode = _committed(store)
    store.move_to_failures(episode, ["fall"])
    _killed(tmp_path, episode, "restore")

    assert _places(tmp_path, episode) == ["failures"]
    assert not (tmp_path / "failures" / episode / FAILURE_FILE).exists()
    import argparse

    code = cmd_repair(
        argparse.Namespace(all=True, episode_id=None, data_root=tmp_path, keep_originals=False, force=False)
    )
    assert code == 0
    assert _places(tmp_path, episode) == ["episodes"]
    assert f"{episode}: finished its interrupted move to episodes" in capsys.readouterr().out


def test_a_crash_while_writing_the_reasons_leaves_the_episode_where_it_was(tmp_path: Path) -> None:
    store = EpisodeStore(tmp_path)
    episode = _committed(store)
    torn = tmp_path / "episodes" / episode / (FAILURE_FILE + ".tmp")
    torn.write_text('{"id": "ep-')  # the atomic write was cut before its replace

    assert store.finish_interrupted_moves() == []
    assert _places(tmp_path, episode) == ["episodes"]
    assert not torn.exists()


def test_a_garbage_failure_record_is_one_line(tmp_path: Path) -> None:
    store = EpisodeStore(tmp_path)
    episode = _committed(store)
    store.move_to_failures(episode, ["fall"])
    (tmp_path / "failures" / episode / FAILURE_FILE).write_bytes(os.urandom(64))
    with pytest.raises(RecordingError, match="is not a failure record") as info:
        store.failure(episode)
    assert "\n" not in str(info.value)


def test_an_episode_queued_for_upload_then_moved_to_failures_is_still_uploaded(tmp_path: Path) -> None:
    from telerig.store.remote import LocalObjectStore
    from telerig.store.upload import EpisodeUploader, StationLoad, UploadQueue

    root = tmp_path / "data"
    store = EpisodeStore(root)
    episode = _committed(store)
    idle = StationLoad(
        cpu_percent=5.0, memory_percent=30.0, net_sent_bytes_per_s=1e3, net_recv_bytes_per_s=1e3
    )
    uploader = EpisodeUploader(LocalObjectStore(tmp_path / "archive"), root / ".uploads")
    with UploadQueue(root, uploader, sample_load=lambda: idle) as queue:
        queue.submit(root / "episodes" / episode, now=True)
        store.move_to_failures(episode, ["fall"])  # the gates ran after the commit queued it
        results = queue.run_pending()
    assert [r.episode_id for r in results] == [episode]
    assert (tmp_path / "archive" / episode / "episode.mcap").read_bytes() == b"mcap bytes"
    assert queue.pending() == []
