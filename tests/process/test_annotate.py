"""Stage 4 (annotate): real PyAV clips, a real local chat-completions server, the offline annotator."""

from __future__ import annotations

import json
import logging
import re
import shutil
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import chat_server
import pytest

from telerig.config.process import AnnotateSettings
from telerig.errors import ProcessError
from telerig.process.annotate import AnnotateStage, read_annotations, read_clips, sample_stills
from telerig.process.stage import Item, Stage, StageContext, StageResult

KEY = "sk-annotate-test-key-7f3a9c"


@pytest.fixture(scope="module")
def clip_files(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    root = tmp_path_factory.mktemp("clipsrc")
    return [chat_server.make_clip(root / f"{i}.mp4", seconds=1.0 + 0.5 * i) for i in range(3)]


def _item(kind: str = "episode", **meta: Any) -> Item:
    return Item(
        id="ep-0001",
        kind=kind,  # type: ignore[arg-type]
        videos=(Path("cameras/front.mp4"),),
        episode_dir=None,
        source_hash="0" * 64,
        meta=meta,
    )


def _clips_dir(
    root: Path, files: list[Path], labels: list[str | None] | None = None
) -> tuple[Path, list[str]]:
    """A clips stage directory: the clip files under their uuid names and clips.json."""
    clips_dir = root / "items" / "ep-0001" / "clips"
    clips_dir.mkdir(parents=True)
    entries, ids = [], []
    for i, src in enumerate(files):
        cid = str(uuid.uuid4())
        (clips_dir / f"{cid}.mp4").write_bytes(src.read_bytes())
        label = labels[i] if labels else "grasp"
        entries.append(
            {
                "uuid": cid,
                "video": "cameras/front.mp4",
                "start_s": i,
                "end_s": i + 1,
                "file": f"{cid}.mp4",
                "label": label,
                "method": "copy",
            }
        )
        ids.append(cid)
    (clips_dir / "clips.json").write_text(json.dumps(entries))
    return clips_dir, ids


def _run(
    root: Path, clips_dir: Path, settings: AnnotateSettings, item: Item | None = None
) -> tuple[StageResult, Path]:
    out = root / "items" / "ep-0001" / "annotate"
    if out.exists():
        for f in out.iterdir():
            f.unlink()
    out.mkdir(parents=True, exist_ok=True)
    progress: list[float] = []
    ctx = StageContext(
        out_dir=out,
        work_root=root,
        upstream={"clips": clips_dir},
        settings=settings,
        progress=progress.append,
    )
    item = item or _item(task="stack the cubes", robots=["ur5e"], operator="alice", rig="demo")
    result = AnnotateStage().run(item, ctx)
    assert progress
    assert progress[-1] == 1.0
    return result, out


def _settings(url: str, **over: Any) -> AnnotateSettings:
    base: dict[str, Any] = {
        "url": url,
        "model": "qwen2.5-vl-test",
        "frames": 4,
        "max_side_px": 96,
        "backoff_base_s": 0.01,
        "timeout_s": 3.0,
        "requests_per_minute": 60_000,
        "max_retries": 2,
        "price_prompt_per_1k": 0.5,
        "price_completion_per_1k": 2.0,
    }
    return AnnotateSettings(**(base | over))


@pytest.fixture
def key_env(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("TELERIG_VLM_API_KEY", KEY)


def test_stage_satisfies_the_stage_protocol() -> None:
    stage = AnnotateStage()
    assert isinstance(stage, Stage)
    assert (stage.name, stage.version) == ("annotate", "1")


def test_offline_annotator_fills_what_metadata_and_labels_tell(
    tmp_path: Path, clip_files: list[Path]
) -> None:
    clips_dir, ids = _clips_dir(tmp_path, clip_files[:2], labels=["pick up cube", None])
    result, out = _run(tmp_path, clips_dir, AnnotateSettings(url=None, model=None))
    assert result.status == "ok"
    assert result.metrics["offline"] == 1.0
    assert result.metrics["requests"] == 0
    records = read_annotations(out)
    first, second = records[ids[0]], records[ids[1]]
    assert first["offline"] is True
    assert first["model"] is None
    assert first["action"]["agent"] == "robot ur5e teleoperated by alice"
    assert first["action"]["interaction"] == "pick up cube"
    assert (
        first["action"]["description"]
        == "robot ur5e teleoperated by alice: pick up cube during task 'stack the cubes'"
    )
    assert first["objects"] == []
    assert first["scene"] == "other"
    assert second["action"]["interaction"] == "unknown"
    assert first["known"] == {
        "task": "stack the cubes",
        "robot": "ur5e",
        "operator": "alice",
        "label": "pick up cube",
        "rig": "demo",
    }


def test_offline_annotator_on_plain_video_with_a_scene_hint(tmp_path: Path, clip_files: list[Path]) -> None:
    clips_dir, ids = _clips_dir(tmp_path, clip_files[:1])
    item = _item("video", scene="kitchen", task=["a", 3])  # a task that is not text is left out
    _, out = _run(tmp_path, clips_dir, AnnotateSettings(url=None, model=None), item)
    record = read_annotations(out)[ids[0]]
    assert record["scene"] == "kitchen"
    assert record["action"]["agent"] == "the camera wearer"
    assert record["known"]["task"] is None


def test_clips_are_annotated_by_the_model_then_served_from_the_cache(
    server: Any, tmp_path: Path, clip_files: list[Path], key_env: None
) -> None:
    clips_dir, ids = _clips_dir(tmp_path, clip_files)
    settings = _settings(server.url)
    result, out = _run(tmp_path, clips_dir, settings)
    assert result.status == "ok", result.message
    assert server.shape_errors == []
    assert len(server.seen) == 3
    assert {s.images for s in server.seen} == {4}  # frames=4 stills per clip, as image_url parts
    records = read_annotations(out)
    assert set(records) == set(ids)
    for rec in records.values():
        assert rec["offline"] is False
        assert rec["status"] == "ok"
        assert rec["scene"] == "assembly_station"
        assert rec["objects"][0] == {"name": "red cube", "quantity": 4, "attributes": ["red", "wooden"]}
        assert rec["tokens"] == {"prompt": 300, "completion": 40}
        assert rec["cost_usd"] == pytest.approx(0.3 * 0.5 + 0.04 * 2.0)
    m = result.metrics
    assert (m["clips"], m["annotated"], m["failed"], m["cached"], m["requests"]) == (3, 3, 0, 0, 3)
    assert m["clips_annotated"] == 3
    assert (m["prompt_tokens"], m["completion_tokens"]) == (900, 120)
    assert m["cost_usd"] == pytest.approx(3 * (0.3 * 0.5 + 0.04 * 2.0))
    assert "label 'grasp'" in server.seen[0].body["messages"][-1]["content"][0]["text"]
    assert "task 'stack the cubes'" in server.seen[0].body["messages"][-1]["content"][0]["text"]

    again, out = _run(tmp_path, clips_dir, settings)
    assert len(server.seen) == 3  # no new request
    assert (again.metrics["cached"], again.metrics["requests"], again.metrics["cost_usd"]) == (3, 0, 0)
    assert all(r["cached"] for r in read_annotations(out).values())
    assert read_annotations(out)[ids[0]]["objects"] == records[ids[0]]["objects"]

    _run(tmp_path, clips_dir, _settings(server.url, model="another-model"))
    assert len(server.seen) == 6  # another model is another cache key


def test_video_input_sends_the_clip_as_one_base64_mp4(
    server: Any, tmp_path: Path, clip_files: list[Path], key_env: None
) -> None:
    clips_dir, _ = _clips_dir(tmp_path, clip_files[:1])
    result, _ = _run(tmp_path, clips_dir, _settings(server.url, input="video"))
    assert result.status == "ok", result.message
    assert (server.seen[0].videos, server.seen[0].images) == (1, 0)


def test_a_failing_clip_is_recorded_and_the_others_annotated(
    server: Any, tmp_path: Path, clip_files: list[Path], key_env: None
) -> None:
    clips_dir, ids = _clips_dir(tmp_path, clip_files)
    (clips_dir / f"{ids[1]}.mp4").write_bytes(b"\x00garbage, not an mp4" * 50)
    server.queue("invalid", "invalid")  # one clip gets two schema-violating answers
    result, out = _run(tmp_path, clips_dir, _settings(server.url, concurrency=1))
    records = read_annotations(out)
    failed = {k: r for k, r in records.items() if r["status"] == "failed"}
    assert result.status == "ok"
    assert (result.metrics["annotated"], result.metrics["failed"]) == (1, 2)
    assert result.message.startswith("2 of 3 clips failed: ")
    assert "\n" not in result.message
    assert failed[ids[1]]["error"].startswith("cannot decode ")
    assert [r["error"] for k, r in failed.items() if k != ids[1]] == [
        "invalid answer: objects.0.quantity: Input should be greater than or equal to 0"
    ]
    assert result.metrics["retries"] == 1

    server.queue()  # the re-run asks again only for what failed (the decodable one succeeds now)
    before = len(server.seen)
    again, out = _run(tmp_path, clips_dir, _settings(server.url, concurrency=1))
    assert len(server.seen) == before + 1
    assert (again.metrics["annotated"], again.metrics["cached"], again.metrics["failed"]) == (2, 1, 1)


def test_every_clip_failing_fails_the_stage_in_one_line(tmp_path: Path, clip_files: list[Path]) -> None:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    clips_dir, _ = _clips_dir(tmp_path, clip_files[:2])
    result, out = _run(tmp_path, clips_dir, _settings(f"http://127.0.0.1:{port}/v1", max_retries=0))
    assert result.status == "failed"
    assert result.message == "all 2 clips failed: connection failed (ConnectError) (after 1 tries)"
    assert (out / "annotations.json").is_file()


def test_the_key_never_reaches_outputs_cache_or_logs(
    server: Any, tmp_path: Path, clip_files: list[Path], key_env: None, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.DEBUG)
    clips_dir, _ = _clips_dir(tmp_path, clip_files[:2])
    server.queue("echo-key-500", "echo-key-500", "echo-key-500")
    result, _ = _run(tmp_path, clips_dir, _settings(server.url, max_retries=1, concurrency=1))
    assert result.metrics["failed"] == 1  # one clip got the server's echo of its headers twice
    assert server.seen[0].authorization == f"Bearer {KEY}"
    for path in tmp_path.rglob("*"):
        if path.is_file():
            assert KEY.encode() not in path.read_bytes(), path
    assert KEY not in caplog.text
    assert KEY not in result.message


def test_no_clips_is_empty(tmp_path: Path) -> None:
    clips_dir, _ = _clips_dir(tmp_path, [])
    result, out = _run(tmp_path, clips_dir, AnnotateSettings(url=None, model=None))
    assert result.status == "empty"
    assert read_annotations(out) == {}


def test_malformed_clip_entries_are_counted_and_dropped(tmp_path: Path, clip_files: list[Path]) -> None:
    clips_dir, ids = _clips_dir(tmp_path, clip_files[:1])
    entries = json.loads((clips_dir / "clips.json").read_text())
    entries += [
        {"uuid": "../../etc", "file": "x.mp4"},
        {"uuid": ids[0], "file": f"{ids[0]}.mp4"},  # duplicate
        {"uuid": "a" * 32, "file": "../outside.mp4"},
        "not an object",
        {"uuid": "b" * 32, "file": "y.mp4", "start_s": -1e300},
        {"uuid": "c" * 32, "file": "z.mp4", "label": "x" * 100_000},
    ]
    (clips_dir / "clips.json").write_text(json.dumps(entries))
    clips, dropped = read_clips(clips_dir)
    assert [c.uuid for c in clips] == ids
    assert dropped == 6
    result, _ = _run(tmp_path, clips_dir, AnnotateSettings(url=None, model=None))
    assert result.metrics["dropped_entries"] == 6


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"{not json", "is not a clips file (invalid JSON"),
        (b'{"clips": 3}', "is not a clips file (expected a JSON list)"),
        (b"[" * 100_000, "is not a clips file (invalid JSON"),
    ],
)
def test_a_garbage_clips_file_is_one_line(tmp_path: Path, content: bytes, message: str) -> None:
    (tmp_path / "clips.json").write_bytes(content)
    with pytest.raises(ProcessError, match=re.escape(message)):
        read_clips(tmp_path)


