"""The episode browser's API on two real demo episodes: list and filters, detail, plot, video with
Range, labels, the failures partition, export jobs in a worker process, roles, and hostile paths."""

from __future__ import annotations

import os
import shutil
import struct
import time
from collections.abc import Iterator
from pathlib import Path

import h5py
import pytest
from argon2 import PasswordHasher
from fastapi.testclient import TestClient

from telerig.server.accounts import AccountStore
from telerig.server.app import create_app
from telerig.server.auth import CSRF_HEADER, LoginLimiter
from telerig.server.jobs import ExportJobRequest, ExportParams, JobRunner, JobStore
from telerig.store.episodes import EpisodeStore
from telerig.store.index import EpisodeIndex

PASSWORD = "correct horse battery"
FAST = PasswordHasher(time_cost=1, memory_cost=64, parallelism=1)


@pytest.fixture
def root(demo_recording: Path, tmp_path: Path) -> Path:
    data = tmp_path / "data"
    shutil.copytree(demo_recording, data)
    return data


@pytest.fixture
def client(root: Path) -> Iterator[TestClient]:
    accounts = AccountStore.open(root, hasher=FAST)
    accounts.add_user("otto", "operator", PASSWORD)
    accounts.add_user("vic", "viewer", PASSWORD)
    app = create_app(accounts, limiter=LoginLimiter(failures=100), data_root=root)
    with TestClient(app) as c:
        yield c
    accounts.close()


def login(client: TestClient, user: str = "otto") -> dict[str, str]:
    reply = client.post("/api/login", json={"user": user, "password": PASSWORD})
    assert reply.status_code == 200, reply.text
    return {CSRF_HEADER: reply.json()["csrf"]}


def _ids(root: Path) -> list[str]:
    return [s.id for s in EpisodeStore(root).list(include_failures=True)]


def _listed(client: TestClient, query: str = "") -> list[str]:
    reply = client.get(f"/api/episodes{query}")
    assert reply.status_code == 200, reply.text
    return [e["id"] for e in reply.json()["episodes"]]


# --- list, detail, plot, video ------------------------------------------------------------------


def test_the_list_filters_sorts_and_pages(client: TestClient, root: Path) -> None:
    login(client, "vic")
    ids = _ids(root)
    page = client.get("/api/episodes").json()
    assert page["total"] == 2
    assert _listed(client, "?sort=start") == ids
    assert _listed(client, "?sort=-start") == ids[::-1]
    first = page["episodes"][0]
    assert first["robots"] == ["ur5e_robotiq85"]
    assert first["gates_checked"] is True
    task, operator = first["task"], first["operator"]
    assert len(_listed(client, f"?task={task}&operator={operator}&robot=ur5e_robotiq85")) == 2
    assert _listed(client, "?task=nothing") == []
    assert _listed(client, "?robot=g1") == []
    assert _listed(client, "?min_quality=0&max_quality=1") != []
    assert _listed(client, "?min_quality=0.999") == []
    assert _listed(client, "?since=2100-01-01") == []
    assert len(_listed(client, "?since=2000-01-01T00:00:00Z&until=2100-01-01")) == 2
    assert _listed(client, "?gate=joint_limits&gate_passed=false") == []
    one = client.get("/api/episodes?limit=1&offset=1&sort=start").json()
    assert (one["total"], [e["id"] for e in one["episodes"]]) == (2, ids[1:])
    statuses = {e["status"] for e in page["episodes"]}
    assert statuses <= {"complete", "failed_qa"}
    for status in statuses:
        assert status in {
            e["status"] for e in client.get(f"/api/episodes?status={status}").json()["episodes"]
        }


_BAD_FILTERS = (
    "limit=201", "limit=0", "offset=-1", "min_quality=2", "sort=size;drop", "status=gone", "since=yesterday",
    "task=" + "x" * 201, "gate=../x", "min_quality=0.9&max_quality=0.1", "outcome=maybe",
)  # fmt: skip


def test_a_bad_or_oversized_filter_is_refused(client: TestClient) -> None:
    login(client, "vic")
    for query in _BAD_FILTERS:
        assert client.get(f"/api/episodes?{query}").status_code == 422, query


