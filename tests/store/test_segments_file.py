"""segments.json: the one schema for machine and human segments; hostile files are one-line errors."""

from __future__ import annotations

import datetime as dt
import json
import uuid
from pathlib import Path
from typing import Any

import pytest

from telerig.errors import RecordingError
from telerig.store.segments_file import (
    MAX_SEGMENTS,
    SEGMENTS_FILE,
    SegmentsRecord,
    edit_segment,
    machine_source,
    merge_machine,
    new_segment,
    read_episode_segments,
    read_segments,
    write_episode_segments,
    write_segments,
)

SOURCE = machine_source("robot_streams", "1")


def _record(episode_id: str | None = None) -> SegmentsRecord:
    return SegmentsRecord(
        video="cameras/scene.mp4",
        duration_s=12.345,
        segments=(
            new_segment("reach", 0.123, 1.256, confidence=0.8, source=SOURCE, actor="arm0"),
            new_segment("grasp", 1.256, 2.0, confidence=1.7, source=SOURCE),
        ),
        episode_id=episode_id,
    )


def _doc(**segment: Any) -> dict[str, Any]:
    seg = {
        "id": str(uuid.uuid4()),
        "label": "grasp",
        "confidence": 0.5,
        "start_s": 1.0,
        "end_s": 2.0,
        "source": SOURCE,
        "status": "proposed",
        "edited_at": None,
    }
    seg.update(segment)
    return {"schema": 1, "video": "a.mp4", "duration_s": 10.0, "segments": [seg], "empty": False}


def test_round_trip_rounds_times_to_centiseconds(tmp_path: Path) -> None:
    path = write_segments(tmp_path / SEGMENTS_FILE, _record())
    raw = json.loads(path.read_text())
    assert raw["schema"] == 1
    assert raw["duration_s"] == 12.35
    assert [s["start_s"] for s in raw["segments"]] == [0.12, 1.26]
    assert raw["segments"][1]["confidence"] == 1.0  # clipped
    back = read_segments(path)
    assert back == read_segments(write_segments(tmp_path / "again.json", back))
    assert back.segments[0].actor == "arm0"


def test_episode_sidecar_belongs_to_its_episode(tmp_path: Path) -> None:
    episode = tmp_path / "ep-1"
    episode.mkdir()
    assert read_episode_segments(episode) is None
    write_episode_segments(episode, _record("ep-1"))
    assert read_episode_segments(episode) == _record("ep-1").model_copy(
        update={"segments": read_episode_segments(episode).segments}  # type: ignore[union-attr]
    )
    other = tmp_path / "ep-2"
    other.mkdir()
    (other / SEGMENTS_FILE).write_text((episode / SEGMENTS_FILE).read_text())
    with pytest.raises(RecordingError, match="belongs to episode 'ep-1'"):
        read_episode_segments(other)
    with pytest.raises(ValueError, match="written into"):
        write_episode_segments(other, _record("ep-1"))


@pytest.mark.parametrize(
    ("text", "match"),
    [
        (b"{not json", "is not a segments file"),
        (b"[1, 2, 3]", "is not a segments file"),
        (json.dumps(_doc(start_s=-1.0)).encode(), r"segments\.0\.start_s"),
        (
            json.dumps(_doc()).replace("1.0,", "NaN,", 1).encode(),
            r"segments\.0\.start_s: Input should be a finite",
        ),
        (json.dumps(_doc(end_s=float("inf"))).encode(), r"segments\.0\.end_s"),
        (json.dumps(_doc(start_s=3.0, end_s=2.0)).encode(), "end_s 2.0 is not after start_s 3.0"),
        (json.dumps(_doc(start_s=2.001, end_s=2.004)).encode(), "is not after"),  # equal once rounded
        (json.dumps(_doc(status="approved")).encode(), r"segments\.0\.status"),
        (json.dumps(_doc(id="not-a-uuid-but-36-characters-long-xx")).encode(), "is not a UUID"),
        (json.dumps(_doc(source="robot")).encode(), r"segments\.0\.source"),
        (json.dumps(_doc(label="a\nb")).encode(), r"segments\.0\.label"),
        (json.dumps(_doc(end_s=99.0)).encode(), "after the video's 10.0 s"),
        (json.dumps(_doc(extra=1)).encode(), r"segments\.0\.extra"),
        (json.dumps(_doc(edited_at="2026-11-26T00:00:00")).encode(), r"segments\.0\.edited_at"),
        (json.dumps({**_doc(), "empty": True}).encode(), "empty is true but it lists 1 segments"),
        (json.dumps({**_doc(), "schema": 2}).encode(), "schema"),
    ],
)
def test_hostile_files_are_one_line_errors(tmp_path: Path, text: bytes, match: str) -> None:
    path = tmp_path / SEGMENTS_FILE
    path.write_bytes(text)
    with pytest.raises(RecordingError, match=match) as info:
        read_segments(path)
    assert "\n" not in str(info.value)
    assert str(path) in str(info.value)