def test_a_missing_clips_stage_fails_the_item(tmp_path: Path) -> None:
    ctx = StageContext(tmp_path, tmp_path, {}, AnnotateSettings(url=None, model=None), lambda _: None)
    result = AnnotateStage().run(_item(), ctx)
    assert result.status == "failed"
    assert result.message == "no clips stage output for this item (run the clips stage)"


def test_sample_stills_are_evenly_spaced_scaled_jpegs(tmp_path: Path, clip_files: list[Path]) -> None:
    import av

    stills = sample_stills(clip_files[0], 4, max_side_px=80)
    assert len(stills) == 4
    assert len(set(stills)) == 4  # four different frames of the moving gradient
    for jpeg in stills:
        assert jpeg[:2] == b"\xff\xd8"
        path = tmp_path / "s.jpg"
        path.write_bytes(jpeg)
        with av.open(str(path)) as c:
            frame = next(c.decode(video=0))
            assert (frame.width, frame.height) == (80, 60)
    few = sample_stills(clip_files[0], 40)  # a 1 s, 10 fps clip has 10 frames
    assert len(few) == 10


def test_a_truncated_video_is_a_one_line_error(tmp_path: Path, clip_files: list[Path]) -> None:
    bad = tmp_path / "bad.mp4"
    bad.write_bytes(clip_files[0].read_bytes()[:300])
    with pytest.raises(ProcessError, match=r"^cannot decode .*bad\.mp4: "):
        sample_stills(bad, 4)


