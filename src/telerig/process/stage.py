"""The stage interface of the annotation pipeline: items in, outputs with recorded provenance out.

A stage is a pure function of (item inputs, upstream outputs, settings, version). The runner
(:mod:`telerig.process.run`) gives it its own output directory per item and writes
``provenance.json`` there after it returns; a stage never writes that file itself. Re-runs compare
the stored provenance with what the stage would be run with now and skip it when they match, so a
changed stage version, settings object, input file or upstream output redoes that stage and the
stages after it, nothing else.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import os
import socket
import tempfile
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Protocol, runtime_checkable

from pydantic import BaseModel, ConfigDict, ValidationError

from telerig.errors import ProcessError

__all__ = [
    "PROVENANCE_FILE",
    "PROVENANCE_SCHEMA",
    "STAGE_ORDER",
    "Item",
    "Provenance",
    "Stage",
    "StageContext",
    "StageResult",
    "hash_upstream",
    "host_name",
    "provenance_key",
    "read_json",
    "read_provenance",
    "record_edit",
    "settings_hash",
    "video_item_id",
    "write_atomic",
    "write_json_atomic",
    "write_provenance",
]

STAGE_ORDER: tuple[str, ...] = ("filter", "segment", "clips", "annotate", "layout")
"""The default pipeline, in order; each later stage may read every earlier stage's outputs."""

PROVENANCE_FILE = "provenance.json"
PROVENANCE_SCHEMA = 1

_MAX_PROVENANCE_BYTES = 1 << 20
"""A provenance record lists a stage's outputs (a few hundred clips at most): 1 MiB is generous."""


@dataclass(frozen=True)
class Item:
    """One input: a telerig episode or one plain video file."""

    id: str
    """Episode id, or ``video-<sha1 of the absolute path>[:12]`` (see :func:`video_item_id`)."""
    kind: Literal["episode", "video"]
    videos: tuple[Path, ...]
    """Episode: its ``cameras/*.mp4`` (anchor camera first); video: ``(path,)``."""
    episode_dir: Path | None
    """The episode directory (``manifest.json``, ``episode.mcap``), else ``None``."""
    source_hash: str
    """sha256 over the input files' bytes (videos + ``episode.mcap``), hex."""
    meta: Mapping[str, Any]
    """Task, operator, robot, device id, date, fps... where known (JSON values)."""


@dataclass(frozen=True)
class StageContext:
    """What a stage gets besides its item: where to write, what came before, its settings."""

    out_dir: Path
    """This item's output directory for THIS stage (created by the runner, empty on a redo)."""
    work_root: Path
    """The ``processed/`` root (the dataset being built)."""
    upstream: Mapping[str, Path]
    """Stage name -> that stage's ``out_dir`` for this item (earlier stages only)."""
    settings: Any
    """The stage's settings object from :mod:`telerig.config.process`."""
    progress: Callable[[float], None]
    """Report progress within this item, 0..1 (cheap; call often)."""


@dataclass(frozen=True)
class StageResult:
    """What a stage reports; the runner stores it in ``provenance.json``."""

    status: Literal["ok", "empty", "failed"]
    """``empty``: nothing to keep (no hands, no actions): kept and marked, not an error."""
    outputs: tuple[str, ...]
    """Paths relative to ``out_dir``."""
    metrics: Mapping[str, float]
    """e.g. ``kept_fraction``, ``seconds_in``, ``seconds_kept``, ``segments``, ``clips``."""
    message: str = ""
    """One line: why empty or failed."""


@runtime_checkable
class Stage(Protocol):
    """One step of the pipeline; see the module docstring for the contract."""

    # Read-only members: a class attribute (``name = "filter"``) or a frozen dataclass field both fit.
    @property
    def name(self) -> str:
        """``filter`` | ``segment`` | ``clips`` | ``annotate`` | ``layout``."""
        ...

    @property
    def version(self) -> str:
        """Bump when the output would change: re-runs redo only changed stages and those after."""
        ...

    def run(self, item: Item, ctx: StageContext) -> StageResult:
        """Process ``item`` into ``ctx.out_dir``; raise (any exception) or return ``failed`` on error."""
        ...


class Provenance(BaseModel):
    """``<out_dir>/provenance.json``: what produced a stage's outputs for one item, and when."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    format: int = PROVENANCE_SCHEMA
    stage: str
    version: str
    settings_hash: str
    source_hash: str
    upstream: dict[str, str]
    """Stage name -> :func:`provenance_key` of that stage's provenance when this one ran."""
    item_id: str
    status: Literal["ok", "empty", "failed"]
    outputs: list[str]
    metrics: dict[str, float]
    message: str = ""
    started: str
    """ISO 8601 UTC wall-clock time the stage started."""
    finished: str
    """ISO 8601 UTC wall-clock time it returned."""
    host: str
    edited: str = ""
    """sha256 (hex) of a person's edit written into this stage's outputs after it ran (the review
    page's segment edits), empty when none: it is part of :func:`provenance_key`, so the stages
    after this one redo with the edit while this one's machine output is kept."""


def video_item_id(path: Path) -> str:
    """The item id of a plain video file: ``video-`` + the first 12 hex of sha1(absolute path)."""
    absolute = os.path.abspath(os.fspath(path))
    return "video-" + hashlib.sha1(absolute.encode("utf-8", "surrogateescape")).hexdigest()[:12]


