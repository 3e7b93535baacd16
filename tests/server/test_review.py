"""Segment review (issue 15) on a real demo episode's segments sidecar and a real processed plain
video: roles, CSRF, optimistic concurrency (409 on a stale version), hostile input refused in one
line, edits stamped with the reviewer and read back by ``telerig.store.segments_file``, a machine
re-run's merge keeping them, the video served with Range, and the page driven by keys in Chromium."""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import av
import numpy as np
import pytest
from argon2 import PasswordHasher
from fastapi.testclient import TestClient

from telerig.process.stage import video_item_id
from telerig.server.accounts import AccountStore
from telerig.server.app import create_app
from telerig.server.auth import CSRF_HEADER, LoginLimiter
from telerig.store.episodes import EpisodeManifest, EpisodeStore
from telerig.store.manifest_extra import EpisodeExtra
from telerig.store.segments_file import (
    SegmentsRecord,
    machine_source,
    merge_machine,
    new_segment,
    read_episode_segments,
    read_segments,
    write_episode_segments,
    write_segments,
)

PASSWORD = "correct horse battery"
FAST = PasswordHasher(time_cost=1, memory_cost=64, parallelism=1)
SOURCE = machine_source("robot_streams", "1")
LABELS = ("reach", "grasp", "transport")


def _machine_record(episode_id: str, video: str, duration: float) -> SegmentsRecord:
    """Three machine proposals spread over the video (what the segment stage writes)."""
    third = duration / 3
    segments = tuple(
        new_segment(
            label,
            i * third,
            (i + 1) * third - 0.02,
            confidence=0.7,
            source=SOURCE,
            key=f"test|{episode_id}",
        )
        for i, label in enumerate(LABELS)
    )
    return SegmentsRecord(video=video, duration_s=duration, segments=segments, episode_id=episode_id)


def seed(root: Path) -> tuple[str, Path, SegmentsRecord]:
    """Write a machine segments sidecar on the first demo episode (in episodes/ or failures/)."""
    summary = EpisodeStore(root).list(include_failures=True)[0]
    manifest = EpisodeManifest.model_validate_json((summary.path / "manifest.json").read_bytes())
    camera = sorted(EpisodeExtra.of(manifest).cameras.items())[0][1]
    with av.open(str(summary.path / camera.file)) as container:  # the file's own length
        stream = container.streams.video[0]
        assert stream.duration is not None
        duration = round(float(stream.duration * stream.time_base), 2)
    assert duration >= 0.3, f"the demo camera video is {duration} s long"
    record = _machine_record(summary.id, camera.file, duration)
    write_episode_segments(summary.path, record)
    return summary.id, summary.path, record


@pytest.fixture
def root(demo_recording: Path, tmp_path: Path) -> Path:
    data = tmp_path / "data"
    shutil.copytree(demo_recording, data)
    return data


@pytest.fixture
def app(root: Path) -> Iterator[Any]:
    accounts = AccountStore.open(root, hasher=FAST)
    accounts.add_user("otto", "operator", PASSWORD)
    accounts.add_user("olga", "operator", PASSWORD)
    accounts.add_user("vic", "viewer", PASSWORD)
    yield create_app(accounts, limiter=LoginLimiter(failures=1000), data_root=root)
    accounts.close()


def client_for(app: Any, user: str) -> tuple[TestClient, dict[str, str]]:
    client = TestClient(app)
    reply = client.post("/api/login", json={"user": user, "password": PASSWORD})
    assert reply.status_code == 200, reply.text
    return client, {CSRF_HEADER: reply.json()["csrf"]}


def _post(client: TestClient, item: str, csrf: dict[str, str], body: dict[str, Any]) -> Any:
    return client.post(f"/api/review/{item}/edits", json=body, headers=csrf)