@pytest.mark.parametrize(
    ("url", "message"),
    [
        ("http://user:hunter2@127.0.0.1:8000/v1", "annotate.url: carries a user name or password"),
        ("http://127.0.0.1:8000/v1?api_key=hunter2", "annotate.url: has a query or fragment"),
        ("ftp://hunter2/v1", "annotate.url: must be http(s) with a host"),
        ("http://[hunter2", "annotate.url: is not a URL"),
    ],
)
def test_a_bad_url_is_refused_without_echoing_it(url: str, message: str) -> None:
    from pydantic import ValidationError

    from telerig.config.process import ProcessSettings
    from telerig.registry import format_validation_error

    with pytest.raises(ValidationError) as caught:
        ProcessSettings.model_validate({"annotate": {"url": url, "model": "m"}})
    line = format_validation_error(caught.value, model=ProcessSettings)
    assert line.startswith(message)
    assert "hunter2" not in line


def test_url_and_model_default_to_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("TELERIG_VLM_URL", "http://127.0.0.1:9/v1/")
    monkeypatch.setenv("TELERIG_VLM_MODEL", "qwen2.5-vl")
    settings = AnnotateSettings()
    assert (settings.url, settings.model) == ("http://127.0.0.1:9/v1", "qwen2.5-vl")
    assert AnnotateSettings(model=None).model is None  # a rig may still ask for offline


