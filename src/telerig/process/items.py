"""What ``telerig process`` reads: telerig episodes and plain folders of video, as :class:`Item` s.

An episode's source hash comes from its manifest (every committed file's sha256 is recorded there
and never changes), so it costs nothing. A plain video is hashed once, streamed in 1 MiB blocks, and
the digest is cached in the processed root by (path, size, mtime): a re-run over hours of footage
does not read it again. Inputs that cannot be read (an unreadable file, a broken link, an episode
with a damaged manifest) are reported as :class:`Skipped` with a one-line reason, never raised:
one bad file must not stop a batch.
"""

from __future__ import annotations

import datetime
import hashlib
import json
import logging
import os
import re
import stat
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from telerig.errors import ProcessError, RecordingError
from telerig.process.stage import Item, video_item_id, write_json_atomic
from telerig.store.episodes import EpisodeStore, EpisodeSummary
from telerig.store.manifest_extra import EpisodeExtra

__all__ = [
    "VIDEO_SUFFIXES",
    "Discovery",
    "EpisodeQuery",
    "HashCache",
    "Skipped",
    "discover",
    "episode_items",
    "is_data_root",
    "parse_query",
    "video_items",
]

_log = logging.getLogger("telerig.process.items")

VIDEO_SUFFIXES: frozenset[str] = frozenset({".mp4", ".mov", ".mkv", ".webm"})
"""File suffixes (lower case) taken as video in a plain folder."""

_BLOCK = 1 << 20
_CACHE_FILE = "hashes.json"
_MAX_CACHE_BYTES = 64 << 20
"""A cache entry is ~200 bytes: 64 MiB holds ~300k videos; a larger file is not ours and is ignored."""
_MAX_DEPTH = 64
"""Deepest folder level searched for videos (a real tree is < 10; deeper is a mistake or a trap)."""
_QUERY_KEYS = ("task", "operator", "rig", "partition")


@dataclass(frozen=True)
class Skipped:
    """An input that was not made into an item: ``path`` and the one-line ``reason``."""

    path: str
    reason: str


@dataclass(frozen=True)
class Discovery:
    """The items found for one ``telerig process`` argument, and the inputs skipped."""

    items: tuple[Item, ...]
    skipped: tuple[Skipped, ...]
    data_root: Path | None
    """The episode store root when the input was episodes (the default output goes under it)."""


@dataclass(frozen=True)
class EpisodeQuery:
    """Which episodes of a store to process (every given field must match).

    Attributes:
        ids: Only these episode ids (full ids or unique prefixes).
        task: Exact task.
        operator: Exact operator id.
        rig: Exact rig name.
        partition: ``episodes`` or ``failures`` only; both when ``None`` (a gate's rejection is
            often exactly what annotation should look at).
    """

    ids: tuple[str, ...] = ()
    task: str | None = None
    operator: str | None = None
    rig: str | None = None
    partition: str | None = None

    def matches(self, episode: EpisodeSummary) -> bool:
        """Whether ``episode`` passes every given field (ids are resolved before)."""
        return (
            (self.task is None or episode.task == self.task)
            and (self.operator is None or episode.operator == self.operator)
            and (self.rig is None or episode.rig == self.rig)
            and (self.partition is None or episode.partition == self.partition)
        )


@dataclass
class HashCache:
    """sha256 of files by (absolute path, size, mtime_ns), kept in ``<processed>/.cache/hashes.json``.

    A changed size or modification time rehashes the file. A damaged cache file is ignored (and
    rewritten): it only costs time.
    """

    path: Path | None
    entries: dict[str, dict[str, Any]] = field(default_factory=dict)
    dirty: bool = False

    @classmethod
    def open(cls, cache_dir: Path | None) -> HashCache:
        """The cache in ``cache_dir`` (``None``: in memory only)."""
        if cache_dir is None:
            return cls(None)
        path = Path(cache_dir) / _CACHE_FILE
        entries: dict[str, dict[str, Any]] = {}
        try:
            if path.is_file() and path.stat().st_size <= _MAX_CACHE_BYTES:
                raw = json.loads(path.read_bytes())
                if isinstance(raw, dict):
                    entries = {k: v for k, v in raw.items() if isinstance(v, dict)}
        except (OSError, ValueError, RecursionError) as exc:
            _log.warning("ignoring the hash cache %s (%s); videos are hashed again", path, exc)
        return cls(path, entries)

    def sha256(self, path: Path) -> str:
        """The file's sha256 (hex), from the cache when its size and mtime are unchanged.

        Raises:
            OSError: The file cannot be read.
        """
        key = os.path.abspath(path)
        st = os.stat(key)
        hit = self.entries.get(key)
        if hit is not None and hit.get("size") == st.st_size and hit.get("mtime_ns") == st.st_mtime_ns:
            digest = hit.get("sha256")
            if isinstance(digest, str) and len(digest) == 64:
                return digest
        digest = _sha256_file(Path(key))
        self.entries[key] = {"size": st.st_size, "mtime_ns": st.st_mtime_ns, "sha256": digest}
        self.dirty = True
        return digest

    def save(self) -> None:
        """Write the cache if anything was added (atomically; a failure only logs)."""
        if self.path is None or not self.dirty:
            return
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            write_json_atomic(self.path, self.entries)
            self.dirty = False
        except (OSError, ProcessError) as exc:
            _log.warning("cannot save the hash cache %s: %s", self.path, exc)


