"""Stage 4, vision-language annotation: each clip described as objects, scene and action, in JSON.

With a model configured (:class:`~telerig.config.process.AnnotateSettings`), each clip of the
``clips`` stage goes to an OpenAI-compatible endpoint (:mod:`telerig.process.vlm`) as evenly spaced
JPEG stills (or the MP4 itself), answers are cached under ``<processed>/cache/annotate`` by clip
bytes, model and prompt, and tokens and cost are totalled. Without one, the offline annotator fills
what the item's metadata (task, robot, operator) and the segment label tell, marked
``offline: true``. Output: ``annotations.json`` (:data:`ANNOTATIONS_FILE`), read back with
:func:`read_annotations`::

    {"schema": 1, "model": "qwen2.5-vl" | null, "offline": false, "prompt_version": "1",
     "clips": {"<clip uuid = segment id>": {
         "status": "ok" | "failed", "error": "" | "<one line>",
         "objects": [{"name", "quantity", "attributes": [...]}],
         "scene": "lab" | "factory_floor" | ... | "other" | null (failed),
         "action": {"description", "agent", "objects": [...], "interaction"} | null (failed),
         "model", "offline", "cached", "tokens": {"prompt", "completion"}, "cost_usd",
         "known": {"task", "robot", "operator", "label", "rig"}   (offline records only)}},
     "usage": {"clips", "annotated", "failed", "cached", "dropped_entries", "requests", "retries",
               "backoff_s", "prompt_tokens", "completion_tokens", "cost_usd"}}

Tokens and cost of a record are what its answer cost when it was asked (a cached record repeats
them); ``usage`` counts only this run's requests.
"""

from __future__ import annotations

import hashlib
import importlib
import logging
from collections.abc import Iterator, Mapping
from concurrent.futures import ThreadPoolExecutor, as_completed
from fractions import Fraction
from pathlib import Path
from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, StringConstraints, ValidationError

from telerig.config.process import SCENE_TYPES, AnnotateSettings
from telerig.errors import DependencyError, ProcessError, RecordingError
from telerig.process.stage import Item, StageContext, StageResult, read_json, write_json_atomic
from telerig.process.vlm import (
    PROMPT_VERSION,
    ClipDescription,
    Completion,
    VlmClient,
    cache_key,
    image_part,
    video_part,
)
from telerig.store.annotations_file import (
    EpisodeAnnotations,
    SegmentAnnotation,
    write_episode_annotations,
)

__all__ = [
    "ANNOTATIONS_FILE",
    "AnnotateStage",
    "AnswerCache",
    "ClipEntry",
    "offline_annotation",
    "read_annotations",
    "read_clips",
    "sample_stills",
]

_log = logging.getLogger("telerig.process.annotate")

ANNOTATIONS_FILE = "annotations.json"
ANNOTATIONS_SCHEMA = 1
_CLIPS_FILE = "clips.json"
_MAX_CLIPS_BYTES = 16 << 20
"""clips.json of a long recording: a few thousand entries of ~300 bytes; 16 MiB is far above."""
_MAX_ANNOTATIONS_BYTES = 64 << 20
_MAX_META_CHARS = 200


class ClipEntry(BaseModel):
    """One entry of the ``clips`` stage's ``clips.json`` (the fields this stage reads)."""

    model_config = ConfigDict(extra="ignore", frozen=True)

    uuid: Annotated[str, StringConstraints(pattern=r"^[0-9a-fA-F-]{8,64}$")]
    file: Annotated[str, StringConstraints(pattern=r"^[A-Za-z0-9][A-Za-z0-9._-]{0,200}$")]
    """The clip's file name inside the clips stage's directory (no path separators)."""
    video: str = Field(default="", max_length=1000)
    start_s: float = Field(default=0.0, ge=0, le=1e7)
    end_s: float = Field(default=0.0, ge=0, le=1e7)
    label: str | None = Field(default=None, max_length=_MAX_META_CHARS)