def _jsonable(value: Any) -> Any:
    if isinstance(value, BaseModel):
        return value.model_dump(mode="json")
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return dataclasses.asdict(value)
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    return value


def settings_hash(settings: Any) -> str:
    """sha256 (hex) of a settings object's canonical JSON (pydantic model, dataclass, mapping, None).

    Secrets do not belong in the hash's input either way: a changed API key must not redo work,
    so settings classes keep keys out of their dumped fields (read them from the environment).
    """
    text = json.dumps(_jsonable(settings), sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def provenance_key(prov: Provenance) -> str:
    """sha256 (hex) of what identifies a stage's output: stage, version, settings, source, upstream.

    Later stages store this for each upstream stage, so a redone upstream stage whose identity
    changed redoes them too. Timestamps and host are left out: an identical redo is the same output.
    """
    ident = {
        "stage": prov.stage,
        "version": prov.version,
        "settings_hash": prov.settings_hash,
        "source_hash": prov.source_hash,
        "upstream": dict(sorted(prov.upstream.items())),
        "status": prov.status,
        "outputs": sorted(prov.outputs),
    }
    if prov.edited:  # only when set: keys of unedited outputs stay what they were
        ident["edited"] = prov.edited
    return hashlib.sha256(json.dumps(ident, sort_keys=True).encode()).hexdigest()


def hash_upstream(upstream: Mapping[str, Provenance]) -> dict[str, str]:
    """Stage name -> :func:`provenance_key`, for :attr:`Provenance.upstream`."""
    return {name: provenance_key(prov) for name, prov in upstream.items()}


def host_name() -> str:
    """This machine's name, for provenance (which worker of a cluster produced an output)."""
    return socket.gethostname()


def write_atomic(path: Path, data: bytes | str) -> Path:
    """Write ``path`` atomically: a temp file in the same directory, fsync, ``os.replace``.

    A crash leaves either the old file or the new one, never half of one.

    Raises:
        ProcessError: It cannot be written (disk full, permissions, no such directory).
    """
    path = Path(path)
    payload = data.encode("utf-8") if isinstance(data, str) else data
    try:
        fd, tmp = tempfile.mkstemp(prefix="." + path.name[:64] + ".", suffix=".tmp", dir=path.parent)
    except OSError as exc:
        raise ProcessError(f"cannot write {path}: {exc.strerror or exc}") from None
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(payload)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except OSError as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise ProcessError(f"cannot write {path}: {exc.strerror or exc}") from None
    return path


def write_json_atomic(path: Path, obj: Any) -> Path:
    """Write ``obj`` as indented JSON (UTF-8, sorted keys) with :func:`write_atomic`."""
    return write_atomic(path, json.dumps(_jsonable(obj), indent=2, sort_keys=True) + "\n")


def read_json(path: Path, *, max_bytes: int, what: str) -> Any:
    """Parse a JSON file written by the pipeline, bounded in size.

    Args:
        path: The file.
        max_bytes: Larger files are refused before parsing.
        what: What the file is, for the message (``a segments file``).

    Raises:
        ProcessError: Missing, unreadable, too large or not JSON (one line naming the file).
    """
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > max_bytes:
            raise ProcessError(f"{path} is {size} bytes, more than {max_bytes} for {what}")
        with open(path, "rb") as f:
            raw = f.read(max_bytes + 1)
    except OSError as exc:
        raise ProcessError(f"cannot read {what} {path}: {exc.strerror or exc}") from None
    try:
        return json.loads(raw)
    except (ValueError, RecursionError) as exc:
        raise ProcessError(f"{path} is not {what} (invalid JSON: {str(exc).splitlines()[0]})") from None


def read_provenance(out_dir: Path) -> Provenance | None:
    """The provenance record in ``out_dir``; ``None`` when the stage has not finished there.

    Raises:
        ProcessError: The file exists but is unreadable, too large or not a provenance record
            (one line; the runner logs it and redoes the stage).
    """
    path = Path(out_dir) / PROVENANCE_FILE
    if not path.is_file():
        return None
    raw = read_json(path, max_bytes=_MAX_PROVENANCE_BYTES, what="a provenance record")
    try:
        return Provenance.model_validate(raw)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"]) or "document"
        raise ProcessError(f"{path} is not a provenance record ({where}: {first['msg']})") from None


def record_edit(out_dir: Path, content: bytes) -> bool:
    """Note in ``out_dir``'s provenance that a person edited its outputs (``content``: the edited
    file's new bytes), so the next run redoes the later stages from the edit; ``False`` when the
    stage has not finished there (nothing to note: its first run reads the edit anyway).

    Raises:
        ProcessError: The provenance record is unreadable (one line).
    """
    prov = read_provenance(out_dir)
    if prov is None:
        return False
    write_provenance(out_dir, prov.model_copy(update={"edited": hashlib.sha256(content).hexdigest()}))
    return True


def write_provenance(out_dir: Path, prov: Provenance) -> Path:
    """Write ``<out_dir>/provenance.json`` atomically (the runner's job, never a stage's)."""
    text = prov.model_dump_json(indent=2) + "\n"
    return write_atomic(Path(out_dir) / PROVENANCE_FILE, text)