def _sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(_BLOCK):
            h.update(block)
    return h.hexdigest()


def is_data_root(path: Path) -> bool:
    """Whether ``path`` looks like an episode store root (has ``episodes/`` or ``failures/``)."""
    return (path / "episodes").is_dir() or (path / "failures").is_dir()


def parse_query(text: str) -> EpisodeQuery:
    """``task=pick,operator=ann`` (comma or space separated ``KEY=VALUE``) as a query.

    Raises:
        ProcessError: An unknown key or a term without ``=`` (the message lists the keys).
    """
    fields: dict[str, str] = {}
    ids: list[str] = []
    for term in re.split(r"[,\s]+", text.strip()):
        if not term:
            continue
        key, sep, value = term.partition("=")
        if not sep:
            ids.append(term)
            continue
        if key == "id":
            ids.append(value)
        elif key in _QUERY_KEYS and value:
            fields[key] = value
        else:
            raise ProcessError(
                f"query term {term[:80]!r}: expected KEY=VALUE with KEY one of id, {', '.join(_QUERY_KEYS)}"
            )
    if fields.get("partition") not in (None, "episodes", "failures"):
        raise ProcessError(f"query partition={fields['partition'][:40]!r}: use episodes or failures")
    return EpisodeQuery(ids=tuple(ids), **fields)


def episode_items(root: Path, query: EpisodeQuery) -> tuple[list[Item], list[Skipped]]:
    """The committed episodes of the store at ``root`` (``episodes`` and ``failures``) that match.

    Raises:
        ProcessError: An id in the query names no episode (or several), with the candidates.
    """
    store = EpisodeStore(root)
    chosen: list[EpisodeSummary] = []
    if query.ids:
        for episode_id in query.ids:
            try:
                chosen.append(store.find(episode_id))
            except RecordingError as exc:
                raise ProcessError(str(exc)) from None
    else:
        chosen = store.list(include_failures=True)
    items: list[Item] = []
    skipped: list[Skipped] = []
    seen: set[str] = set()
    for summary in chosen:
        if summary.id in seen or not query.matches(summary):
            continue
        seen.add(summary.id)
        try:
            items.append(_episode_item(store, summary))
        except (RecordingError, ProcessError) as exc:
            skipped.append(Skipped(str(summary.path), str(exc)))
    return items, skipped


def _episode_item(store: EpisodeStore, summary: EpisodeSummary) -> Item:
    manifest = store.get(summary.id)
    extra = EpisodeExtra.of(manifest)
    files = {f.path: f for f in manifest.files}
    cameras = sorted(p for p in files if p.startswith("cameras/") and p.endswith(".mp4"))
    # The anchor camera is the first camera key in sorted order, as in the exports' frame grid.
    h = hashlib.sha256()
    for path in [*cameras, "episode.mcap"]:
        entry = files.get(path)
        if entry is not None:
            h.update(f"{path}\0{entry.size}\0{entry.sha256}\n".encode())
    anchor = Path(cameras[0]).stem if cameras else None
    record = extra.cameras.get(anchor) if anchor is not None else None
    meta: dict[str, Any] = {
        "task": manifest.task,
        "operator": manifest.operator,
        "rig": manifest.rig,
        "robots": list(extra.robots),
        "device_id": extra.station or manifest.rig,
        "date": _iso(manifest.start_ns),
        "start_ns": manifest.start_ns,
        "duration_s": manifest.duration_s,
        "partition": summary.partition,
        "cameras": [Path(c).stem for c in cameras],
        "anchor_camera": anchor,
        "fps": record.fps if record is not None else None,
        "outcome": extra.outcome,
    }
    return Item(
        id=manifest.id,
        kind="episode",
        videos=tuple(summary.path / c for c in cameras),
        episode_dir=summary.path,
        source_hash=h.hexdigest(),
        meta=meta,
    )


