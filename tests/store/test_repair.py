"""Crash recovery: a torn draft becomes a committed episode holding exactly its verified prefix."""

from __future__ import annotations

import argparse
import fcntl
import os
import struct
import tempfile
import time
from pathlib import Path
from typing import Any

import av
import numpy as np
import pytest
from mcap.reader import make_reader

from telerig.bus.broker import BROKER_DIR_PREFIX
from telerig.cameras.encoder import VideoEncoder
from telerig.errors import RecordingError
from telerig.ir import wire
from telerig.ir.mcap_log import McapLog, iter_raw
from telerig.ir.types import CameraFrame, JointState, Stamp
from telerig.store.episodes import EpisodeDraft, EpisodeManifest, EpisodeStore
from telerig.store.repair import REPAIRED_STATUS, add_repair_arguments, cmd_repair, interrupted, repair

_T0 = 1_700_000_000_000_000_000  # [ns]
_JOINTS = "telerig/v1/test/arm0/joint_state"
_FRAMES = "telerig/v1/test/cam/frames"
_STATUS = "telerig/v1/test/arm0/status"
_FPS = 30.0
_W, _H = 64, 48


def _joint_state(i: int) -> bytes:
    stamp = Stamp("arm0", i, device_ns=i, capture_ns=_T0 + i * 10_000_000)
    return wire.encode(JointState(stamp, ("j0",), np.array([0.01 * i]), np.zeros(1)))


def _frame(i: int) -> bytes:
    stamp = Stamp("cam", i, device_ns=i, capture_ns=_T0 + round(i * 1e9 / _FPS))
    return wire.encode(CameraFrame(stamp, "cam", i, _W, _H))