def test_a_clip_over_max_video_mb_goes_as_stills(
    server: Any, tmp_path: Path, clip_files: list[Path], key_env: None
) -> None:
    clips_dir, _ = _clips_dir(tmp_path, clip_files[:1])
    result, _ = _run(tmp_path, clips_dir, _settings(server.url, input="video", max_video_mb=0.001))
    assert result.status == "ok", result.message
    assert (server.seen[0].videos, server.seen[0].images) == (0, 4)


def test_a_damaged_cache_entry_is_asked_again_and_replaced(
    server: Any, tmp_path: Path, clip_files: list[Path], key_env: None
) -> None:
    clips_dir, ids = _clips_dir(tmp_path, clip_files[:1])
    settings = _settings(server.url)
    _run(tmp_path, clips_dir, settings)
    (entry,) = (tmp_path / "cache" / "annotate" / "answers").rglob("*.json")
    entry.write_text('{"description": {"scene": "moon"}, "tokens": {}}')
    result, out = _run(tmp_path, clips_dir, settings)
    assert len(server.seen) == 2
    assert result.metrics["cached"] == 0
    assert read_annotations(out)[ids[0]]["scene"] == "assembly_station"
    assert json.loads(entry.read_text())["description"]["scene"] == "assembly_station"


@pytest.mark.parametrize(
    "content",
    [b"", b"\x00" * 64, b'{"schema": 1, "clips": []}', b'{"schema": 2, "clips": {}}', b"[]"],
)
def test_read_annotations_refuses_garbage_in_one_line(tmp_path: Path, content: bytes) -> None:
    (tmp_path / "annotations.json").write_bytes(content)
    with pytest.raises(ProcessError, match=r"^\S*annotations\.json is not an annotations file") as caught:
        read_annotations(tmp_path)
    assert "\n" not in str(caught.value)