def video_items(
    folder: Path, cache: HashCache, *, on_file: Callable[[Path], None] | None = None
) -> tuple[list[Item], list[Skipped]]:
    """Every video under ``folder`` (recursive; links to folders are not followed, so a link loop
    cannot trap the walk), or the one file when ``folder`` is a video file, sorted by path.

    Args:
        folder: A folder, or a single video file.
        cache: Where digests are cached.
        on_file: Called before each file is hashed (progress).
    """
    items: list[Item] = []
    skipped: list[Skipped] = []
    for path in _video_paths(Path(folder), skipped):
        if on_file is not None:
            on_file(path)
        try:
            st = path.stat()
            if not stat.S_ISREG(st.st_mode):
                raise ProcessError("not a regular file")
            digest = cache.sha256(path)
        except (OSError, ProcessError) as exc:
            reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
            skipped.append(Skipped(_shown(path), f"cannot read: {reason}"))
            continue
        items.append(
            Item(
                id=video_item_id(path),
                kind="video",
                videos=(Path(os.path.abspath(path)),),
                episode_dir=None,
                source_hash=digest,
                meta={
                    "name": path.name,
                    "path": os.path.abspath(path),
                    "size": st.st_size,
                    "date": _iso(st.st_mtime_ns),
                    "device_id": path.parent.name or None,
                },
            )
        )
    return items, skipped


def _video_paths(folder: Path, skipped: list[Skipped]) -> Iterator[Path]:
    if folder.is_file():
        if folder.suffix.lower() in VIDEO_SUFFIXES:
            yield folder
        else:
            skipped.append(Skipped(_shown(folder), f"not a video ({', '.join(sorted(VIDEO_SUFFIXES))})"))
        return
    found: list[Path] = []
    base_depth = len(folder.parts)

    def _error(exc: OSError) -> None:
        skipped.append(Skipped(_shown(Path(exc.filename or folder)), f"cannot list: {exc.strerror or exc}"))

    for dirpath, dirnames, filenames in os.walk(folder, onerror=_error, followlinks=False):
        here = Path(dirpath)
        if len(here.parts) - base_depth >= _MAX_DEPTH:
            skipped.append(Skipped(_shown(here), f"deeper than {_MAX_DEPTH} folders; not searched"))
            dirnames.clear()
            continue
        # Never walk into the pipeline's own output (a processed/ folder inside the input folder).
        dirnames[:] = sorted(d for d in dirnames if not d.startswith(".") and not _processed_root(here / d))
        for name in filenames:
            if Path(name).suffix.lower() in VIDEO_SUFFIXES and not name.startswith("."):
                found.append(here / name)
    yield from sorted(found)


def _processed_root(path: Path) -> bool:
    """A pipeline output folder (``processed/``, or any ``--out`` with the runner's lock and items):
    its clips must not come back as inputs."""
    return path.name == "processed" or ((path / ".lock").is_file() and (path / "items").is_dir())


def _shown(path: Path) -> str:
    """A path for a one-line message: at most 200 characters, undecodable bytes escaped."""
    text = os.fsdecode(path).encode("utf-8", "backslashreplace").decode("utf-8")
    return text if len(text) <= 200 else text[:90] + "..." + text[-90:]


def _iso(ns: int) -> str:
    return datetime.datetime.fromtimestamp(ns / 1e9, tz=datetime.UTC).isoformat(timespec="seconds")


def discover(target: str, *, data_root: Path | None = None, cache_dir: Path | None = None) -> Discovery:
    """The items named by ``telerig process``'s argument.

    ``target`` is, in this order: a data root (a folder with ``episodes/`` or ``failures/``; every
    committed episode), an episode directory, a video file or a folder of videos, an episode id (or
    unique prefix) in ``data_root``, or a query ``KEY=VALUE[,KEY=VALUE]`` over ``data_root``
    (keys ``id``, ``task``, ``operator``, ``rig``, ``partition``).

    Raises:
        ProcessError: Nothing of that name exists (one line with what was looked for).
    """
    path = Path(target)
    cache = HashCache.open(cache_dir)
    try:
        if path.is_dir() and is_data_root(path):
            items, skipped = episode_items(path, EpisodeQuery())
            return Discovery(tuple(items), tuple(skipped), path)
        if path.is_dir() and (path / "manifest.json").is_file() and is_data_root(path.parent.parent):
            items, skipped = episode_items(path.parent.parent, EpisodeQuery(ids=(path.name,)))
            return Discovery(tuple(items), tuple(skipped), path.parent.parent)
        if path.exists():
            v_items, v_skipped = video_items(path, cache)
            return Discovery(tuple(v_items), tuple(v_skipped), None)
    except OSError as exc:
        raise ProcessError(f"cannot read {_shown(path)}: {exc.strerror or exc}") from None
    finally:
        cache.save()
    root = Path(data_root) if data_root is not None else None
    if root is None or not is_data_root(root):
        where = f"; {root} is not a data root (no episodes/ or failures/)" if root is not None else ""
        raise ProcessError(
            f"{_shown(path)} is not a file, folder, data root or episode{where}; give a folder of "
            "videos, a data root, or an episode id / query with --data-root"
        )
    query = parse_query(target) if "=" in target else EpisodeQuery(ids=(target,))
    items, skipped = episode_items(root, query)
    return Discovery(tuple(items), tuple(skipped), root)
