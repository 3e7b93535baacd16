"""The episode browser in headless Chromium on a real server: log in, open a recorded episode, see its
plot, play its video (seekable: the server answers ranges), label it, and see the label in the list."""

from __future__ import annotations

import shutil
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from argon2 import PasswordHasher

from telerig.server.accounts import AccountStore
from telerig.server.app import create_app
from telerig.store.episodes import EpisodeStore
from telerig.store.label_file import read_label

PASSWORD = "correct horse battery"

pytestmark = pytest.mark.browser


@pytest.fixture
def server(
    demo_recording: Path, tmp_path: Path, live_server: Callable[..., str]
) -> Iterator[tuple[str, Path]]:
    root = tmp_path / "data"
    shutil.copytree(demo_recording, root)
    accounts = AccountStore.open(root, hasher=PasswordHasher(time_cost=1, memory_cost=64, parallelism=1))
    accounts.add_user("otto", "operator", PASSWORD)
    try:
        yield live_server(create_app(accounts, data_root=root)), root
    finally:
        accounts.close()


def test_open_a_recorded_episode_see_its_plot_video_and_label_it(
    server: tuple[str, Path], page: Any, log_in: Callable[..., None], tmp_path: Path
) -> None:
    base, root = server
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    log_in(page, base, "otto", PASSWORD, start="/episodes")
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
