"""Episode upload: verified, resumable without resending parts, checksum errors, policy, persistent queue."""

from __future__ import annotations

import hashlib
import json
import random
import threading
from collections.abc import Sequence
from pathlib import Path

import pytest

from telerig.store.episodes import EpisodeStore
from telerig.store.remote import (
    ChecksumMismatchError,
    LocalObjectStore,
    ObjectStore,
    RemoteConfig,
    S3ObjectStore,
    UploadError,
)
from telerig.store.upload import (
    EpisodeUploader,
    Later,
    Now,
    RateLimiter,
    StationLoad,
    UploadEvent,
    UploadPolicy,
    UploadQueue,
    UploadResult,
    episode_size,
)

_MiB = 1 << 20
_PART = 64 * 1024  # multipart part size [bytes]; the moto server accepts parts this small
_T0 = 1_700_000_000.0  # Unix time [s]
_IDLE = StationLoad(cpu_percent=5.0, memory_percent=30.0, net_sent_bytes_per_s=1e3, net_recv_bytes_per_s=1e3)
_BUSY_CPU = StationLoad(
    cpu_percent=95.0, memory_percent=30.0, net_sent_bytes_per_s=1e3, net_recv_bytes_per_s=1e3
)


class CountingStore(ObjectStore):
    """Wraps a store and records every part and whole object sent (a fake the uploader is given)."""

    def __init__(self, inner: ObjectStore) -> None:
        self.inner = inner
        self.min_part_size = inner.min_part_size
        self.etag_is_md5 = inner.etag_is_md5
        self.sent: list[tuple[str, int]] = []

    @property
    def url(self) -> str:
        return self.inner.url

    def check(self) -> None:
        self.inner.check()

    def head(self, key: str):  # type: ignore[no-untyped-def]
        return self.inner.head(key)

    def put(self, key: str, data: bytes, *, sha256: str) -> str:
        self.sent.append((key, 0))
        return self.inner.put(key, data, sha256=sha256)

    def begin_multipart(self, key: str, *, sha256: str) -> str:
        return self.inner.begin_multipart(key, sha256=sha256)

    def list_parts(self, key: str, upload_id: str) -> dict[int, str] | None:
        return self.inner.list_parts(key, upload_id)

    def put_part(self, key: str, upload_id: str, number: int, data: bytes) -> str:
        self.sent.append((key, number))
        return self.inner.put_part(key, upload_id, number, data)

    def complete_multipart(self, key: str, upload_id: str, parts: Sequence[tuple[int, str]]) -> None:
        self.inner.complete_multipart(key, upload_id, parts)

    def abort_multipart(self, key: str, upload_id: str) -> None:
        self.inner.abort_multipart(key, upload_id)

    def read_sha256(self, key: str) -> str:
        return self.inner.read_sha256(key)


def _episode(root: Path, sizes: dict[str, int], seed: int = 0) -> Path:
    """A committed episode with files of the given sizes [bytes] of seeded random content."""
    rng = random.Random(seed)
    draft = EpisodeStore(root).begin(rig="demo", task="pick", operator="alice", start_ns=int(_T0 * 1e9))
    for rel, size in sizes.items():
        path = draft.dir / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(rng.randbytes(size))
    draft.commit()
    return draft.dir


_SIZES = {"episode.mcap": 2 * _PART + 123, "cameras/wrist.mp4": 30_000, "cameras/top.mp4": 0}


def _uploader(store: ObjectStore, root: Path, **kw: object) -> EpisodeUploader:
    return EpisodeUploader(store, root / ".uploads", part_size=_PART, multipart_threshold=_PART, **kw)  # type: ignore[arg-type]


class _StopAfter:
    """Progress hook that fails the upload after ``n`` parts of episode.mcap were sent (an injected crash)."""

    def __init__(self, n: int) -> None:
        self.n = n
        self.seen = 0

    def __call__(self, event: UploadEvent) -> None:
        if event.sent and event.path == "episode.mcap":
            self.seen += 1
            if self.seen == self.n:
                raise RuntimeError("injected crash")


def _remote_sha256(moto: object, config: RemoteConfig, key: str) -> str:
    bucket, prefix = config.url.removeprefix("s3://").split("/", 1)
    body = moto.client().get_object(Bucket=bucket, Key=f"{prefix}/{key}")["Body"].read()
    return hashlib.sha256(body).hexdigest()


# -- upload --------------------------------------------------------------------------------------