def read_clips(clips_dir: Path) -> tuple[list[ClipEntry], int]:
    """The valid entries of ``<clips_dir>/clips.json`` and how many malformed ones were dropped.

    Raises:
        ProcessError: The file is missing, too large, not JSON or not a list of entries.
    """
    doc = read_json(Path(clips_dir) / _CLIPS_FILE, max_bytes=_MAX_CLIPS_BYTES, what="a clips file")
    if isinstance(doc, dict) and isinstance(doc.get("clips"), list):
        doc = doc["clips"]
    if not isinstance(doc, list):
        raise ProcessError(f"{Path(clips_dir) / _CLIPS_FILE} is not a clips file (expected a JSON list)")
    clips: list[ClipEntry] = []
    seen: set[str] = set()
    dropped = 0
    for raw in doc:
        try:
            entry = ClipEntry.model_validate(raw)
        except ValidationError:
            dropped += 1
            continue
        if entry.uuid in seen:
            dropped += 1
            continue
        seen.add(entry.uuid)
        clips.append(entry)
    if dropped:
        _log.warning("%s: %d malformed or duplicate clip entries dropped", clips_dir, dropped)
    return clips, dropped


_SEEK_GAP_S = 2.0
"""Stills further apart than this [s] are reached by seeking to the keyframe before each one
instead of decoding every frame between them: cameras and phones write a keyframe every 0.5-2 s,
so a seek then skips most of the gap (benchmarks/annotate.py: long clips)."""


def sample_stills(path: Path, count: int, *, max_side_px: int = 448, qscale: int = 4) -> list[bytes]:
    """``count`` JPEG stills evenly spaced over a video (centres of equal spans), in time order.

    A clip with fewer frames gives each frame once. Stills keep the aspect ratio, the longer side
    scaled down to ``max_side_px`` [px] (never up); ``qscale`` is the JPEG quantizer, 2 (best) to 31.
    Stills more than :data:`_SEEK_GAP_S` apart are reached by seeking (the same frames as one
    decoding pass, fewer frames decoded).

    Raises:
        ProcessError: The file cannot be opened or decoded, or has no video stream.
    """
    if count < 1:
        raise ValueError(f"count must be >= 1, got {count}")
    av = _av()
    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                raise ProcessError(f"{path} has no video stream")
            stream = container.streams.video[0]
            stream.thread_type = "AUTO"
            duration = _duration_s(container, stream)
            targets = [(i + 0.5) * duration / count for i in range(count)]
            picker = _Picker(stream, max_side_px, qscale)
            seek = duration / count > _SEEK_GAP_S and stream.start_time is not None
            for target in targets:
                if (
                    seek
                    and picker.seeks_help
                    and picker.last_t is not None
                    and target - picker.last_t > _SEEK_GAP_S
                ):
                    picker.seek_before(container, target)
                if not picker.advance_to(container, target):
                    break  # the video ended before this target
            return picker.finish(path)
    except av.FFmpegError as exc:
        raise ProcessError(f"cannot decode {path}: {str(exc).splitlines()[0]}") from None
    except OSError as exc:
        raise ProcessError(f"cannot read {path}: {exc.strerror or exc}") from None


class _Picker:
    """Walks one video stream forward (seeking when told) and encodes the frame covering each target.

    A frame stands for ``[t, t + 1/fps)`` on the clip's time axis (``t`` from the stream's start):
    it is taken when a target falls in that span; a frame taken once is not taken again.
    """

    def __init__(self, stream: Any, max_side_px: int, qscale: int) -> None:
        self.stream = stream
        self.span = 1.0 / float(stream.average_rate) if stream.average_rate else 0.0
        self.start = float(stream.start_time * stream.time_base) if stream.start_time is not None else None
        self.max_side_px, self.qscale = max_side_px, qscale
        self.frames: Iterator[Any] | None = None
        self.index = 0
        self.last: Any = None
        self.last_t: float | None = None
        self.taken: float | None = None
        self.encoder: _Jpeg | None = None
        self.stills: list[bytes] = []
        self.seeks_help = True
        """Cleared when a seek lands at or before the frame already decoded (keyframes further
        apart than the stills): decoding on is then cheaper than seeking back."""
        self._before_seek: float | None = None

    def seek_before(self, container: Any, target: float) -> None:
        base = self.start or 0.0
        offset = round((base + target) / float(self.stream.time_base))
        container.seek(offset, stream=self.stream, backward=True, any_frame=False)
        self._before_seek = self.last_t
        self.frames = None  # PyAV flushed the decoder; decode afresh from the keyframe

    def advance_to(self, container: Any, target: float) -> bool:
        """Decode up to the frame covering ``target`` [s] and encode it; ``False`` at the end."""
        if self.last_t is not None and self.last_t + self.span > target + 1e-9:
            return True  # the last frame decoded covers it too
        if self.frames is None:
            self.frames = iter(container.decode(self.stream))
        for frame in self.frames:
            t = float(frame.time) if frame.time is not None else self.index * (self.span or 1 / 30)
            self.index += 1
            if self.start is None:
                self.start = t
            t -= self.start
            if self._before_seek is not None:
                self.seeks_help = t > self._before_seek + 1e-9
                self._before_seek = None
            self.last, self.last_t = frame, t
            if t + self.span > target + 1e-9:
                self._take(frame, t)
                return True
        return False

    def _take(self, frame: Any, t: float) -> None:
        if self.taken is not None and abs(self.taken - t) < 1e-9:
            return
        self.taken = t
        if self.encoder is None:
            self.encoder = _jpeg_encoder(frame.width, frame.height, self.max_side_px, self.qscale)
        self.stills.append(_encode(self.encoder, frame))

    def finish(self, path: Path) -> list[bytes]:
        if self.last is None:
            raise ProcessError(f"{path} has no decodable frames")
        if not self.stills:  # no usable duration: the last frame stands for the clip
            self._take(self.last, self.last_t or 0.0)
        return self.stills


