"""Shared fixtures of the control center's browser tests: one headless Chromium for the session (the
Debian ``/usr/bin/chromium`` with the issue's flags, never a browser download), a fresh context per
test, a login helper and a real uvicorn server for an app on 127.0.0.1."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest

if TYPE_CHECKING:
    from playwright.sync_api import Browser, BrowserContext, Page

CHROMIUM = Path("/usr/bin/chromium")
#: The issue's flags for this machine (Playwright adds --headless; each launch gets a fresh
#: temporary --user-data-dir, and each test a fresh context: no cookies carry over).
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
#: A generous bound per browser step on a loaded 2-core test host [ms].
STEP_MS = 30_000


@pytest.fixture(scope="session")
def chromium() -> Iterator[Browser]:
    """One Chromium for every browser test of the session (a launch costs seconds here)."""
    if not CHROMIUM.exists():
        pytest.fail(
            f"Chromium is missing at {CHROMIUM}: run `make sysdeps-test` (apt-get install chromium)",
            pytrace=False,
        )
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=str(CHROMIUM), headless=True, args=CHROMIUM_ARGS)
        try:
            yield browser
        finally:
            browser.close()


@pytest.fixture
def browser_context(chromium: Browser) -> Iterator[BrowserContext]:
    """A fresh context (own cookies and storage) that trusts telerig serve's self-signed certificate."""
    context = chromium.new_context(ignore_https_errors=True, viewport={"width": 1280, "height": 900})
    context.set_default_timeout(STEP_MS)
    try:
        yield context
    finally:
        context.close()


@pytest.fixture
def page(browser_context: BrowserContext) -> Page:
    """A page of a fresh context."""
    return browser_context.new_page()


def _log_in(page: Page, base: str, user: str, password: str, *, start: str = "/login") -> None:
    page.goto(f"{base}{start}")
    page.wait_for_url(f"{base}/login")
    page.fill("input[name=user]", user)
    page.fill("input[name=password]", password)
    page.click("button[type=submit]")
    page.wait_for_url(f"{base}/")


@pytest.fixture
def log_in() -> Callable[..., None]:
    """``log_in(page, base, user, password, start="/login")``: log ``user`` in through the login
    page (from ``start``, which must redirect to it) and wait for the dashboard."""
    return _log_in


@pytest.fixture
def live_server() -> Iterator[Callable[..., str]]:
    """``serve(app, tls=None)``: run ``app`` with uvicorn on a free 127.0.0.1 port in a thread (HTTPS
    with ``tls=(cert, key)``), return its base URL; stopped at teardown."""
    import uvicorn
    import websockets.exceptions

    servers: list[tuple[uvicorn.Server, threading.Thread]] = []

    def serve(app: Any, tls: tuple[Path, Path] | None = None) -> str:
        config = uvicorn.Config(
            app,
            host="127.0.0.1",
            port=0,  # any free one, read back below
            log_level="warning",
            ws="websockets-sansio",  # the default imports websockets.legacy (deprecated)
            ssl_certfile=None if tls is None else str(tls[0]),
            ssl_keyfile=None if tls is None else str(tls[1]),
        )
        server = uvicorn.Server(config)

        def run() -> None:
            try:
                server.run()
            except websockets.exceptions.InvalidState:
                # uvicorn 0.38's websockets-sansio shutdown sends its 1012 close on every open
                # socket, also one the browser is already closing, which websockets 17 refuses
                # (seen once in a full suite). Only while stopping: nothing is left to serve then.
                if not server.should_exit:
                    raise

        thread = threading.Thread(target=run, daemon=True)
        thread.start()
        servers.append((server, thread))
        deadline = time.monotonic() + 30
        while not server.started:
            assert thread.is_alive(), "the server thread ended before it started"
            assert time.monotonic() < deadline, "the server did not start in 30 s"
            time.sleep(0.05)
        port = server.servers[0].sockets[0].getsockname()[1]
        return f"{'http' if tls is None else 'https'}://127.0.0.1:{port}"

    yield serve
    for server, thread in servers:
        server.should_exit = True
        thread.join(20)