@dataclass(frozen=True)
class WholeVideoClips:
    """A clips stage for the runner test: each video of the item is one clip (copied bytes)."""

    name: str = "clips"
    version: str = "1"

    def run(self, item: Item, ctx: StageContext) -> StageResult:
        entries = []
        for video in item.videos:
            cid = str(uuid.uuid5(uuid.NAMESPACE_URL, str(video)))
            shutil.copyfile(video, ctx.out_dir / f"{cid}.mp4")
            entries.append({"uuid": cid, "file": f"{cid}.mp4", "video": video.name, "label": "wipe"})
        (ctx.out_dir / "clips.json").write_text(json.dumps(entries))
        return StageResult("ok", ("clips.json", *(e["file"] for e in entries)), {"clips": len(entries)})


def test_runner_reuses_annotations_and_redoes_them_for_another_model(
    server: Any, tmp_path: Path, clip_files: list[Path], key_env: None
) -> None:
    from telerig.process.run import plan, run_pipeline
    from telerig.process.stage import video_item_id

    items = [
        Item(video_item_id(p), "video", (p,), None, f"{i:064x}", {"name": p.name})
        for i, p in enumerate(clip_files[:2])
    ]
    work = tmp_path / "processed"

    def run(settings: AnnotateSettings) -> Any:
        stages = plan([WholeVideoClips(), AnnotateStage()], {"annotate": settings})
        return run_pipeline(items, stages, work, workers=1)

    first = run(_settings(server.url))
    assert [o.failed for o in first.outcomes] == [None, None]
    assert first.total("clips_annotated") == 2
    assert len(server.seen) == 2
    again = run(_settings(server.url))
    assert [s.reused for o in again.outcomes for s in o.stages] == [True, True, True, True]
    assert len(server.seen) == 2
    other = run(_settings(server.url, model="another-model"))
    assert [(s.name, s.reused) for s in other.outcomes[0].stages] == [("clips", True), ("annotate", False)]
    assert len(server.seen) == 4
    down = run(_settings("http://127.0.0.1:9/v1", model="third-model", max_retries=0))
    assert [o.failed.message for o in down.outcomes if o.failed] == [
        "all 1 clips failed: connection failed (ConnectError) (after 1 tries)"
    ] * 2
    for path in work.rglob("*"):
        if path.is_file():
            assert KEY.encode() not in path.read_bytes(), path


def test_annotates_the_real_clips_stage_output_by_segment_id(
    server: Any, tmp_path: Path, key_env: None
) -> None:
    from telerig.config.process import ClipSettings
    from telerig.process.clips import ClipsStage
    from telerig.store.segments_file import (
        SEGMENTS_FILE,
        SegmentsRecord,
        machine_source,
        new_segment,
        write_segments,
    )

    video = chat_server.make_clip(tmp_path / "src.mp4", seconds=3.0)
    source = machine_source("motion_energy", "1")
    segments = (
        new_segment("reach", 0.5, 1.5, confidence=0.8, source=source),
        new_segment("wipe", 1.8, 2.8, confidence=0.6, source=source),
    )
    seg_dir = tmp_path / "items" / "v" / "segment"
    seg_dir.mkdir(parents=True)
    write_segments(
        seg_dir / SEGMENTS_FILE, SegmentsRecord(video=str(video), duration_s=3.0, segments=segments)
    )
    clips_dir = tmp_path / "items" / "v" / "clips"
    clips_dir.mkdir()
    item = Item("video-0123456789ab", "video", (video,), None, "0" * 64, {"task": "clean the table"})
    clip_ctx = StageContext(clips_dir, tmp_path, {"segment": seg_dir}, ClipSettings(), lambda _f: None)
    assert ClipsStage().run(item, clip_ctx).status == "ok"

    out = tmp_path / "items" / "v" / "annotate"
    out.mkdir()
    ctx = StageContext(
        out, tmp_path, {"segment": seg_dir, "clips": clips_dir}, _settings(server.url), lambda _f: None
    )
    result = AnnotateStage().run(item, ctx)
    assert result.status == "ok", result.message
    assert set(read_annotations(out)) == {s.id for s in segments}
    texts = sorted(s.body["messages"][-1]["content"][0]["text"] for s in server.seen)
    assert ["label 'reach'" in texts[0], "label 'wipe'" in texts[1]] == [True, True]
    assert {s.images for s in server.seen} == {4}