def test_edits_are_stamped_written_through_the_store_and_survive_a_machine_rerun(
    app: Any, root: Path
) -> None:
    ep, directory, machine = seed(root)
    otto, csrf = client_for(app, "otto")
    listed = otto.get("/api/review").json()
    assert [(r["id"], r["kind"], r["segments"], r["proposed"]) for r in listed] == [(ep, "episode", 3, 3)]
    got = otto.get(f"/api/review/{ep}")
    assert got.status_code == 200, got.text
    detail = got.json()
    assert got.headers["etag"] == f'"{detail["version"]}"'
    first, second, third = (s["id"] for s in detail["segments"])
    version = detail["version"]
    middle = round((machine.segments[2].start_s + machine.segments[2].end_s) / 2, 2)

    steps: list[dict[str, Any]] = [
        {"op": "accept", "segment_id": first},
        {"op": "reject", "segment_id": second},
        {"op": "rename", "segment_id": third, "label": "  place  "},
        {"op": "bounds", "segment_id": third, "start_s": middle + 0.004, "end_s": machine.duration_s},
        {"op": "add", "label": "wave", "start_s": 0.0, "end_s": 0.1, "actor": "left_hand"},
    ]
    for body in steps:
        reply = _post(otto, ep, csrf, {**body, "version": version})
        assert reply.status_code == 200, (body, reply.text)
        assert reply.json()["version"] != version
        version = reply.json()["version"]

    record = read_episode_segments(directory)
    assert record is not None
    by_id = {s.id: s for s in record.segments}
    assert (by_id[first].status, by_id[first].source, by_id[first].origin) == (
        "accepted",
        "human:otto",
        SOURCE,
    )
    assert by_id[second].status == "rejected"
    assert (by_id[third].label, by_id[third].start_s, by_id[third].status) == ("place", middle, "corrected")
    drawn = [s for s in record.segments if s.id not in {first, second, third}]
    assert [(s.label, s.start_s, s.end_s, s.source, s.status, s.actor) for s in drawn] == [
        ("wave", 0.0, 0.1, "human:otto", "corrected", "left_hand")
    ]
    assert all(s.edited_at is not None for s in record.segments)

    # undo: the drawn segment goes again; a second undo restores the machine bounds' predecessor
    reply = _post(otto, ep, csrf, {"op": "undo", "version": version})
    assert reply.status_code == 200, reply.text
    assert len(reply.json()["segments"]) == 3
    reply = _post(otto, ep, csrf, {"op": "undo", "version": reply.json()["version"]})
    restored = {s["id"]: s for s in reply.json()["segments"]}[third]
    assert (restored["label"], restored["start_s"]) == ("place", machine.segments[2].start_s)

    # a machine re-run (the segment stage merges through the store) keeps every human edit
    fresh = _machine_record(ep, machine.video, machine.duration_s)
    merged = merge_machine(read_episode_segments(directory), fresh)
    write_episode_segments(directory, merged)
    after = {s.id: s for s in merged.segments}
    assert after[first].status == "accepted"
    assert after[second].status == "rejected"
    assert after[third].label == "place"
    assert len(merged.segments) == 3

    audit = [e for e in app.state.accounts.audit_log(limit=50) if e.action == "segments_edited"]
    assert len(audit) == 7
    assert {e.user for e in audit} == {"otto"}
    assert {e.target for e in audit} == {ep}


def test_a_stale_version_is_refused_with_409(app: Any, root: Path) -> None:
    ep, directory, _ = seed(root)
    otto, otto_csrf = client_for(app, "otto")
    olga, olga_csrf = client_for(app, "olga")
    seen = otto.get(f"/api/review/{ep}").json()
    assert olga.get(f"/api/review/{ep}").json()["version"] == seen["version"]
    target = seen["segments"][0]["id"]
    assert (
        _post(
            olga, ep, olga_csrf, {"op": "reject", "segment_id": target, "version": seen["version"]}
        ).status_code
        == 200
    )
    stale = _post(otto, ep, otto_csrf, {"op": "accept", "segment_id": target, "version": seen["version"]})
    assert stale.status_code == 409
    assert "changed since version" in stale.json()["detail"]
    assert "\n" not in stale.json()["detail"]
    record = read_episode_segments(directory)
    assert record is not None
    assert record.segments[0].source == "human:olga"
    # otto cannot undo olga's edit: he has nothing to undo
    now = otto.get(f"/api/review/{ep}").json()["version"]
    assert _post(otto, ep, otto_csrf, {"op": "undo", "version": now}).status_code == 409


def test_roles_and_csrf(app: Any, root: Path) -> None:
    ep, directory, _ = seed(root)
    before = (directory / "segments.json").read_bytes()
    anonymous = TestClient(app)
    assert anonymous.get("/api/review").status_code == 401
    assert anonymous.get(f"/api/review/{ep}").status_code == 401
    assert anonymous.get(f"/api/review/{ep}/video").status_code == 401
    vic, vic_csrf = client_for(app, "vic")
    detail = vic.get(f"/api/review/{ep}").json()  # a viewer reads
    body = {"op": "accept", "segment_id": detail["segments"][0]["id"], "version": detail["version"]}
    assert _post(vic, ep, vic_csrf, body).status_code == 403
    otto, _ = client_for(app, "otto")
    assert _post(otto, ep, {}, body).status_code == 403
    assert _post(otto, ep, {CSRF_HEADER: "forged"}, body).status_code == 403
    assert (directory / "segments.json").read_bytes() == before
    assert anonymous.get("/review", follow_redirects=False).status_code == 303
    page = otto.get("/review")
    assert page.status_code == 200
    assert "default-src 'self'" in page.headers["content-security-policy"]