def test_the_detail_has_the_manifest_cameras_gates_and_score(client: TestClient, root: Path) -> None:
    login(client, "vic")
    for episode_id in _ids(root):
        detail = client.get(f"/api/episodes/{episode_id}").json()
        assert detail["id"] == episode_id
        assert detail["partition"] in ("episodes", "failures")
        assert [c["name"] for c in detail["cameras"]] == ["scene"]
        assert {g["gate"] for g in detail["gates"]} >= {"joint_limits", "sync", "idle"}
        assert detail["score"] is not None
        assert 0.0 <= detail["score"] <= 1.0
        assert (detail["partition"] == "failures") == bool(detail["failure_reasons"])


def test_the_plot_is_a_png_cached_outside_the_episode(client: TestClient, root: Path) -> None:
    login(client, "vic")
    episode_id = _ids(root)[0]
    directory = EpisodeStore(root).episode_dir(episode_id)
    before = sorted((p.name, p.stat().st_mtime_ns) for p in directory.rglob("*"))
    reply = client.get(f"/api/episodes/{episode_id}/plot.png")
    assert reply.status_code == 200
    assert reply.headers["content-type"] == "image/png"
    png = reply.content
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    width, height = struct.unpack(">II", png[16:24])
    assert (width, height) == (1600, height)
    assert height > 400
    cached = list((root / ".cache" / "plots").glob(f"{episode_id}-*.png"))
    assert len(cached) == 1
    assert cached[0].read_bytes() == png
    assert sorted((p.name, p.stat().st_mtime_ns) for p in directory.rglob("*")) == before
    started = time.perf_counter()
    assert client.get(f"/api/episodes/{episode_id}/plot.png").content == png
    assert time.perf_counter() - started < 2.0  # served from the cache


def test_a_video_range_request_returns_206_with_those_bytes(client: TestClient, root: Path) -> None:
    login(client, "vic")
    episode_id = _ids(root)[0]
    mp4 = (EpisodeStore(root).episode_dir(episode_id) / "cameras" / "scene.mp4").read_bytes()
    whole = client.get(f"/api/episodes/{episode_id}/video/scene")
    assert whole.status_code == 200
    assert whole.headers["content-type"] == "video/mp4"
    assert whole.headers["accept-ranges"] == "bytes"
    assert whole.content == mp4
    part = client.get(f"/api/episodes/{episode_id}/video/scene", headers={"Range": "bytes=100-1099"})
    assert part.status_code == 206
    assert part.headers["content-range"] == f"bytes 100-1099/{len(mp4)}"
    assert part.content == mp4[100:1100]
    tail = client.get(f"/api/episodes/{episode_id}/video/scene", headers={"Range": "bytes=-10"})
    assert tail.status_code == 206
    assert tail.content == mp4[-10:]
    beyond = client.get(
        f"/api/episodes/{episode_id}/video/scene", headers={"Range": f"bytes={len(mp4) + 5}-"}
    )
    assert beyond.status_code == 416


# --- labels, failures ---------------------------------------------------------------------------


def test_a_label_persists_and_shows_in_the_list_and_the_audit_log(client: TestClient, root: Path) -> None:
    csrf = login(client)
    first, second = _ids(root)
    reply = client.post(f"/api/episodes/{first}/label", json={"outcome": "success"}, headers=csrf)
    assert reply.status_code == 200, reply.text
    assert reply.json()["by"] == "otto"
    client.post(f"/api/episodes/{second}/label", json={"outcome": "failure"}, headers=csrf)
    assert _listed(client, "?outcome=success") == [first]
    assert _listed(client, "?outcome=failure") == [second]
    rows = {e["id"]: e["outcome"] for e in client.get("/api/episodes").json()["episodes"]}
    assert rows == {first: "success", second: "failure"}
    assert client.get(f"/api/episodes/{first}").json()["label"]["outcome"] == "success"
    # relabel; the file beside qa.json is what a rebuilt index and the exports read
    client.post(f"/api/episodes/{first}/label", json={"outcome": "failure"}, headers=csrf)
    with EpisodeIndex.open("sqlite://") as index:
        index.rebuild(EpisodeStore(root))
        assert index.get(first).outcome == "failure"
    for bad in ({"outcome": "maybe"}, {}, {"outcome": "success", "by": "ada"}):
        assert client.post(f"/api/episodes/{first}/label", json=bad, headers=csrf).status_code == 422
    audit = AccountStore.open(root, hasher=FAST).audit_log()
    labelled = [(e.user, e.target, e.detail) for e in audit if e.action == "episode_labelled"]
    assert labelled[0] == ("otto", first, "failure")
    assert len(labelled) == 3