def test_duplicate_ids_oversized_and_too_many_are_refused(tmp_path: Path) -> None:
    doc = _doc()
    doc["segments"].append(dict(doc["segments"][0]))
    path = tmp_path / SEGMENTS_FILE
    path.write_text(json.dumps(doc))
    with pytest.raises(RecordingError, match="appears twice"):
        read_segments(path)
    path.write_bytes(b" " * (9 << 20))
    with pytest.raises(RecordingError, match="larger than 8 MiB"):
        read_segments(path)
    seg = _doc()["segments"][0]
    doc["segments"] = [{**seg, "id": str(uuid.uuid4())} for _ in range(MAX_SEGMENTS + 1)]
    path.write_text(json.dumps(doc))
    with pytest.raises(RecordingError, match="segments: Tuple should have at most 10000 items"):
        read_segments(path)
    with pytest.raises(RecordingError, match="cannot read"):
        read_segments(tmp_path / "missing.json")


def test_review_keeps_who_and_what_it_replaced() -> None:
    record = _record()
    reach = record.segments[0]
    now = dt.datetime(2026, 11, 26, 1, 0, tzinfo=dt.UTC)
    accepted = edit_segment(record, reach.id, by="alice", status="accepted", now=now)
    seg = accepted.segments[0]
    assert (seg.status, seg.source, seg.origin, seg.confidence) == ("accepted", "human:alice", SOURCE, 1.0)
    assert seg.edited_at == now
    moved = edit_segment(accepted, reach.id, by="bob", status="accepted", start_s=0.5)
    seg = moved.segments[0]
    assert (seg.status, seg.start_s, seg.origin) == ("corrected", 0.5, SOURCE)  # moving is correcting
    with pytest.raises(ValueError, match="not after"):
        edit_segment(record, reach.id, by="bob", status="corrected", end_s=0.0)
    with pytest.raises(KeyError):
        edit_segment(record, str(uuid.uuid4()), by="bob", status="rejected")


def test_machine_rerun_keeps_reviewed_segments() -> None:
    old = _record()
    reviewed = edit_segment(old, old.segments[1].id, by="alice", status="rejected")
    fresh = SegmentsRecord(
        video="cameras/scene.mp4",
        duration_s=12.3,
        segments=(
            new_segment("reach", 0.1, 1.2, confidence=0.9, source=SOURCE),
            new_segment("grasp", 1.3, 2.0, confidence=0.9, source=SOURCE),  # the rejected one again
        ),
    )
    merged = merge_machine(reviewed, fresh)
    assert [(s.label, s.status) for s in merged.segments] == [("reach", "proposed"), ("grasp", "rejected")]
    assert merged.active() == (merged.segments[0],)
    assert merge_machine(None, fresh) is fresh
    # A proposal with a reviewed segment's id (same input, name-based ids) is not proposed again,
    # even when the review moved the segment far from it.
    same = new_segment("grasp", 5.0, 6.0, confidence=0.9, source=SOURCE, key="input")
    assert same == new_segment("grasp", 5.0, 6.0, confidence=0.9, source=SOURCE, key="input")
    assert same.id != new_segment("grasp", 5.0, 6.01, confidence=0.9, source=SOURCE, key="input").id
    moved = SegmentsRecord(video="v.mp4", duration_s=12.0, segments=(same,))
    moved = edit_segment(moved, same.id, by="bob", status="corrected", start_s=9.0, end_s=10.0)
    again = SegmentsRecord(video="v.mp4", duration_s=12.0, segments=(same,))
    assert [(s.start_s, s.status) for s in merge_machine(moved, again).segments] == [(9.0, "corrected")]
