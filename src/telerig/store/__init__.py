"""Episode store: drafts committed atomically, manifests, the index database, object storage, uploads."""

from telerig.store.episodes import EpisodeDraft, EpisodeManifest, EpisodeStore, EpisodeSummary
from telerig.store.index import EpisodeIndex, EpisodeRecord, IndexStatus
from telerig.store.remote import RemoteConfig, open_store
from telerig.store.upload import EpisodeUploader, StationLoad, UploadPolicy, UploadQueue, UploadResult

__all__ = [
    "EpisodeDraft",
    "EpisodeIndex",
    "EpisodeManifest",
    "EpisodeRecord",
    "EpisodeStore",
    "EpisodeSummary",
    "EpisodeUploader",
    "IndexStatus",
    "RemoteConfig",
    "StationLoad",
    "UploadPolicy",
    "UploadQueue",
    "UploadResult",
    "open_store",
]
