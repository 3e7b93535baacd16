"""Control-center accounts: Argon2 passwords, sessions, roles, the last admin, the audit log."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import pytest
from argon2 import PasswordHasher

from telerig.server import accounts as accounts_module
from telerig.server.accounts import AccountError, AccountStore

PASSWORD = "correct horse battery"
# Cheap Argon2 parameters: the tests check behaviour, not the cost (the server uses the defaults).
FAST = PasswordHasher(time_cost=1, memory_cost=64, parallelism=1)


@pytest.fixture
def store(tmp_path: Path) -> AccountStore:
    s = AccountStore.open(tmp_path, hasher=FAST)
    s.add_user("ada", "admin", PASSWORD)
    return s


def test_passwords_are_stored_as_argon2id_hashes_never_in_clear(store: AccountStore, tmp_path: Path) -> None:
    with sqlite3.connect(tmp_path / "control.sqlite") as db:
        (digest,) = db.execute("select password_hash from users where name = 'ada'").fetchone()
    assert digest.startswith("$argon2id$")
    assert PASSWORD not in (tmp_path / "control.sqlite").read_bytes().decode("latin-1")


def test_login_opens_a_session_found_by_its_token(store: AccountStore) -> None:
    session = store.login("ada", PASSWORD)
    found = store.session(session.token)
    assert found is not None
    assert found.user.name == "ada"
    assert found.csrf == session.csrf
    assert len(session.token) >= 40


def test_the_database_holds_only_the_token_hash(store: AccountStore, tmp_path: Path) -> None:
    session = store.login("ada", PASSWORD)
    assert session.token.encode() not in (tmp_path / "control.sqlite").read_bytes()


@pytest.mark.parametrize(
    ("user", "password"), [("ada", "wrong password!"), ("nobody", PASSWORD), ("ADA", PASSWORD)]
)
def test_a_wrong_login_says_the_same_for_unknown_users_and_wrong_passwords(
    store: AccountStore, user: str, password: str
) -> None:
    with pytest.raises(AccountError, match=r"^wrong user name or password$"):
        store.login(user, password)


def test_a_disabled_user_cannot_log_in_and_loses_its_sessions(store: AccountStore) -> None:
    store.add_user("bob", "operator", PASSWORD)
    session = store.login("bob", PASSWORD)
    store.disable("bob")
    assert store.session(session.token) is None
    with pytest.raises(AccountError):
        store.login("bob", PASSWORD)


def test_a_new_password_ends_every_session(store: AccountStore) -> None:
    session = store.login("ada", PASSWORD)
    store.set_password("ada", "another long password")
    assert store.session(session.token) is None
    assert store.login("ada", "another long password").user.name == "ada"


def test_sessions_expire_when_idle(store: AccountStore, monkeypatch: pytest.MonkeyPatch) -> None:
    session = store.login("ada", PASSWORD)
    monkeypatch.setattr(accounts_module, "SESSION_IDLE_S", -1)
    assert store.session(session.token) is None


@pytest.mark.parametrize("token", ["", "x", "A" * 10_000, "\x00\xff"])
def test_garbage_tokens_find_no_session(store: AccountStore, token: str) -> None:
    assert store.session(token) is None


@pytest.mark.parametrize(
    ("name", "role", "password", "error"),
    [
        ("Bob", "viewer", PASSWORD, "not allowed"),
        ("../x", "viewer", PASSWORD, "not allowed"),
        ("b" * 40, "viewer", PASSWORD, "not allowed"),
        ("bob", "root", PASSWORD, "does not exist"),
        ("bob", "viewer", "short", "at least 12"),
        ("bob", "viewer", "p" * 2000, "at most"),
        ("ada", "viewer", PASSWORD, "exists"),
    ],
)
def test_bad_users_are_refused_in_one_line(
    store: AccountStore, name: str, role: str, password: str, error: str
) -> None:
    with pytest.raises(AccountError, match=error) as info:
        store.add_user(name, role, password)
    assert "\n" not in str(info.value)


def test_the_last_admin_cannot_be_demoted_or_disabled(store: AccountStore) -> None:
    with pytest.raises(AccountError, match="last admin"):
        store.set_role("ada", "viewer")
    with pytest.raises(AccountError, match="last admin"):
        store.disable("ada")
    store.add_user("eve", "admin", PASSWORD)
    store.set_role("ada", "operator")
    assert store.user("ada").role == "operator"


def test_roles_are_ordered(store: AccountStore) -> None:
    store.add_user("vic", "viewer", PASSWORD)
    viewer, admin = store.user("vic"), store.user("ada")
    assert viewer.may("viewer")
    assert not viewer.may("operator")
    assert admin.may("operator")


def test_has_admin_is_false_on_a_fresh_database(tmp_path: Path) -> None:
    assert not AccountStore.open(tmp_path / "other", hasher=FAST).has_admin()


def test_the_audit_log_keeps_newest_first_and_cuts_long_text(store: AccountStore) -> None:
    store.audit("login", user="ada", client="127.0.0.1")
    store.audit("estop", user="ada", target="x" * 5000)
    log = store.audit_log()
    assert [e.action for e in log] == ["estop", "login"]
    assert len(log[0].target) == 500
    assert store.audit_log(before_seq=log[0].seq)[0].action == "login"