def test_upload_to_s3_stores_every_file_and_verifies(
    tmp_path: Path, s3_config: RemoteConfig, moto_s3: object
) -> None:
    ep = _episode(tmp_path, _SIZES)
    uploader = _uploader(S3ObjectStore(s3_config), tmp_path)

    result = uploader.upload(ep)

    assert result.url == f"{s3_config.url}/{ep.name}"
    assert result.files == 4
    assert result.parts_skipped == 0
    assert result.bytes_sent == result.bytes_total == episode_size(ep) + (ep / "manifest.json").stat().st_size
    manifest = json.loads((ep / "manifest.json").read_text())
    for f in manifest["files"]:
        assert _remote_sha256(moto_s3, s3_config, f"{ep.name}/{f['path']}") == f["sha256"]
    assert (
        _remote_sha256(moto_s3, s3_config, f"{ep.name}/manifest.json")
        == hashlib.sha256((ep / "manifest.json").read_bytes()).hexdigest()
    )


def test_upload_to_a_local_directory_mirrors_the_episode(tmp_path: Path) -> None:
    ep = _episode(tmp_path / "data", _SIZES)
    result = _uploader(LocalObjectStore(tmp_path / "archive"), tmp_path / "data").upload(ep)
    copy = tmp_path / "archive" / ep.name
    assert result.url == copy.as_uri()
    for rel in [*_SIZES, "manifest.json"]:
        assert (copy / rel).read_bytes() == (ep / rel).read_bytes()


def test_uploading_twice_sends_nothing_the_second_time(tmp_path: Path, s3_config: RemoteConfig) -> None:
    ep = _episode(tmp_path, _SIZES)
    _uploader(S3ObjectStore(s3_config), tmp_path).upload(ep)
    counting = CountingStore(S3ObjectStore(s3_config))
    again = _uploader(counting, tmp_path).upload(ep)
    assert counting.sent == []
    assert again.bytes_sent == 0


def test_interrupted_upload_resumes_without_resending_stored_parts(
    tmp_path: Path, s3_config: RemoteConfig
) -> None:
    ep = _episode(tmp_path, _SIZES)
    first = CountingStore(S3ObjectStore(s3_config))
    with pytest.raises(RuntimeError, match="injected crash"):
        _uploader(first, tmp_path, progress=_StopAfter(2)).upload(ep)
    assert [n for key, n in first.sent if key.endswith("episode.mcap")] == [1, 2]

    second = CountingStore(S3ObjectStore(s3_config))
    result = _uploader(second, tmp_path).upload(ep)

    assert not set(first.sent) & set(second.sent)
    assert result.parts_skipped == len(first.sent)  # two whole small files and two parts
    assert result.parts_sent == len(second.sent)


def test_a_part_stored_but_missing_from_the_journal_is_not_resent(
    tmp_path: Path, s3_config: RemoteConfig
) -> None:
    ep = _episode(tmp_path, _SIZES)
    first = CountingStore(S3ObjectStore(s3_config))
    uploader = _uploader(first, tmp_path, progress=_StopAfter(2))
    with pytest.raises(RuntimeError, match="injected crash"):
        uploader.upload(ep)
    journal = uploader.journal_path(ep.name)
    lines = journal.read_text().splitlines(keepends=True)
    assert json.loads(lines[-1])["op"] == "part"
    journal.write_text("".join(lines[:-1]))  # crash between the store's reply and the journal write

    second = CountingStore(S3ObjectStore(s3_config))
    _uploader(second, tmp_path).upload(ep)
    assert not set(first.sent) & set(second.sent)


def test_local_file_changed_after_commit_is_a_checksum_mismatch(
    tmp_path: Path, s3_config: RemoteConfig
) -> None:
    ep = _episode(tmp_path, _SIZES)
    mcap = ep / "episode.mcap"
    data = bytearray(mcap.read_bytes())
    data[-1] ^= 0xFF  # same size, different content
    mcap.write_bytes(bytes(data))
    store = S3ObjectStore(s3_config)
    with pytest.raises(ChecksumMismatchError, match=r"episode\.mcap does not match its manifest sha256"):
        _uploader(store, tmp_path).upload(ep)
    assert store.head(f"{ep.name}/episode.mcap") is None  # the multipart upload was aborted