def test_move_to_failures_and_back(client: TestClient, root: Path) -> None:
    csrf = login(client)
    episode_id = _ids(root)[0]
    store = EpisodeStore(root)
    if store.find(episode_id).partition == "failures":  # the station's gates may have moved it already
        assert (
            client.post(f"/api/episodes/{episode_id}/restore", headers=csrf).json()["partition"] == "episodes"
        )
    assert store.find(episode_id).partition == "episodes"
    assert client.post(f"/api/episodes/{episode_id}/restore", headers=csrf).status_code == 409
    reply = client.post(f"/api/episodes/{episode_id}/failures", headers=csrf)
    assert reply.json() == {"episode_id": episode_id, "partition": "failures"}
    assert client.post(f"/api/episodes/{episode_id}/failures", headers=csrf).status_code == 409
    failure = store.failure(episode_id)
    assert failure is not None
    assert failure.reasons == ("moved by otto",)
    assert client.get(f"/api/episodes/{episode_id}").json()["failure_reasons"] == ["moved by otto"]
    assert episode_id in _listed(client, "?status=failed_qa")
    assert client.post(f"/api/episodes/{episode_id}/restore", headers=csrf).status_code == 200
    assert store.find(episode_id).partition == "episodes"
    assert episode_id not in _listed(client, "?status=failed_qa")
    actions = [e.action for e in AccountStore.open(root, hasher=FAST).audit_log()]
    assert actions.count("episode_to_failures") == 1
    assert "episode_restored" in actions


# --- jobs -----------------------------------------------------------------------------------------


def test_an_export_job_runs_in_a_worker_process_with_visible_progress(client: TestClient, root: Path) -> None:
    csrf = login(client)
    labelled = _ids(root)[0]
    client.post(f"/api/episodes/{labelled}/label", json={"outcome": "success"}, headers=csrf)
    params = {"format": "hdf5", "name": "lab-set_1", "include_failures": True}
    reply = client.post("/api/jobs", json={"kind": "export", "params": params}, headers=csrf)
    assert reply.status_code == 202, reply.text
    job = reply.json()
    assert job["state"] in ("queued", "running")
    seen: list[tuple[str, int, int, str]] = []
    deadline = time.monotonic() + 120
    while job["state"] in ("queued", "running"):
        assert time.monotonic() < deadline, f"export job still {job['state']} after 120 s: {seen[-3:]}"
        time.sleep(0.2)
        job = client.get(f"/api/jobs/{job['id']}").json()
        seen.append((job["state"], job["done"], job["total"], job["message"]))
        if job["state"] == "running":
            assert job["worker_pid"] not in (None, os.getpid())
    assert job["state"] == "done", job["error"]
    assert (job["done"], job["total"]) == (2, 2)
    assert any(state == "running" for state, *_ in seen)
    assert job["result"]["out"] == "exports/lab-set_1"
    assert sorted(job["result"]["added"]) == _ids(root)
    with h5py.File(root / "exports" / "lab-set_1" / "episodes" / f"{labelled}.hdf5", "r") as f:
        assert f["metadata"].attrs["outcome"] == "success"  # the label reached the dataset
    # every client sees it
    login(client, "vic")
    assert [j["id"] for j in client.get("/api/jobs").json()] == [job["id"]]
    assert client.get("/api/jobs?state=done").json()[0]["result"]["added"] == job["result"]["added"]