def test_stills_of_an_extreme_aspect_ratio_stay_decodable(tmp_path: Path) -> None:
    import av

    clip = chat_server.make_clip(tmp_path / "strip.mp4", seconds=0.5, width=1024, height=16)
    (jpeg,) = sample_stills(clip, 1, max_side_px=448)
    (tmp_path / "s.jpg").write_bytes(jpeg)
    with av.open(str(tmp_path / "s.jpg")) as c:
        frame = next(c.decode(video=0))
    assert (frame.width, frame.height) == (448, 6)
    with pytest.raises(ValueError, match="count must be >= 1"):
        sample_stills(clip, 0)


def test_an_unwritable_cache_does_not_fail_the_clips(
    server: Any, tmp_path: Path, clip_files: list[Path], key_env: None
) -> None:
    clips_dir, _ = _clips_dir(tmp_path, clip_files[:1])
    answers = tmp_path / "cache" / "annotate" / "answers"
    answers.parent.mkdir(parents=True)
    answers.write_text("a file where the cache directory should be")
    result, _ = _run(tmp_path, clips_dir, _settings(server.url))
    assert (result.status, result.metrics["annotated"]) == ("ok", 1)


def test_telerig_process_annotates_with_the_model_named_in_the_environment(
    server: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.syspath_prepend(str(Path(__file__).parent))
    from core_kit import make_episode

    from telerig.cli.main import main

    root = tmp_path / "data"
    make_episode(root, seconds=3.0)
    monkeypatch.setenv("TELERIG_VLM_URL", server.url)
    monkeypatch.setenv("TELERIG_VLM_MODEL", "qwen2.5-vl-test")
    monkeypatch.setenv("TELERIG_VLM_API_KEY", KEY)
    args = ["process", str(root), "--stages", "segment,clips,annotate,layout", "--workers", "1"]
    assert main(args) == 0
    assert (len(server.seen), server.shape_errors) == (1, [])
    (note,) = (root / "processed" / "dataset" / "assembly_station").glob("*.json")
    annotation = json.loads(note.read_text())["annotation"]
    assert (annotation["offline"], annotation["model"]) == (False, "qwen2.5-vl-test")
    assert main(args) == 0  # the re-run reuses every stage
    assert len(server.seen) == 1
    assert KEY not in capsys.readouterr().out
    for path in root.rglob("*"):
        if path.is_file():
            assert KEY.encode() not in path.read_bytes(), path


@pytest.mark.parametrize(
    ("gop", "b_frames"),
    [(10, 0), (10, 2), (None, 0)],  # a keyframe each second (with B-frames), or only the first
)
def test_seeking_to_far_apart_stills_gives_the_frames_of_one_pass(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, gop: int | None, b_frames: int
) -> None:
    from telerig.process import annotate

    clip = chat_server.make_clip(tmp_path / "long.mp4", seconds=14.0, gop=gop, b_frames=b_frames)
    seeking = sample_stills(clip, 4, max_side_px=64)  # 3.5 s apart: sought
    monkeypatch.setattr(annotate, "_SEEK_GAP_S", 1e9)
    one_pass = sample_stills(clip, 4, max_side_px=64)
    assert len(seeking) == 4
    assert seeking == one_pass
