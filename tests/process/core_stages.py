"""Small real stages for the runner tests, in their own module so that spawned pool and Dask
workers import only this (PyAV and the stage interface), not the episode store the generators need.

``probe`` decodes the item's videos with PyAV (a garbage file makes it raise, as a real stage
would); ``double`` reads the probe's output from its upstream directory; ``crash`` ends its worker
process for one input, as a segfault would.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import av

from telerig.process.stage import Item, StageContext, StageResult


def _probe(path: Path) -> dict[str, float]:
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        frames = sum(1 for _ in container.decode(stream))
        rate = float(stream.average_rate or 0)
    return {"frames": float(frames), "fps": rate, "seconds": frames / rate if rate else 0.0}


@dataclass(frozen=True)
class ProbeStage:
    """Decodes every video of the item; writes ``probe.json`` (frames, fps, seconds per video)."""

    name: str = "probe"
    version: str = "1"

    def run(self, item: Item, ctx: StageContext) -> StageResult:
        settings: dict[str, Any] = dict(ctx.settings or {})
        if item.meta.get("name", "").startswith(settings.get("fail_prefix", "\0")):
            raise RuntimeError(f"refusing {item.meta['name']} by setting fail_prefix")
        videos = {}
        for n, video in enumerate(item.videos):
            videos[video.name] = _probe(video)
            ctx.progress((n + 1) / len(item.videos))
        (ctx.out_dir / "probe.json").write_text(json.dumps({"videos": videos, "pid": os.getpid()}))
        seconds = sum(v["seconds"] for v in videos.values())
        return StageResult("ok", ("probe.json",), {"seconds_in": seconds, "seconds_kept": seconds / 2})


@dataclass(frozen=True)
class DoubleStage:
    """Reads ``probe.json`` upstream; writes ``double.json`` with twice the frames; one segment and
    one clip per video."""

    name: str = "double"
    version: str = "1"

    def run(self, item: Item, ctx: StageContext) -> StageResult:
        probe = json.loads((ctx.upstream["probe"] / "probe.json").read_text())
        doubled = {k: 2 * v["frames"] for k, v in probe["videos"].items()}
        (ctx.out_dir / "double.json").write_text(json.dumps(doubled, sort_keys=True))
        n = float(len(doubled))
        if not n:
            return StageResult("empty", ("double.json",), {}, "no video")
        return StageResult("ok", ("double.json",), {"segments": n, "clips": n, "clips_annotated": n})


@dataclass(frozen=True)
class CrashStage:
    """Ends its worker process (as a segfault would) for items whose video name starts with ``crash``."""

    name: str = "crash"
    version: str = "1"

    def run(self, item: Item, ctx: StageContext) -> StageResult:
        if str(item.meta.get("name", "")).startswith("crash"):
            os._exit(3)
        return StageResult("ok", (), {})


@dataclass(frozen=True)
class CopyStage:
    """Copies the item's first video into its output (as a clip stage writes videos)."""

    name: str = "copy"
    version: str = "1"

    def run(self, item: Item, ctx: StageContext) -> StageResult:
        (ctx.out_dir / "copy.mp4").write_bytes(item.videos[0].read_bytes())
        return StageResult("ok", ("copy.mp4",), {})


@dataclass(frozen=True)
class OddStage:
    """Returns what a buggy plug-in might: not a StageResult, an unknown status, odd metrics."""

    name: str = "odd"
    version: str = "1"

    def run(self, item: Item, ctx: StageContext) -> Any:
        kind = ctx.settings["kind"]
        if kind == "none":
            return None
        if kind == "status":
            return StageResult("done", (), {})  # type: ignore[arg-type]
        return StageResult("ok", (), {"frames": "many"})  # type: ignore[dict-item]


@dataclass(frozen=True)
class PartlyStage:
    """Finishes ``ok`` with one part failed (``metrics["failed"] == 1``) until the file named by the
    ``ready`` setting exists, like annotation with a model that did not answer for one clip."""

    name: str = "partly"
    version: str = "1"

    def run(self, item: Item, ctx: StageContext) -> StageResult:
        ready = Path(dict(ctx.settings or {})["ready"]).exists()
        (ctx.out_dir / "partly.json").write_text(json.dumps({"ready": ready}))
        return StageResult("ok", ("partly.json",), {"failed": 0.0 if ready else 1.0})