_BAD_JOBS: tuple[dict[str, object], ...] = (
    {"kind": "export", "params": {"format": "hdf5", "name": "../escape"}},
    {"kind": "export", "params": {"format": "hdf5", "name": "/tmp/x"}},
    {"kind": "export", "params": {"format": "hdf5", "name": ".hidden"}},
    {"kind": "export", "params": {"format": "hdf5", "name": "n" * 65}},
    {"kind": "export", "params": {"format": "zip", "name": "ok"}},
    {"kind": "export", "params": {"format": "hdf5", "name": "ok", "ids": ["ep-20261125-213901-df55"] * 1001}},
    {"kind": "export", "params": {"format": "hdf5", "name": "ok", "ids": ["../../etc/passwd"]}},
    {"kind": "export", "params": {"format": "hdf5", "name": "ok", "task": "t" * 201}},
    {"kind": "export", "params": {"format": "hdf5", "name": "ok", "out": "/tmp"}},
    {"kind": "qa", "params": {"recheck": True, "thresholds": {}}},
    {"kind": "shell", "params": {}},
)


def test_bad_or_oversized_job_params_are_refused(client: TestClient, root: Path) -> None:
    csrf = login(client)
    for body in _BAD_JOBS:
        assert client.post("/api/jobs", json=body, headers=csrf).status_code == 422, body
    assert client.get("/api/jobs").json() == []
    assert not (root / "exports").exists()


def test_a_restart_marks_running_jobs_whose_worker_is_gone_failed(tmp_path: Path) -> None:
    store = JobStore(tmp_path)
    request = ExportJobRequest(kind="export", params=ExportParams(format="hdf5", name="x"))
    lost = store.add(request, "otto")
    store.claim(lost.id, pid=2**22 + 12345)  # no such process
    alive = store.add(request, "otto")
    store.claim(alive.id, pid=os.getpid())  # a process, but not this job's worker
    runner = JobRunner(tmp_path, max_running=0)  # starts nothing: only the recovery is under test
    assert sorted(runner.recover()) == [lost.id, alive.id]
    for job_id in (lost.id, alive.id):
        job = store.get(job_id)
        assert job.state == "failed"
        assert job.error is not None
        assert "worker process is gone" in job.error
    runner.close()
    store.close()


# --- security ---------------------------------------------------------------------------------------


def test_a_viewer_cannot_label_move_or_start_jobs(client: TestClient, root: Path) -> None:
    csrf = login(client, "vic")
    episode_id = _ids(root)[0]
    where = EpisodeStore(root).find(episode_id).partition
    for path, body in (
        (f"/api/episodes/{episode_id}/label", {"outcome": "success"}),
        (f"/api/episodes/{episode_id}/failures", None),
        (f"/api/episodes/{episode_id}/restore", None),
        ("/api/jobs", {"kind": "qa", "params": {}}),
    ):
        assert client.post(path, json=body, headers=csrf).status_code == 403, path
    assert EpisodeStore(root).find(episode_id).partition == where
    assert not (EpisodeStore(root).episode_dir(episode_id) / "label.json").exists()
    assert client.get("/api/jobs").json() == []


def test_an_operator_needs_the_csrf_token(client: TestClient, root: Path) -> None:
    login(client)
    episode_id = _ids(root)[0]
    assert client.post(f"/api/episodes/{episode_id}/label", json={"outcome": "success"}).status_code == 403
    assert client.post("/api/jobs", json={"kind": "qa", "params": {}}).status_code == 403


def test_every_episode_and_job_route_needs_a_session(client: TestClient, root: Path) -> None:
    episode_id = _ids(root)[0]
    spec = client.get("/openapi.json").json()["paths"]
    routes = [
        (method.upper(), path)
        for path, operations in spec.items()
        if path.startswith(("/api/episodes", "/api/jobs"))
        for method in operations
    ]
    assert len(routes) == 10
    for method, template in routes:
        path = (
            template.replace("{episode_id}", episode_id).replace("{camera}", "scene").replace("{job_id}", "1")
        )
        assert client.request(method, path, json={}).status_code == 401, (method, path)


_HOSTILE_PATHS = (
    "/api/episodes/..%2F..%2Fcontrol.sqlite",
    "/api/episodes/%2Fetc%2Fpasswd",
    "/api/episodes/ep-20261125-213901-df55x",
    "/api/episodes/ep-20261125-213901-df5",
    "/api/episodes/ep-20261125-213901-DF55",
    "/api/episodes/ep-20261125-213901-df55%00",
    "/api/episodes/..",
    "/api/episodes/ep-20200101-000000-0000",
    "/api/episodes/ep-20200101-000000-0000/plot.png",
    "/api/episodes/ep-20200101-000000-0000/video/scene",
    "/api/episodes/ep-20261125-213901-df55/../../control.sqlite",
    "/api/jobs/0",
    "/api/jobs/..%2F1",
    "/api/jobs/99",
)


