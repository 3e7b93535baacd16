"""The devices page in headless Chromium on a real server: an admin registers a device, sees its
password once (the one the broker's password file accepts), closes the dialog (the password leaves
the page) and revokes it; a viewer sees the list but no register form."""

from __future__ import annotations

import base64
import hashlib
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from argon2 import PasswordHasher

from telerig.config import load_rig
from telerig.server.accounts import AccountStore
from telerig.server.app import create_app
from telerig.server.devices import DeviceRegistry

PASSWORD = "correct horse battery"

pytestmark = pytest.mark.browser


@pytest.fixture
def server(tmp_path: Path, live_server: Callable[..., str]) -> Iterator[tuple[str, Path]]:
    root = tmp_path / "data"
    accounts = AccountStore.open(root, hasher=PasswordHasher(time_cost=1, memory_cost=64, parallelism=1))
    accounts.add_user("ada", "admin", PASSWORD)
    accounts.add_user("vic", "viewer", PASSWORD)
    registry = DeviceRegistry.open(root, [load_rig("fleet")])
    app = create_app(accounts)
    app.state.devices = registry
    try:
        yield live_server(app), root / "broker" / "fleet"
    finally:
        registry.close()
        accounts.close()


def _accepts(folder: Path, user: str, password: str) -> bool:
    line = next(x for x in (folder / "passwd").read_text().splitlines() if x.startswith(f"{user}:"))
    _, _, iterations, salt, digest = line.split(":", 1)[1].split("$")
    mine = hashlib.pbkdf2_hmac("sha512", password.encode(), base64.b64decode(salt), int(iterations), dklen=64)
    return base64.b64encode(mine).decode() == digest


def test_an_admin_registers_sees_the_password_once_and_revokes(
    server: tuple[str, Path], page: Any, log_in: Callable[..., None], tmp_path: Path
) -> None:
    base, folder = server
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.on("dialog", lambda dialog: dialog.accept())  # the revoke confirmation
    log_in(page, base, "ada", PASSWORD, start="/devices")
    page.click("a[href='/devices']")
    page.wait_for_selector("#register-section:not([hidden])")
    page.select_option("#kind", "teleoperating")
    page.select_option("#device", "glove")
    page.click("#register button[type=submit]")
    page.wait_for_selector("#issued[open]")
    assert page.text_content("#issued-username") == "dev-glove"
    password = page.text_content("#issued-password")
    assert len(password) == 32
    assert _accepts(folder, "dev-glove", password)  # what the page shows is what the broker checks
    assert "external Mosquitto" in page.text_content("#issued-broker")  # the fleet rig embeds its broker
    page.screenshot(path=str(tmp_path / "devices-issued.png"), full_page=True)
    page.click("#issued-close")
    page.wait_for_selector("#issued:not([open])", state="attached")
    assert page.text_content("#issued-password") == ""
    row = page.locator("#devices tbody tr", has_text="dev-glove")
    assert row.locator("td").nth(6).text_content() == "active"
    assert password not in page.content()
    row.locator("button", has_text="Revoke").click()
    # (a locator, not wait_for_function: the page's CSP forbids evaluating strings)
    page.locator("#devices tbody td", has_text="revoked by ada").wait_for()
    assert "dev-glove:" not in (folder / "passwd").read_text()
    page.screenshot(path=str(tmp_path / "devices.png"), full_page=True)
    assert errors == []


def test_a_viewer_sees_the_list_without_the_register_form(
    server: tuple[str, Path], page: Any, log_in: Callable[..., None]
) -> None:
    base, _ = server
    log_in(page, base, "vic", PASSWORD, start="/devices")
    page.goto(f"{base}/devices")
    page.wait_for_selector("#who:not(:empty)")
    page.wait_for_timeout(300)
    assert page.is_hidden("#register-section")
    assert page.text_content("#error") == ""
