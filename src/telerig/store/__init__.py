"""Episode store: drafts committed atomically, manifests, listing."""

from telerig.store.episodes import EpisodeDraft, EpisodeManifest, EpisodeStore, EpisodeSummary

__all__ = ["EpisodeDraft", "EpisodeManifest", "EpisodeStore", "EpisodeSummary"]