BAD_BODIES: list[Any] = [
    {"op": "bounds", "start_s": float("nan")},
    {"op": "bounds", "end_s": float("inf")},
    {"op": "bounds", "start_s": -1.0},
    {"op": "bounds", "end_s": 1e9},
    {"op": "bounds", "end_s": 99999.0},  # after the video's end
    {"op": "bounds", "start_s": 0.2, "end_s": 0.2},  # start not before end
    {"op": "bounds", "start_s": 0.204, "end_s": 0.201},  # equal once rounded to 0.01 s
    {"op": "bounds"},
    {"op": "bounds", "start_s": "soon"},
    {"op": "rename", "label": "x" * 65},
    {"op": "rename", "label": "   "},
    {"op": "rename", "label": "bad\nlabel"},
    {"op": "rename", "label": "x" * 1_000_000},
    {"op": "add", "label": "a", "start_s": 0.2, "end_s": 0.1},
    {"op": "add", "label": "a", "start_s": 0.0, "end_s": 99999.0},
    {"op": "explode"},
    {"op": "accept", "segment_id": "../../etc/passwd"},
    {"op": "accept", "extra": 1},
    {"op": "accept", "version": "not-a-version"},
    [],
    None,
    "accept",
]


def test_bad_edits_are_refused_in_one_line_and_change_nothing(app: Any, root: Path) -> None:
    ep, directory, _ = seed(root)
    before = (directory / "segments.json").read_bytes()
    otto, csrf = client_for(app, "otto")
    detail = otto.get(f"/api/review/{ep}").json()
    seg = detail["segments"][0]["id"]
    for bad in BAD_BODIES:
        body = bad
        if isinstance(bad, dict):
            body = {"segment_id": seg, "version": detail["version"], **bad}
            if bad.get("op") == "add":
                body.pop("segment_id")
        raw = json.dumps(body, allow_nan=True)
        reply = otto.post(
            f"/api/review/{ep}/edits", content=raw, headers={**csrf, "content-type": "application/json"}
        )
        assert reply.status_code == 422, (bad, reply.status_code, reply.text[:200])
        detail_text = reply.json()["detail"]
        assert isinstance(detail_text, str), detail_text
        assert "\n" not in detail_text, detail_text
        assert len(detail_text) <= 300, detail_text
    for garbage in (b"{", b"\xff\xfe", b"[" * 10_000, b'{"op": "accept"' + b" " * (2 << 20) + b"}"):
        reply = otto.post(
            f"/api/review/{ep}/edits", content=garbage, headers={**csrf, "content-type": "application/json"}
        )
        assert reply.status_code in (400, 422), (garbage[:20], reply.text[:200])
        assert isinstance(reply.json()["detail"], str)
    unknown = _post(
        otto,
        ep,
        csrf,
        {"op": "accept", "segment_id": "0" * 8 + "-0000-4000-8000-" + "0" * 12, "version": detail["version"]},
    )
    assert unknown.status_code == 404
    assert (directory / "segments.json").read_bytes() == before


def test_a_damaged_sidecar_is_refused_in_one_line_and_left_alone(app: Any, root: Path) -> None:
    ep, directory, _ = seed(root)
    otto, csrf = client_for(app, "otto")
    version = otto.get(f"/api/review/{ep}").json()["version"]
    for damaged in (b"{not json", b'{"schema": 1, "video": "x", "duration_s": NaN}', b"[]" * 5_000_000):
        (directory / "segments.json").write_bytes(damaged)
        reply = otto.get(f"/api/review/{ep}")
        assert reply.status_code == 409, reply.text[:200]
        assert "\n" not in reply.json()["detail"]
        assert otto.get("/api/review").json() == []  # the list leaves it out instead of failing
        edit = _post(otto, ep, csrf, {"op": "undo", "version": version})
        assert edit.status_code == 409
        assert (directory / "segments.json").read_bytes() == damaged
    other = SegmentsRecord(video="cameras/x.mp4", duration_s=1.0, episode_id="ep-20990101-000000-abcd")
    (directory / "segments.json").write_text(other.to_json())
    assert "another episode" in otto.get(f"/api/review/{ep}").json()["detail"]