def test_hostile_episode_paths_are_refused(client: TestClient) -> None:
    login(client, "vic")
    for path in _HOSTILE_PATHS:
        assert client.get(path).status_code in (404, 422), path


_HOSTILE_CAMERAS = (
    "%2E%2E", "..%2F..%2Fmanifest.json", "%2Fetc%2Fpasswd", "manifest.json", "episode", ".scene", "scene.mp4",
    "scene%00", "c" * 65, "..%2Fepisode.mcap", "..%2Fqa.json", "%2E%2E%2Fepisode.mcap",
)  # fmt: skip


def test_only_the_manifest_cameras_are_served(client: TestClient, root: Path) -> None:
    login(client, "vic")
    episode_id = _ids(root)[0]
    for camera in _HOSTILE_CAMERAS:
        reply = client.get(f"/api/episodes/{episode_id}/video/{camera}")
        assert reply.status_code in (404, 422), camera
        assert reply.headers["content-type"] == "application/json", camera


def test_the_openapi_spec_documents_the_episode_and_job_routes(client: TestClient) -> None:
    spec = client.get("/openapi.json").json()
    paths = spec["paths"]
    for path, method in (
        ("/api/episodes", "get"),
        ("/api/episodes/{episode_id}", "get"),
        ("/api/episodes/{episode_id}/plot.png", "get"),
        ("/api/episodes/{episode_id}/video/{camera}", "get"),
        ("/api/episodes/{episode_id}/label", "post"),
        ("/api/episodes/{episode_id}/failures", "post"),
        ("/api/episodes/{episode_id}/restore", "post"),
        ("/api/jobs", "post"),
        ("/api/jobs", "get"),
        ("/api/jobs/{job_id}", "get"),
    ):
        operation = paths[path][method]
        assert operation["responses"], path
        assert "401" in operation["responses"], path
    schemas = spec["components"]["schemas"]
    assert {"EpisodePage", "EpisodeDetail", "Job", "ExportParams", "QaParams", "LabelOut"} <= set(schemas)
    assert "image/png" in paths["/api/episodes/{episode_id}/plot.png"]["get"]["responses"]["200"]["content"]
    assert "206" in paths["/api/episodes/{episode_id}/video/{camera}"]["get"]["responses"]


def test_the_episode_page_is_served_and_linked(client: TestClient) -> None:
    before = client.get("/episodes", follow_redirects=False)
    assert (before.status_code, before.headers["location"]) == (303, "/login")
    login(client, "vic")
    page = client.get("/episodes")
    assert page.status_code == 200
    assert "default-src 'self'" in page.headers["content-security-policy"]
    assert '<script src="/assets/episodes.js"' in page.text
    script = client.get("/assets/episodes.js")
    assert script.status_code == 200
    assert "innerHTML" not in script.text
    assert "X-CSRF-Token" in script.text
    assert 'href="/episodes"' in client.get("/").text


def test_a_quality_check_job_rechecks_an_episode_in_a_worker(client: TestClient, root: Path) -> None:
    csrf = login(client)
    episode_id = _ids(root)[0]
    directory = EpisodeStore(root).episode_dir(episode_id)
    checked = (directory / "qa.json").stat().st_mtime_ns
    reply = client.post("/api/jobs", json={"kind": "qa", "params": {"ids": [episode_id]}}, headers=csrf)
    assert reply.status_code == 202, reply.text
    job = reply.json()
    deadline = time.monotonic() + 120
    while job["state"] in ("queued", "running"):
        assert time.monotonic() < deadline, f"qa job still {job['state']} after 120 s"
        time.sleep(0.2)
        job = client.get(f"/api/jobs/{job['id']}").json()
    assert job["state"] == "done", job["error"]
    assert (job["done"], job["total"]) == (1, 1)
    assert job["result"]["summary"].startswith("1 checked")
    after = EpisodeStore(root).episode_dir(episode_id)  # it may have moved (the gates decide)
    assert (after / "qa.json").stat().st_mtime_ns > checked