def _av() -> Any:
    try:
        return importlib.import_module("av")
    except ImportError:
        raise DependencyError("sampling clip frames needs PyAV: pip install 'telerig[process]'") from None


def _duration_s(container: Any, stream: Any) -> float:
    if stream.duration is not None and stream.time_base is not None:
        return max(0.0, float(stream.duration * stream.time_base))
    if container.duration is not None:
        return max(0.0, float(container.duration) / 1e6)
    return 0.0  # unknown: the first frame stands for the clip


class _Jpeg:
    def __init__(self, codec: Any, width: int, height: int) -> None:
        self.codec, self.width, self.height = codec, width, height
        self.count = 0
        """Stills encoded so far: the encoder wants strictly increasing pts."""


def _jpeg_encoder(width: int, height: int, max_side_px: int, qscale: int) -> _Jpeg:
    av = _av()
    scale = min(1.0, max_side_px / max(width, height))
    w = max(2, int(width * scale) // 2 * 2)  # 4:2:0 JPEG wants even sizes
    h = max(2, int(height * scale) // 2 * 2)
    codec = av.CodecContext.create("mjpeg", "w")
    codec.width, codec.height = w, h
    codec.pix_fmt = "yuvj420p"
    codec.time_base = Fraction(1, 1)
    codec.qmin = codec.qmax = qscale
    return _Jpeg(codec, w, h)


def _encode(jpeg: _Jpeg, frame: Any) -> bytes:
    small = frame.reformat(width=jpeg.width, height=jpeg.height, format="yuvj420p")
    small.pts = jpeg.count
    small.time_base = jpeg.codec.time_base
    jpeg.count += 1
    return b"".join(bytes(p) for p in jpeg.codec.encode(small))


class AnswerCache:
    """Validated model answers on disk, one JSON file per :func:`~telerig.process.vlm.cache_key`.

    Files are written atomically; a damaged or foreign file reads as a miss (and is overwritten).
    """

    def __init__(self, root: Path) -> None:
        self.root = Path(root)

    def _path(self, key: str) -> Path:
        return self.root / key[:2] / f"{key}.json"

    def get(self, key: str) -> dict[str, Any] | None:
        """The stored record (``description``, ``model``, ``tokens``) or ``None``."""
        path = self._path(key)
        if not path.is_file():
            return None
        try:
            doc = read_json(path, max_bytes=4 << 20, what="a cached answer")
            ClipDescription.model_validate(doc["description"])
            tokens = doc["tokens"]
            if not (isinstance(tokens, dict) and all(isinstance(v, int) for v in tokens.values())):
                raise ValueError("tokens")
        except (ProcessError, ValidationError, KeyError, TypeError, ValueError):
            _log.warning("%s: damaged cache entry ignored", path)
            return None
        return dict(doc)

    def put(self, key: str, record: Mapping[str, Any]) -> None:
        """Store one answer record (replaces any earlier one).

        A cache that cannot be written (disk full, read-only) is logged and skipped: the answer is
        still good, only a re-run will ask again.
        """
        try:
            self._path(key).parent.mkdir(parents=True, exist_ok=True)
            write_json_atomic(self._path(key), dict(record))
        except (OSError, ProcessError) as exc:
            _log.warning("answer cache %s not written: %s", self.root, exc)


def _meta_text(meta: Mapping[str, Any], key: str) -> str | None:
    """A metadata value as a short string (lists of names joined), or ``None`` when absent/odd."""
    value = meta.get(key)
    if isinstance(value, list | tuple) and all(isinstance(v, str) for v in value):
        value = ", ".join(value)
    if isinstance(value, bool) or not isinstance(value, str | int | float):
        return None
    text = " ".join(str(value).split())[:_MAX_META_CHARS]
    return text or None


def _clip_label(clip: ClipEntry) -> str | None:
    return " ".join(clip.label.split())[:_MAX_META_CHARS] or None if clip.label else None


def offline_annotation(clip: ClipEntry, item: Item) -> dict[str, Any]:
    """What can be said of a clip without a model: its segment label and the item's metadata.

    Read from ``item.meta``: ``task``, ``robots`` (or ``robot``), ``operator`` and ``scene``.

    Objects stay empty (nothing looked at the pixels); the scene is ``meta["scene"]`` when it is a
    known scene type, else ``other``. Marked ``offline: true`` so no one mistakes it for a model's.
    """
    task = _meta_text(item.meta, "task")
    # Episode items name the rig's robot models in "robots" (telerig.process.items); "robot" is
    # accepted for items made elsewhere.
    robot = _meta_text(item.meta, "robots") or _meta_text(item.meta, "robot")
    operator = _meta_text(item.meta, "operator")
    label = _clip_label(clip)
    rig = _meta_text(item.meta, "rig")
    scene = _meta_text(item.meta, "scene")
    if item.kind == "episode":
        agent = f"robot {robot}" if robot else "the robot"
        agent += f" teleoperated by {operator}" if operator else " (teleoperated)"
    else:
        agent = "the camera wearer" if not operator else f"{operator} (camera wearer)"
    interaction = label or "unknown"
    parts = [f"{agent}: {interaction}"]
    if task:
        parts.append(f"during task '{task}'")
    return {
        "objects": [],
        "scene": scene if scene in SCENE_TYPES else "other",
        "action": {
            "description": " ".join(parts),
            "agent": agent,
            "objects": [],
            "interaction": interaction,
        },
        "model": None,
        "offline": True,
        "known": {"task": task, "robot": robot, "operator": operator, "label": label, "rig": rig},
        "status": "ok",
        "error": "",
        "cached": False,
        "tokens": {"prompt": 0, "completion": 0},
        "cost_usd": 0.0,
    }


def _context(clip: ClipEntry, item: Item) -> str:
    """Facts given to the model with the clip: the segment label and the item's task."""
    known = []
    label = _clip_label(clip)
    if label:
        known.append(f"segment label '{label}'")
    task = _meta_text(item.meta, "task")
    if task:
        known.append(f"recorded for the task '{task}'")
    return "; ".join(known)


def _file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    try:
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
    except OSError as exc:
        raise ProcessError(f"cannot read clip {path}: {exc.strerror or exc}") from None
    return h.hexdigest()


class _Annotator:
    """One stage run with a model: client, cache and per-clip work (called from a thread pool)."""

    def __init__(self, settings: AnnotateSettings, item: Item, ctx: StageContext) -> None:
        self.settings = settings
        self.item = item
        self.clips_dir = ctx.upstream["clips"]
        endpoint = hashlib.sha256(str(settings.url).encode()).hexdigest()[:16]
        base = ctx.work_root / "cache" / "annotate"
        self.cache = AnswerCache(base / "answers") if settings.cache else None
        self.client = VlmClient(settings, limits_dir=base / "limits" / endpoint)

    def cost(self, prompt: int, completion: int) -> float:
        s = self.settings
        return prompt / 1000 * s.price_prompt_per_1k + completion / 1000 * s.price_completion_per_1k

    def annotate(self, clip: ClipEntry) -> tuple[dict[str, Any], Completion | None]:
        """The clip's annotation record, and the completion when a request was made."""
        s = self.settings
        path = self.clips_dir / clip.file
        try:
            digest = _file_sha256(path)
            size = path.stat().st_size
        except (ProcessError, OSError) as exc:
            return self._failed(str(exc) if isinstance(exc, ProcessError) else f"cannot read {path}"), None
        send_video = s.input == "video" and size <= s.max_video_mb * (1 << 20)
        context = _context(clip, self.item)
        shape = {
            "input": "video" if send_video else "frames",
            "frames": s.frames,
            "max_side_px": s.max_side_px,
            "jpeg_qscale": s.jpeg_qscale,
            "max_tokens": s.max_tokens,
            "temperature": s.temperature,
            "context": context,
        }
        key = cache_key(digest, self.client.model, shape)
        if self.cache is not None and (hit := self.cache.get(key)) is not None:
            return self._record(ClipDescription.model_validate(hit["description"]), hit["tokens"], True), None
        try:
            if send_video:
                parts = [video_part(path.read_bytes())]
            else:
                stills = sample_stills(path, s.frames, max_side_px=s.max_side_px, qscale=s.jpeg_qscale)
                parts = [image_part(jpeg) for jpeg in stills]
        except (ProcessError, OSError) as exc:
            return self._failed(str(exc) if isinstance(exc, ProcessError) else f"cannot read {path}"), None
        done = self.client.describe(parts, context=context)
        tokens = {"prompt": done.prompt_tokens, "completion": done.completion_tokens}
        if done.description is None:
            record = self._failed(done.error)
            record["tokens"] = tokens
            record["cost_usd"] = self.cost(done.prompt_tokens, done.completion_tokens)
            return record, done
        if self.cache is not None:
            self.cache.put(
                key,
                {
                    "description": done.description.model_dump(mode="json"),
                    "model": self.client.model,
                    "prompt_version": PROMPT_VERSION,
                    "tokens": tokens,
                },
            )
        return self._record(done.description, tokens, False), done

    def _record(self, desc: ClipDescription, tokens: Mapping[str, int], cached: bool) -> dict[str, Any]:
        record = desc.model_dump(mode="json")
        prompt, completion = int(tokens.get("prompt", 0)), int(tokens.get("completion", 0))
        record.update(
            model=self.client.model,
            offline=False,
            status="ok",
            error="",
            cached=cached,
            tokens={"prompt": prompt, "completion": completion},
            cost_usd=self.cost(prompt, completion),
        )
        return record

    def _failed(self, reason: str) -> dict[str, Any]:
        return {
            "objects": [],
            "scene": None,
            "action": None,
            "model": self.client.model,
            "offline": False,
            "status": "failed",
            "error": " ".join(reason.split())[:300],
            "cached": False,
            "tokens": {"prompt": 0, "completion": 0},
            "cost_usd": 0.0,
        }


class AnnotateStage:
    """Stage 4: ``annotations.json`` for the item's clips (model answers or the offline annotator).

    Status: ``ok`` when at least one clip was annotated (failed clips are listed with their reason
    and counted; a re-run asks again only for them, the rest come from the cache), ``empty`` when
    the item has no clips, ``failed`` when every clip failed.
    """

    name = "annotate"
    version = "1"

    def run(self, item: Item, ctx: StageContext) -> StageResult:
        """Annotate every clip of ``ctx.upstream["clips"]`` into ``ctx.out_dir``."""
        settings = ctx.settings if isinstance(ctx.settings, AnnotateSettings) else AnnotateSettings()
        if "clips" not in ctx.upstream:
            return StageResult("failed", (), {}, "no clips stage output for this item (run the clips stage)")
        clips, dropped = read_clips(ctx.upstream["clips"])
        offline = settings.model is None
        records: dict[str, dict[str, Any]] = {}
        totals = {"requests": 0.0, "retries": 0.0, "backoff_s": 0.0, "prompt_tokens": 0.0}
        totals |= {"completion_tokens": 0.0, "cost_usd": 0.0}
        if offline:
            for clip in clips:
                records[clip.uuid] = offline_annotation(clip, item)
            ctx.progress(1.0)
        elif clips:
            self._with_model(settings, item, ctx, clips, records, totals)
        failed = [r for r in records.values() if r["status"] == "failed"]
        cached = sum(1 for r in records.values() if r["cached"])
        usage = {
            "clips": len(clips),
            "annotated": len(records) - len(failed),
            "failed": len(failed),
            "cached": cached,
            "dropped_entries": dropped,
            **{k: round(v, 6) if k in ("cost_usd", "backoff_s") else int(v) for k, v in totals.items()},
        }
        doc = {
            "schema": ANNOTATIONS_SCHEMA,
            "model": settings.model,
            "offline": offline,
            "prompt_version": PROMPT_VERSION,
            "clips": records,
            "usage": usage,
        }
        write_json_atomic(ctx.out_dir / ANNOTATIONS_FILE, doc)
        _episode_sidecar(item, records)
        metrics = {k: float(v) for k, v in usage.items()}
        # The runner's summary adds up "clips_annotated" (offline records count: "offline" says so).
        metrics |= {"clips_annotated": float(usage["annotated"]), "offline": 1.0 if offline else 0.0}
        if not clips:
            return StageResult("empty", (ANNOTATIONS_FILE,), metrics, "no clips to annotate")
        if failed and len(failed) == len(records):
            msg = f"all {len(failed)} clips failed: {failed[0]['error']}"
            return StageResult("failed", (ANNOTATIONS_FILE,), metrics, msg)
        msg = f"{len(failed)} of {len(records)} clips failed: {failed[0]['error']}" if failed else ""
        return StageResult("ok", (ANNOTATIONS_FILE,), metrics, msg)

    @staticmethod
    def _with_model(
        settings: AnnotateSettings,
        item: Item,
        ctx: StageContext,
        clips: list[ClipEntry],
        records: dict[str, dict[str, Any]],
        totals: dict[str, float],
    ) -> None:
        annotator = _Annotator(settings, item, ctx)
        try:
            with ThreadPoolExecutor(max_workers=settings.concurrency, thread_name_prefix="annotate") as pool:
                futures = {pool.submit(annotator.annotate, clip): clip for clip in clips}
                for n, future in enumerate(as_completed(futures), 1):
                    record, done = future.result()
                    records[futures[future].uuid] = record
                    if done is not None:
                        totals["requests"] += done.requests
                        totals["retries"] += done.retries
                        totals["backoff_s"] += done.backoff_s
                        totals["prompt_tokens"] += done.prompt_tokens
                        totals["completion_tokens"] += done.completion_tokens
                        totals["cost_usd"] += annotator.cost(done.prompt_tokens, done.completion_tokens)
                    ctx.progress(n / len(clips))
        finally:
            annotator.client.close()


def read_annotations(path: Path) -> dict[str, dict[str, Any]]:
    """Clip uuid -> annotation record of an ``annotations.json`` (file or its stage directory).

    Raises:
        ProcessError: Missing, too large, not JSON or not an annotations file.
    """
    path = Path(path)
    if path.is_dir():
        path = path / ANNOTATIONS_FILE
    doc = read_json(path, max_bytes=_MAX_ANNOTATIONS_BYTES, what="an annotations file")
    clips = doc.get("clips") if isinstance(doc, dict) else None
    if not isinstance(clips, dict) or doc.get("schema") != ANNOTATIONS_SCHEMA:
        raise ProcessError(f"{path} is not an annotations file (schema {ANNOTATIONS_SCHEMA} with clips)")
    return {str(k): v for k, v in clips.items() if isinstance(v, dict)}


def _episode_sidecar(item: Item, records: Mapping[str, Mapping[str, Any]]) -> None:
    """Copy each clip's action description beside the episode's files (``segment_annotations.json``,
    :mod:`telerig.store.annotations_file`): the exports read it there (they never import this
    package). Clip uuids are segment ids. A sidecar that cannot be written is logged, not fatal."""
    if item.kind != "episode" or item.episode_dir is None:
        return
    notes: dict[str, SegmentAnnotation] = {}
    for uuid, rec in records.items():
        action = rec.get("action")
        text = action.get("description") if isinstance(action, Mapping) else None
        if rec.get("status") != "ok" or not isinstance(text, str) or not text.strip():
            continue
        scene, model = rec.get("scene"), rec.get("model")
        notes[uuid] = SegmentAnnotation(
            description=text.replace("\x00", "").strip()[:1000],
            scene=scene[:64] if isinstance(scene, str) else None,
            model=model[:200] if isinstance(model, str) else None,
            offline=bool(rec.get("offline")),
        )
    try:
        write_episode_annotations(item.episode_dir, EpisodeAnnotations(episode_id=item.id, segments=notes))
    except (RecordingError, ValueError) as exc:
        _log.warning("%s: segment annotations not copied beside the episode: %s", item.id, exc)