def test_hostile_ids_are_refused_and_nothing_outside_is_served(app: Any, root: Path, tmp_path: Path) -> None:
    seed(root)
    otto, _ = client_for(app, "otto")
    for item in (
        "..",
        "..%2F..%2Fetc%2Fpasswd",
        "ep-1",
        "video-../../x",
        "video-ZZZZZZZZZZZZ",
        "a" * 5000,
        "%00",
    ):
        for suffix in ("", "/video"):
            assert otto.get(f"/api/review/{item}{suffix}").status_code in (404, 422), item
    assert otto.get("/api/review/ep-20990101-000000-abcd").status_code == 404
    # a processed item whose record names a file that is not the item's video: not served
    secret = tmp_path / "secret.mp4"
    secret.write_bytes(b"not yours")
    forged = "video-" + "0" * 12
    (root / "processed" / "items" / forged / "segment").mkdir(parents=True)
    write_segments(
        root / "processed" / "items" / forged / "segment" / "segments.json",
        SegmentsRecord(video=str(secret), duration_s=1.0),
    )
    assert otto.get(f"/api/review/{forged}").status_code == 200
    assert otto.get(f"/api/review/{forged}/video").status_code == 404


def _make_video(path: Path, seconds: float = 2.0, fps: int = 10) -> Path:
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=fps, options={"preset": "ultrafast"})
        stream.width, stream.height, stream.pix_fmt = 160, 120, "yuv420p"
        image = np.zeros((120, 160, 3), dtype=np.uint8)
        for i in range(round(seconds * fps)):
            image[:] = (9 * i) % 256
            for packet in stream.encode(av.VideoFrame.from_ndarray(image, format="rgb24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    return path


def test_a_processed_plain_video_is_listed_served_with_range_and_edited(
    app: Any, root: Path, tmp_path: Path
) -> None:
    folder = tmp_path / "phone"
    folder.mkdir()
    video = _make_video(folder / "kitchen.mp4")
    item = video_item_id(video)
    path = root / "processed" / "items" / item / "segment" / "segments.json"
    path.parent.mkdir(parents=True)
    segment = new_segment(
        "stir", 0.2, 1.5, confidence=0.6, source=machine_source("hand_motion", "1"), key="k"
    )
    write_segments(path, SegmentsRecord(video=str(video.resolve()), duration_s=2.0, segments=(segment,)))
    annotate = root / "processed" / "items" / item / "annotate"
    annotate.mkdir()
    (annotate / "annotations.json").write_text(
        json.dumps({segment.id: {"scene": "kitchen", "action": {"description": "a hand stirs a pot"}}})
    )
    otto, csrf = client_for(app, "otto")
    assert [(r["id"], r["kind"], r["title"]) for r in otto.get("/api/review").json()] == [
        (item, "video", "kitchen.mp4")
    ]
    detail = otto.get(f"/api/review/{item}").json()
    assert detail["video"] == "kitchen.mp4"  # no absolute path of the host in the answer
    assert detail["segments"][0]["annotation"] == "kitchen: a hand stirs a pot"
    part = otto.get(f"/api/review/{item}/video", headers={"Range": "bytes=0-99"})
    assert part.status_code == 206
    assert part.content == video.read_bytes()[:100]
    assert part.headers["content-type"] == "video/mp4"
    reply = _post(
        otto,
        item,
        csrf,
        {"op": "bounds", "segment_id": segment.id, "end_s": 1.999, "version": detail["version"]},
    )
    assert reply.status_code == 200, reply.text
    back = read_segments(path)  # the stage's copy, which the clips stage reads
    assert (back.segments[0].end_s, back.segments[0].source, back.segments[0].status) == (
        2.0,
        "human:otto",
        "corrected",
    )
    assert read_segments(path.parent.parent / "review" / "segments.json") == back

    # a segment stage re-run (a new version) empties its directory and proposes afresh: the review
    # stays, merged over the new proposals as the store's merge_machine does for an episode
    shutil.rmtree(path.parent)
    path.parent.mkdir()
    later = new_segment("pour", 0.1, 0.5, confidence=0.5, source=machine_source("hand_motion", "2"), key="k")
    redo = new_segment("stir", 0.2, 1.5, confidence=0.6, source=machine_source("hand_motion", "2"), key="k")
    write_segments(path, SegmentsRecord(video=str(video.resolve()), duration_s=2.0, segments=(later, redo)))
    now = otto.get(f"/api/review/{item}").json()["segments"]
    # the fresh "pour" is new; the fresh "stir" mostly covers the reviewed one (IoU 0.72): dropped
    assert [(s["label"], s["source"], s["end_s"]) for s in now] == [
        ("pour", "machine:hand_motion@2", 0.5),
        ("stir", "human:otto", 2.0),
    ]


# -- the page in Chromium --------------------------------------------------------------------------


@pytest.mark.browser
def test_review_a_demo_episode_with_keys_in_chromium(
    root: Path,
    app: Any,
    page: Any,
    live_server: Callable[..., str],
    log_in: Callable[..., None],
    tmp_path: Path,
) -> None:
    from playwright.sync_api import expect  # locator assertions: no eval, which the page's CSP forbids

    ep, directory, machine = seed(root)
    base = live_server(app)
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    log_in(page, base, "otto", PASSWORD, start="/episodes")
    page.click("a[href='/review']")  # the nav link
    page.wait_for_selector(f"#items tbody tr[data-id='{ep}']")
    page.goto(f"{base}/episodes")
    page.wait_for_selector("#episodes tbody tr")
    page.locator("#episodes tbody tr", has_text=ep).click()
    expect(page.locator("#review-link")).to_have_attribute("href", f"/review?item={ep}")
    page.click("#review-link")  # the episode detail page's link
    page.wait_for_selector("body[data-ready='1']")
    bars = page.locator("#timeline .seg")
    expect(bars).to_have_count(3)
    expect(page.locator("#timeline .seg.selected")).to_have_attribute("data-id", machine.segments[0].id)
    duration = page.eval_on_selector(
        "video",
        "v => new Promise(done => { if (v.readyState >= 1) done(v.duration);"
        " v.onloadedmetadata = () => done(v.duration); v.onerror = () => done(-1); })",
    )
    assert duration > 0

    def edited(version: str) -> str:
        expect(page.locator("body")).not_to_have_attribute("data-version", version)
        now: str = page.get_attribute("body", "data-version") or ""
        return now

    def playhead() -> float:
        at: float = page.eval_on_selector("video", "v => v.currentTime")
        return at

    version = page.get_attribute("body", "data-version") or ""
    page.keyboard.press("a")  # accept the first
    version = edited(version)
    page.keyboard.press("j")
    page.keyboard.press("r")  # reject the second
    version = edited(version)
    page.keyboard.press("j")  # the third, the video seeks to its start
    expect(page.locator("#timeline .seg.selected")).to_have_attribute("data-id", machine.segments[2].id)
    target = round((machine.segments[2].start_s + machine.segments[2].end_s) / 2, 2)
    page.eval_on_selector("video", f"v => {{ v.currentTime = {target}; }}")  # the reviewer scrubs
    deadline = time.monotonic() + 10
    while abs(playhead() - target) > 0.005:
        assert time.monotonic() < deadline, f"the video did not seek to {target} s"
        time.sleep(0.05)
    page.keyboard.press("[")  # its start to the playhead
    version = edited(version)
    expect(page.locator("#segments tbody tr[data-status='rejected']")).to_have_count(1)
    page.keyboard.press("e")  # rename inline
    page.keyboard.type("lift")
    page.keyboard.press("Enter")
    version = edited(version)
    expect(page.locator("#timeline .seg.selected")).to_have_text("lift")
    page.keyboard.press("n")  # draw one at the playhead, then undo it
    page.keyboard.type("wave")
    page.keyboard.press("Enter")
    version = edited(version)
    expect(bars).to_have_count(4)
    page.keyboard.press("u")
    version = edited(version)
    expect(bars).to_have_count(3)
    page.screenshot(path=str(tmp_path / "review.png"), full_page=True)

    record = read_episode_segments(directory)
    assert record is not None
    by_id = {s.id: s for s in record.segments}
    first, second, third = (by_id[s.id] for s in machine.segments)
    assert (first.status, first.source) == ("accepted", "human:otto")
    assert (second.status, second.source) == ("rejected", "human:otto")
    assert (third.status, third.start_s, third.end_s, third.label) == (
        "corrected",
        target,
        machine.segments[2].end_s,
        "lift",
    )
    assert errors == []
