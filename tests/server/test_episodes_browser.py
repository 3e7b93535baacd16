"""The episode browser in headless Chromium on a real server: log in, open a recorded episode, see its
plot, play its video (seekable: the server answers ranges), label it, and see the label in the list."""

from __future__ import annotations

import shutil
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import uvicorn
from argon2 import PasswordHasher

from telerig.server.accounts import AccountStore
from telerig.server.app import create_app
from telerig.store.episodes import EpisodeStore
from telerig.store.label_file import read_label

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
PASSWORD = "correct horse battery"

pytestmark = pytest.mark.browser


@pytest.fixture
def server(demo_recording: Path, tmp_path: Path) -> Iterator[tuple[str, Path]]:
    if not CHROMIUM.exists():
        pytest.fail(f"Chromium is missing at {CHROMIUM}: run `make sysdeps-test` (apt-get install chromium)")
    root = tmp_path / "data"
    shutil.copytree(demo_recording, root)
    accounts = AccountStore.open(root, hasher=PasswordHasher(time_cost=1, memory_cost=64, parallelism=1))
    accounts.add_user("otto", "operator", PASSWORD)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    config = uvicorn.Config(
        create_app(accounts, data_root=root), host="127.0.0.1", port=port, log_level="warning", ws="none"
    )
    web = uvicorn.Server(config)
    thread = threading.Thread(target=web.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not web.started:
        assert time.monotonic() < deadline, "the server did not start in 30 s"
        time.sleep(0.05)
    try:
        yield f"http://127.0.0.1:{port}", root
    finally:
        web.should_exit = True
        thread.join(20)
        accounts.close()


@pytest.fixture
def page(tmp_path: Path) -> Iterator[Any]:
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        context = pw.chromium.launch_persistent_context(
            str(tmp_path / "profile"),
            executable_path=str(CHROMIUM),
            headless=True,
            args=CHROMIUM_ARGS,
            viewport={"width": 1280, "height": 900},
        )
        try:
            yield context.new_page()
        finally:
            context.close()


def test_open_a_recorded_episode_see_its_plot_video_and_label_it(
    server: tuple[str, Path], page: Any, tmp_path: Path
) -> None:
    base, root = server
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.goto(f"{base}/episodes")
    page.wait_for_url(f"{base}/login")
    page.fill("input[name=user]", "otto")
    page.fill("input[name=password]", PASSWORD)
    page.click("button[type=submit]")
    page.wait_for_url(f"{base}/")
    page.click("a[href='/episodes']")
    page.wait_for_selector("#episodes tbody tr")
    rows = page.locator("#episodes tbody tr")
    assert rows.count() == 2
    newest = EpisodeStore(root).list(include_failures=True)[-1]
    assert rows.first.locator("td").first.text_content() == newest.id
    rows.first.click()
    page.wait_for_selector("#plot:not([hidden])", timeout=120_000)
    assert page.eval_on_selector("#plot", "img => img.naturalWidth") == 1600
    duration = page.eval_on_selector(
        "video",
        "v => new Promise(done => { if (v.readyState >= 1) done(v.duration);"
        " v.onloadedmetadata = () => done(v.duration); v.onerror = () => done(-1); })",
    )
    assert duration > 0
    assert page.locator("#gates tbody tr").count() >= 6
    page.click("#label-failure")
    from playwright.sync_api import expect  # locator assertions: no eval, which the page's CSP forbids

    expect(rows.first.locator("td").last).to_have_text("failure", timeout=30_000)
    label = read_label(EpisodeStore(root).episode_dir(newest.id))
    assert label is not None
    assert (label.outcome, label.by) == ("failure", "otto")
    page.screenshot(path=str(tmp_path / "episodes.png"), full_page=True)
    assert errors == []