def test_damaged_remote_object_is_detected_and_sent_again(
    tmp_path: Path, s3_config: RemoteConfig, moto_s3: object
) -> None:
    ep = _episode(tmp_path, _SIZES)
    uploader = _uploader(S3ObjectStore(s3_config), tmp_path)
    uploader.upload(ep)
    wrist = ep / "cameras" / "wrist.mp4"
    sha = hashlib.sha256(wrist.read_bytes()).hexdigest()
    bucket, prefix = s3_config.url.removeprefix("s3://").split("/", 1)
    # Same size and the right sha256 metadata, wrong bytes: only the ETag / read-back can tell.
    moto_s3.client().put_object(
        Bucket=bucket, Key=f"{prefix}/{ep.name}/cameras/wrist.mp4", Body=b"\0" * wrist.stat().st_size,
        Metadata={"sha256": sha},
    )  # fmt: skip

    with pytest.raises(ChecksumMismatchError, match=r"cameras/wrist\.mp4"):
        uploader.verify(ep)
    counting = CountingStore(S3ObjectStore(s3_config))
    _uploader(counting, tmp_path).upload(ep)
    assert counting.sent == [(f"{ep.name}/cameras/wrist.mp4", 0)]
    assert _remote_sha256(moto_s3, s3_config, f"{ep.name}/cameras/wrist.mp4") == sha


def test_uploading_a_draft_is_refused(tmp_path: Path) -> None:
    draft = EpisodeStore(tmp_path).begin(rig="demo", task="pick", operator="alice")
    with pytest.raises(UploadError, match="still recording; commit it"):
        _uploader(LocalObjectStore(tmp_path / "archive"), tmp_path).upload(draft.dir)


def test_bandwidth_limit_paces_parts(tmp_path: Path) -> None:
    ep = _episode(tmp_path, _SIZES)
    waits: list[float] = []
    limiter = RateLimiter(_MiB, clock=lambda: 0.0, sleep=waits.append)
    _uploader(LocalObjectStore(tmp_path / "archive"), tmp_path, limiter=limiter).upload(ep)
    # In path order: top.mp4 (0 B) and wrist.mp4 (30 kB) go at once, then the 3 parts of the
    # mcap each wait until everything before them would have gone at 1 MiB/s.
    assert waits[:3] == pytest.approx([30_000 / _MiB, (30_000 + _PART) / _MiB, (30_000 + 2 * _PART) / _MiB])


# -- policy --------------------------------------------------------------------------------------

_POLICY = UploadPolicy(uplink_bytes_per_s=10e6, max_now_s=60, small_bytes=16 * _MiB, retry_after_s=600)


def test_policy_uploads_a_medium_episode_now_when_idle() -> None:
    assert isinstance(_POLICY.decide(200_000_000, _IDLE, now=_T0), Now)


def test_policy_defers_a_medium_episode_when_the_cpu_is_busy() -> None:
    decision = _POLICY.decide(200_000_000, _BUSY_CPU, now=_T0)
    assert decision == Later("cpu 95% > 60%", _T0 + 600)


def test_policy_defers_when_the_network_is_busy() -> None:
    load = StationLoad(cpu_percent=5, memory_percent=30, net_sent_bytes_per_s=8e6, net_recv_bytes_per_s=1e6)
    decision = _POLICY.decide(200_000_000, load, now=_T0)
    assert isinstance(decision, Later)
    assert decision.reason.startswith("network 9.0 MB/s")


def test_policy_defers_an_episode_too_large_to_finish_before_the_next_session() -> None:
    decision = _POLICY.decide(2_000_000_000, _IDLE, now=_T0)
    assert isinstance(decision, Later)
    assert "deferred to idle time" in decision.reason
    assert decision.retry_at == _T0 + 600


def test_policy_uploads_a_small_episode_now_even_when_busy() -> None:
    assert isinstance(_POLICY.decide(1_000_000, _BUSY_CPU, now=_T0), Now)


def test_policy_defers_even_a_small_episode_when_memory_is_short() -> None:
    load = StationLoad(cpu_percent=5, memory_percent=97, net_sent_bytes_per_s=0, net_recv_bytes_per_s=0)
    assert isinstance(_POLICY.decide(1_000_000, load, now=_T0), Later)


def test_station_load_sample_measures_the_machine() -> None:
    load = StationLoad.sample(interval_s=0.05)
    assert 0 <= load.cpu_percent <= 100
    assert 0 < load.memory_percent <= 100
    assert load.net_sent_bytes_per_s >= 0
    assert load.net_recv_bytes_per_s >= 0


# -- queue ---------------------------------------------------------------------------------------


class _Clock:
    def __init__(self) -> None:
        self.t = _T0

    def __call__(self) -> float:
        return self.t


def _queue(
    root: Path,
    uploader: EpisodeUploader,
    clock: _Clock,
    loads: list[StationLoad],
    done: list[UploadResult],
    policy: UploadPolicy = _POLICY,
) -> UploadQueue:
    return UploadQueue(
        root, uploader, policy=policy, sample_load=lambda: loads[0], on_uploaded=done.append, clock=clock,
        backoff_s=30,
    )  # fmt: skip


