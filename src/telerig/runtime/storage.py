"""A station's storage: the episode store, the index database, deferred uploads to object storage and
the quality gates run after each commit."""

from __future__ import annotations

from concurrent.futures import Future
from pathlib import Path

from telerig.config.qa import QaThresholds
from telerig.config.schema import StorageConfig
from telerig.qa.checker import QaOutcome
from telerig.runtime.qa_worker import QaWorker, outcome_or_none
from telerig.store.episodes import EpisodeManifest, EpisodeStore
from telerig.store.fingerprint import RigFingerprint, check_compatible
from telerig.store.index import EpisodeIndex
from telerig.store.remote import RemoteConfig, open_store
from telerig.store.upload import EpisodeUploader, RateLimiter, UploadQueue, UploadResult

__all__ = ["StationStorage"]


class StationStorage:
    """Where a station's episodes go and how they are found again.

    The constructor has no side effects; :meth:`open` checks the data root holds episodes of a
    compatible rig, opens the index and, when the rig names object storage, starts the upload queue.

    Args:
        root: The data root.
        config: The rig's ``storage`` section.
        fingerprint: The rig's fingerprint (episodes of an incompatible rig are refused).
        qa: The rig's ``qa`` section: with ``after_commit``, each committed episode goes through
            the quality gates in a low-priority background process (:class:`QaWorker`); ``None``
            runs none.
    """

    def __init__(
        self,
        root: Path,
        config: StorageConfig,
        fingerprint: RigFingerprint,
        qa: QaThresholds | None = None,
    ) -> None:
        self.store = EpisodeStore(root)
        self._config = config
        self._qa_config = qa
        self.fingerprint = fingerprint
        self.index: EpisodeIndex | None = None
        self.uploads: UploadQueue | None = None
        self.qa: QaWorker | None = None
        #: Each episode submitted to the gates, by id: its outcome once they ran.
        self.qa_checks: dict[str, Future[QaOutcome]] = {}

    @property
    def root(self) -> Path:
        return self.store.root

    def open(self) -> None:
        """Refuse an incompatible data root, then open the index and the upload queue."""
        # Refuse to silently mix episodes of an incompatible rig into one data root.
        check_compatible(self.store, self.fingerprint)
        config = self._config
        self.index = index = EpisodeIndex.open(config.index or self.store.root)
        if self._qa_config is not None and self._qa_config.after_commit:
            self.qa = QaWorker(self.store.root, self._qa_config, index_target=config.index or self.store.root)
            self.qa.start()  # its process starts and imports the gates now, not after the first episode
        if config.remote is None or config.upload == "off":
            return
        remote = open_store(RemoteConfig(url=config.remote, endpoint_url=config.endpoint_url))
        limiter = RateLimiter(config.bandwidth_mb_s * 1e6) if config.bandwidth_mb_s else None
        uploader = EpisodeUploader(remote, self.store.root / ".uploads", limiter=limiter)

        def uploaded(result: UploadResult) -> None:
            index.set_location(result.episode_id, result.url)

        self.uploads = UploadQueue(self.store.root, uploader, on_uploaded=uploaded)
        self.uploads.start()

    def pause_uploads(self) -> None:
        """Before an episode: uploads pause, and so do the quality gates unless they run under
        ``SCHED_IDLE`` (``qa.while_recording``), where they take only CPU time nobody else wants."""
        if self.uploads is not None:
            self.uploads.pause()
        if self.qa is not None:
            self.qa.pause()

    def directory(self, manifest: EpisodeManifest) -> Path:
        """Where a finished episode lies."""
        partition = "incomplete" if manifest.status == "incomplete" else "episodes"
        return self.store.root / partition / manifest.id

    def archive(self, manifest: EpisodeManifest) -> Path:
        """Index the finished episode and queue a committed one for upload (uploads resume); returns its
        directory."""
        directory = self.directory(manifest)
        if self.qa is not None:
            self.qa.resume()  # first: a check paused inside an index transaction holds its lock
        if self.index is not None:
            self.index.upsert_episode(manifest, location=directory)
        if self.uploads is not None:
            if manifest.status == "complete":
                self.uploads.submit(directory, now=self._config.upload == "now")
            self.uploads.resume()
        if self.qa is not None and manifest.status == "complete":
            self.qa_checks[manifest.id] = self.qa.submit(manifest.id)
        return directory

    def qa_outcome(self, episode_id: str, timeout_s: float = 0.0) -> QaOutcome | None:
        """The gates' outcome on an episode, waiting up to ``timeout_s`` [s]; ``None`` when they did not
        run (yet), failed or were cut short (``telerig qa`` then checks it)."""
        future = self.qa_checks.get(episode_id)
        return None if future is None else outcome_or_none(future, timeout_s)

    def close(self) -> None:
        """Stop the uploads, close the index. Idempotent."""
        uploads, index, qa = self.uploads, self.index, self.qa
        self.uploads = self.index = self.qa = None
        try:
            if qa is not None:
                qa.close()
            if uploads is not None:
                uploads.close()
        finally:
            if index is not None:
                index.close()