def _write_mcap(path: Path, batches: int, per_batch: int = 50) -> list[int]:
    """Log ``batches`` flushed batches of 100 Hz joint states (+ frame stamps, a JSON status); returns
    the file size after each flush [bytes]."""
    sizes = []
    with McapLog(path, flush_interval_s=60.0) as log:
        i = 0
        for _ in range(batches):
            for _ in range(per_batch):
                t = _T0 + i * 10_000_000
                log.write(_JOINTS, _joint_state(i), log_time_ns=t, publish_time_ns=t)
                if i % 3 == 0:
                    log.write(_FRAMES, _frame(i // 3), log_time_ns=t, publish_time_ns=t)
                i += 1
            log.write_json(_STATUS, b'{"state": "ok"}', log_time_ns=_T0 + (i - 1) * 10_000_000)
            log.flush()
            sizes.append(path.stat().st_size)
    return sizes


def _write_mp4(path: Path, frames: int) -> None:
    """A fragmented MP4 with a fragment every 0.2 s of capture time."""
    image = np.zeros((_H, _W, 3), dtype=np.uint8)
    with VideoEncoder(path, width=_W, height=_H, fps=_FPS, keyframe_interval_s=0.2) as encoder:
        for i in range(frames):
            image[:] = i * 7 % 255
            while not encoder.submit(image, _T0 + round(i * 1e9 / _FPS)):  # queue full: wait, never drop
                time.sleep(0.001)


def _boxes(path: Path) -> list[tuple[bytes, int, int]]:
    data = path.read_bytes()
    out, offset = [], 0
    while offset + 8 <= len(data):
        length, kind = struct.unpack(">I4s", data[offset : offset + 8])
        out.append((kind, offset, length))
        offset += length
    return out


def _tear(path: Path, size: int) -> None:
    with open(path, "r+b") as f:
        f.truncate(size)


def _report(manifest: EpisodeManifest) -> Any:
    return manifest.extra["repair"]


def _decoded(path: Path) -> int:
    with av.open(str(path)) as c:
        return sum(1 for _ in c.decode(video=0))


@pytest.fixture
def crashed(tmp_path: Path) -> tuple[EpisodeStore, EpisodeDraft, int]:
    """A draft as a crash leaves it: MCAP torn inside its 3rd chunk, MP4 torn inside its 3rd fragment.

    Returns the store, the draft and how many joint states were in the two whole chunks.
    """
    store = EpisodeStore(tmp_path / "data")
    draft = store.begin(rig="test", task="pick", operator="alice", start_ns=_T0)
    sizes = _write_mcap(draft.mcap_path, batches=3)
    _tear(draft.mcap_path, sizes[1] + (sizes[2] - sizes[1]) // 2)
    video = draft.camera_path("cam")
    _write_mp4(video, frames=30)  # 1 s: fragments of 6 frames
    mdats = [(o, n) for kind, o, n in _boxes(video) if kind == b"mdat"]
    _tear(video, mdats[2][0] + mdats[2][1] // 2)
    return store, draft, 100


def test_repair_commits_the_verified_prefix(crashed: tuple[EpisodeStore, EpisodeDraft, int]) -> None:
    store, draft, whole = crashed
    manifest = repair(store, draft.id, min_idle_s=0)
    assert manifest.status == REPAIRED_STATUS
    assert not draft.dir.exists()
    assert sorted(f.path for f in manifest.files) == ["cameras/cam.mp4", "episode.mcap"]
    assert manifest.end_ns == _T0 + (whole - 1) * 10_000_000
    assert _report(manifest)["streams"][_JOINTS]["messages"] == whole
    assert store.list()[0].id == draft.id


def test_repaired_mcap_is_valid_and_keeps_json_channels(
    crashed: tuple[EpisodeStore, EpisodeDraft, int],
) -> None:
    store, draft, whole = crashed
    repair(store, draft.id, min_idle_s=0)
    path = store.root / "episodes" / draft.id / "episode.mcap"
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
        assert summary is not None
        f.seek(0)
        topics = [c.topic for _, c, _ in make_reader(f).iter_messages()]
    assert topics.count(_JOINTS) == whole
    assert topics.count(_STATUS) == 2
    assert sum(1 for t, *_ in iter_raw(path) if t == _JOINTS) == whole


def test_repaired_video_keeps_whole_fragments_that_decode(
    crashed: tuple[EpisodeStore, EpisodeDraft, int],
) -> None:
    store, draft, _ = crashed
    manifest = repair(store, draft.id, min_idle_s=0)
    video = store.root / "episodes" / draft.id / "cameras" / "cam.mp4"
    assert _decoded(video) == 12  # two fragments of 6 frames
    cam = _report(manifest)["cameras"]["cam"]
    assert (cam["frames"], cam["fragments"]) == (12, 2)
    assert cam["start_ns"] == _T0
    assert cam["end_ns"] == pytest.approx(_T0 + 11e9 / _FPS, abs=1000)
    assert manifest.extra["cameras"] == {"cam": {"file": "cameras/cam.mp4", "frames": 12}}


def test_losses_are_reported_from_the_newest_recovered_data(
    crashed: tuple[EpisodeStore, EpisodeDraft, int],
) -> None:
    store, draft, whole = crashed
    manifest = repair(store, draft.id, min_idle_s=0)
    report = _report(manifest)
    newest = _T0 + (whole - 1) * 10_000_000
    assert report["last_evidence_ns"] == newest
    assert report["streams"][_JOINTS]["lost_s"] == 0.0
    video_end = _T0 + 11e9 / _FPS
    assert report["cameras"]["cam"]["lost_s"] == pytest.approx((newest - video_end) / 1e9, abs=1e-6)


def test_keep_originals_leaves_the_torn_files_listed(crashed: tuple[EpisodeStore, EpisodeDraft, int]) -> None:
    store, draft, _ = crashed
    torn_mcap = draft.mcap_path.read_bytes()
    manifest = repair(store, draft.id, min_idle_s=0, keep_originals=True)
    episode = store.root / "episodes" / draft.id
    assert (episode / "episode.mcap.torn").read_bytes() == torn_mcap
    assert {f.path for f in manifest.files} >= {"episode.mcap.torn", "cameras/cam.mp4.torn"}


def test_a_video_without_a_whole_fragment_is_removed(tmp_path: Path) -> None:
    store = EpisodeStore(tmp_path)
    draft = store.begin(rig="test", task="pick", operator="alice", start_ns=_T0)
    _write_mcap(draft.mcap_path, batches=1)
    video = draft.camera_path("cam")
    _write_mp4(video, frames=10)
    first_mdat = next((o, n) for kind, o, n in _boxes(video) if kind == b"mdat")
    _tear(video, first_mdat[0] + 10)
    manifest = repair(store, draft.id, min_idle_s=0)
    assert [f.path for f in manifest.files] == ["episode.mcap"]
    assert _report(manifest)["cameras"]["cam"]["frames"] == 0


def test_a_complete_log_is_kept_byte_for_byte(tmp_path: Path) -> None:
    store = EpisodeStore(tmp_path)
    draft = store.begin(rig="test", task="pick", operator="alice", start_ns=_T0)
    _write_mcap(draft.mcap_path, batches=1)  # closed: crash after the recorder stopped
    before = draft.mcap_path.read_bytes()
    repair(store, draft.id, min_idle_s=0)
    assert (store.root / "episodes" / draft.id / "episode.mcap").read_bytes() == before


def test_a_crash_inside_commit_is_finished_as_it_was(tmp_path: Path) -> None:
    store = EpisodeStore(tmp_path)
    draft = store.begin(rig="test", task="pick", operator="alice", start_ns=_T0)
    _write_mcap(draft.mcap_path, batches=1)
    committed = draft.commit({"note": "x"}, end_ns=_T0 + 10**9)
    # Put it back as the crash left it: final manifest written, not yet moved.
    os.rename(draft.dir, store.root / ".incoming" / draft.id)
    again = repair(store, draft.id, min_idle_s=0)
    assert again == committed


def test_committed_episodes_are_refused(crashed: tuple[EpisodeStore, EpisodeDraft, int]) -> None:
    store, draft, _ = crashed
    repair(store, draft.id, min_idle_s=0)
    with pytest.raises(RecordingError, match=rf"is {REPAIRED_STATUS}, not interrupted"):
        repair(store, draft.id, min_idle_s=0)


def test_unknown_ids_list_the_interrupted_ones(crashed: tuple[EpisodeStore, EpisodeDraft, int]) -> None:
    store, draft, _ = crashed
    with pytest.raises(RecordingError, match=f"Interrupted: {draft.id}"):
        repair(store, "ep-2099", min_idle_s=0)


def test_a_draft_written_just_now_is_refused(crashed: tuple[EpisodeStore, EpisodeDraft, int]) -> None:
    store, draft, _ = crashed
    draft.mcap_path.touch()
    with pytest.raises(RecordingError, match="may still be recording"):
        repair(store, draft.id, min_idle_s=60)
    assert draft.dir.is_dir()


def test_a_locked_draft_is_refused(crashed: tuple[EpisodeStore, EpisodeDraft, int]) -> None:
    store, draft, _ = crashed
    fd = os.open(draft.dir, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        with pytest.raises(RecordingError, match="locked by a running recorder"):
            repair(store, draft.id, min_idle_s=0)
    finally:
        os.close(fd)


def test_cli_repairs_all_interrupted_episodes(
    crashed: tuple[EpisodeStore, EpisodeDraft, int], capsys: pytest.CaptureFixture[str]
) -> None:
    store, draft, _ = crashed
    parser = argparse.ArgumentParser()
    add_repair_arguments(parser)
    args = parser.parse_args(["--all", "--force", "--data-root", str(store.root)])
    assert cmd_repair(args) == 0
    out = capsys.readouterr().out
    assert draft.id in out
    assert "camera cam 12 frames" in out
    assert interrupted(store) == []


def test_cli_repair_removes_the_directory_a_killed_embedded_broker_left(
    crashed: tuple[EpisodeStore, EpisodeDraft, int],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    # Issue 11 finding 6: after kill -9 the broker's temp dir (with the run's password hashes) stayed.
    store, _, _ = crashed
    temp = tmp_path / "tmp"
    temp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(temp))
    left = Path(tempfile.mkdtemp(prefix=BROKER_DIR_PREFIX))
    (left / "passwd").write_text("station:$7$...")
    old = time.time() - 120.0
    os.utime(left, (old, old))
    parser = argparse.ArgumentParser()
    add_repair_arguments(parser)
    assert cmd_repair(parser.parse_args(["--all", "--force", "--data-root", str(store.root)])) == 0
    assert not left.exists()
    assert str(left) in capsys.readouterr().out.replace("\n", "")  # rich wraps long lines


def test_a_retained_alert_published_once_does_not_count_as_lost_data(tmp_path: Path) -> None:
    # Issue 11 finding 6: an alert published once at the start made the loss "at least 6.5 s".
    store = EpisodeStore(tmp_path / "data")
    draft = store.begin(rig="test", task="pick", operator="alice", start_ns=_T0)
    with McapLog(draft.mcap_path, flush_interval_s=60.0) as log:
        log.write_json("telerig/v1/test/recorder/alerts", b'{"code": "stream_stalled"}', log_time_ns=_T0)
        for i in range(150):
            t = _T0 + i * 10_000_000
            log.write(_JOINTS, _joint_state(i), log_time_ns=t, publish_time_ns=t)
    manifest = repair(store, draft.id, min_idle_s=0)
    assert manifest.reason is not None
    assert "lost at least 0.0 s" in manifest.reason