def test_deferred_upload_survives_a_restart_and_runs_when_due_and_idle(
    tmp_path: Path, s3_config: RemoteConfig
) -> None:
    ep = _episode(tmp_path, _SIZES)
    clock, loads, done = _Clock(), [_BUSY_CPU], []
    store = S3ObjectStore(s3_config)
    policy = _POLICY.model_copy(update={"small_bytes": 0})  # the small test episode obeys the load
    queue = _queue(tmp_path, _uploader(store, tmp_path), clock, loads, done, policy)
    decision = queue.submit(ep)
    assert decision == Later("cpu 95% > 60%", _T0 + 600)
    queue.close()

    restarted = _queue(tmp_path, _uploader(store, tmp_path), clock, loads, done, policy)
    assert [(j.episode_id, j.not_before) for j in restarted.pending()] == [(ep.name, _T0 + 600)]
    assert restarted.run_pending() == []  # not due yet
    clock.t = _T0 + 601
    assert restarted.run_pending() == []  # due, but the station is still busy: waits again
    assert restarted.pending()[0].not_before == clock.t + 600
    clock.t += 601
    loads[0] = _IDLE
    results = restarted.run_pending()

    assert [r.url for r in results] == [f"{s3_config.url}/{ep.name}"]
    assert done == results
    assert _queue(tmp_path, _uploader(store, tmp_path), clock, loads, done).pending() == []


def test_failed_upload_backs_off_and_resumes_after_a_restart(tmp_path: Path, s3_config: RemoteConfig) -> None:
    ep = _episode(tmp_path, _SIZES)
    clock, loads, done = _Clock(), [_IDLE], []
    crashing = CountingStore(S3ObjectStore(s3_config))
    queue = _queue(tmp_path, _uploader(crashing, tmp_path, progress=_StopAfter(2)), clock, loads, done)
    assert isinstance(queue.submit(ep, now=True), Now)
    assert queue.run_pending() == []
    (job,) = queue.pending()
    assert (job.attempts, job.not_before) == (1, _T0 + 30)
    assert "injected crash" in job.reason
    queue.close()

    clock.t = _T0 + 31
    resumed = CountingStore(S3ObjectStore(s3_config))
    restarted = _queue(tmp_path, _uploader(resumed, tmp_path), clock, loads, done)
    assert restarted.pending()[0].attempts == 1
    (result,) = restarted.run_pending()
    assert result.parts_skipped == len(crashing.sent)
    assert not set(crashing.sent) & set(resumed.sent)


def test_background_worker_uploads_and_stops_on_close(tmp_path: Path) -> None:
    ep = _episode(tmp_path, {"episode.mcap": 1000})
    uploaded = threading.Event()
    results: list[UploadResult] = []

    def on_uploaded(result: UploadResult) -> None:
        results.append(result)
        uploaded.set()

    with UploadQueue(
        tmp_path, _uploader(LocalObjectStore(tmp_path / "archive"), tmp_path), sample_load=lambda: _IDLE,
        on_uploaded=on_uploaded, poll_s=0.05,
    ) as queue:  # fmt: skip
        queue.start()
        queue.submit(ep, now=True)
        assert uploaded.wait(20), "the worker did not upload within 20 s"
    assert results[0].url == (tmp_path / "archive" / ep.name).as_uri()
    assert queue.pending() == []


def test_an_upload_asked_for_now_does_not_wait_for_a_busy_cpu(tmp_path: Path) -> None:
    ep = _episode(tmp_path, {"episode.mcap": 1000})
    uploaded = threading.Event()
    with UploadQueue(
        tmp_path, _uploader(LocalObjectStore(tmp_path / "archive"), tmp_path), sample_load=lambda: _BUSY_CPU,
        on_uploaded=lambda _: uploaded.set(), poll_s=0.05,
    ) as queue:  # fmt: skip
        queue.start()
        queue.submit(ep, now=True)
        assert uploaded.wait(20), "an upload asked for now waited for the busy CPU"


def test_pause_stops_the_upload_between_parts_and_keeps_the_job(tmp_path: Path) -> None:
    ep = _episode(tmp_path, _SIZES)
    holder: list[UploadQueue] = []

    def pause_after_first_part(event: UploadEvent) -> None:
        if event.sent:
            holder[0].pause()

    uploader = _uploader(LocalObjectStore(tmp_path / "archive"), tmp_path, progress=pause_after_first_part)
    queue = UploadQueue(tmp_path, uploader, sample_load=lambda: _IDLE)
    holder.append(queue)
    queue.submit(ep, now=True)
    assert queue.run_pending() == []
    (job,) = queue.pending()
    assert job.attempts == 0  # a pause is not a failure
    queue.close()
