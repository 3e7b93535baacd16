"""The control center's web API as a browser and a hostile client see it: login, CSRF, roles,
rate limits, every route behind login, and a real server over TLS."""

from __future__ import annotations

import os
import re
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx2
import pytest
from argon2 import PasswordHasher
from fastapi.routing import APIRoute
from fastapi.testclient import TestClient

from telerig.cli.serve import URL_LINE, wait_for_url
from telerig.server.accounts import AccountStore
from telerig.server.app import create_app
from telerig.server.auth import COOKIE, CSRF_HEADER, LoginLimiter

PASSWORD = "correct horse battery"
FAST = PasswordHasher(time_cost=1, memory_cost=64, parallelism=1)


@pytest.fixture
def accounts(tmp_path: Path) -> AccountStore:
    store = AccountStore.open(tmp_path, hasher=FAST)
    store.add_user("ada", "admin", PASSWORD)
    store.add_user("otto", "operator", PASSWORD)
    store.add_user("vic", "viewer", PASSWORD)
    return store


@pytest.fixture
def client(accounts: AccountStore) -> Iterator[TestClient]:
    with TestClient(create_app(accounts, limiter=LoginLimiter(failures=3, window_s=60))) as c:
        yield c


def login(client: TestClient, user: str = "ada") -> str:
    reply = client.post("/api/login", json={"user": user, "password": PASSWORD})
    assert reply.status_code == 200, reply.text
    csrf: str = reply.json()["csrf"]
    return csrf


def test_login_sets_an_httponly_strict_cookie_and_returns_the_csrf_token(client: TestClient) -> None:
    reply = client.post("/api/login", json={"user": "ada", "password": PASSWORD})
    assert reply.status_code == 200
    cookie = reply.headers["set-cookie"]
    assert cookie.startswith(f"{COOKIE}=")
    assert "HttpOnly" in cookie
    assert "SameSite=strict" in cookie
    assert reply.json()["role"] == "admin"
    assert client.get("/api/me").json()["user"] == "ada"


def _api_routes(client: TestClient) -> list[tuple[str, str]]:
    routes = []
    for route in client.app.routes:  # type: ignore[attr-defined]
        if isinstance(route, APIRoute) and route.path.startswith("/api") and route.path != "/api/login":
            routes += [(m, route.path.replace("{name}", "ada")) for m in sorted(route.methods)]
    return routes


def test_every_api_route_but_login_needs_a_session(client: TestClient) -> None:
    routes = _api_routes(client)
    assert len(routes) >= 6
    for method, path in routes:
        reply = client.request(method, path, json={})
        assert reply.status_code == 401, (method, path, reply.status_code)


def test_a_state_change_without_the_csrf_token_is_refused(client: TestClient) -> None:
    csrf = login(client)
    new = {"name": "bob", "role": "viewer", "password": PASSWORD}
    assert client.post("/api/users", json=new).status_code == 403
    assert client.post("/api/users", json=new, headers={CSRF_HEADER: "forged"}).status_code == 403
    assert client.post("/api/users", json=new, headers={CSRF_HEADER: csrf}).status_code == 201


@pytest.mark.parametrize("user", ["otto", "vic"])
def test_only_admins_manage_users_and_read_the_audit_log(client: TestClient, user: str) -> None:
    csrf = login(client, user)
    assert client.get("/api/users").status_code == 403
    assert client.get("/api/audit").status_code == 403
    new = {"name": "bob", "role": "admin", "password": PASSWORD}
    assert client.post("/api/users", json=new, headers={CSRF_HEADER: csrf}).status_code == 403


def test_failed_logins_are_rate_limited_per_user(client: TestClient) -> None:
    for _ in range(3):
        assert (
            client.post("/api/login", json={"user": "ada", "password": "wrong password!"}).status_code == 401
        )
    reply = client.post("/api/login", json={"user": "ada", "password": PASSWORD})
    assert reply.status_code == 429
    assert int(reply.headers["retry-after"]) > 0


def test_a_login_from_another_site_is_refused(client: TestClient) -> None:
    reply = client.post(
        "/api/login", json={"user": "ada", "password": PASSWORD}, headers={"Origin": "https://evil.example"}
    )
    assert reply.status_code == 403


@pytest.mark.parametrize(
    "body",
    [
        {"user": "ada"},
        {"user": "ada", "password": PASSWORD, "admin": True},
        {"user": "a" * 10_000, "password": PASSWORD},
        {"user": "ada", "password": "p" * 100_000},
        {"user": ["ada"], "password": PASSWORD},
    ],
)
def test_malformed_logins_are_422_not_500(client: TestClient, body: object) -> None:
    assert client.post("/api/login", json=body).status_code == 422


def test_logins_and_user_changes_are_audited_with_who_and_from_where(client: TestClient) -> None:
    client.post("/api/login", json={"user": "ada", "password": "wrong password!"})
    csrf = login(client)
    client.post(
        "/api/users",
        json={"name": "bob", "role": "viewer", "password": PASSWORD},
        headers={CSRF_HEADER: csrf},
    )
    client.patch("/api/users/bob", json={"role": "operator"}, headers={CSRF_HEADER: csrf})
    actions = [(e["action"], e["user"], e["target"]) for e in client.get("/api/audit").json()]
    assert actions[:4] == [
        ("user_changed", "ada", "bob"), ("user_added", "ada", "bob"),
        ("login", "ada", ""), ("login_failed", None, "ada"),
    ]  # fmt: skip
    assert all(e["client"] for e in client.get("/api/audit").json())


def test_passwords_never_reach_the_audit_log_or_the_logs(
    client: TestClient, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level("DEBUG")
    client.post("/api/login", json={"user": "ada", "password": "wrong password!"})
    csrf = login(client)
    client.post(
        "/api/users",
        json={"name": "bob", "role": "viewer", "password": "bobs secret 123"},
        headers={CSRF_HEADER: csrf},
    )
    text = client.get("/api/audit").text + caplog.text
    for secret in (PASSWORD, "wrong password!", "bobs secret 123"):
        assert secret not in text


def test_logout_ends_the_session(client: TestClient) -> None:
    csrf = login(client)
    assert client.post("/api/logout", headers={CSRF_HEADER: csrf}).status_code == 204
    assert client.get("/api/me").status_code == 401


def test_the_dashboard_redirects_to_login_until_logged_in(client: TestClient) -> None:
    reply = client.get("/", follow_redirects=False)
    assert reply.status_code == 303
    assert reply.headers["location"] == "/login"
    login(client)
    page = client.get("/")
    assert page.status_code == 200
    assert "default-src 'self'" in page.headers["content-security-policy"]


@pytest.mark.parametrize("name", ["../accounts.py", "..%2Faccounts.py", "index.html", "/etc/passwd"])
def test_static_files_are_a_fixed_list(client: TestClient, name: str) -> None:
    assert client.get(f"/static/{name}").status_code == 404


def test_the_openapi_spec_documents_every_api_route(client: TestClient) -> None:
    spec = client.get("/openapi.json").json()
    documented = {(m.upper(), p) for p, ops in spec["paths"].items() for m in ops}
    for method, path in _api_routes(client):
        assert (method, path.replace("/ada", "/{name}")) in documented


# --- a real server ------------------------------------------------------------------------------------


def test_telerig_serve_names_a_taken_port_or_a_bad_one_in_one_line(tmp_path: Path) -> None:
    add = [sys.executable, "-m", "telerig.cli.main", "users", "add", "ada", "--role", "admin"]
    subprocess.run(
        [*add, "--password-stdin", "--data-root", str(tmp_path)],
        input=PASSWORD + "\n",
        text=True,
        check=True,
        timeout=60,
    )
    serve = [sys.executable, "-m", "telerig.cli.main", "serve", "--data-root", str(tmp_path), "--port"]
    with socket.create_server(("127.0.0.1", 0)) as taken:
        port = taken.getsockname()[1]
        done = subprocess.run([*serve, str(port)], capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 2
    assert f"port {port} on 127.0.0.1 is in use" in done.stderr
    assert "--port" in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1
    for bad in ("70000", "-1"):
        done = subprocess.run([*serve, bad], capture_output=True, text=True, timeout=60, check=False)
        assert done.returncode == 2
        assert f"--port {bad} is not a TCP port" in done.stderr


def test_telerig_serve_refuses_to_start_without_an_admin(tmp_path: Path) -> None:
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "telerig.cli.main",
            "serve",
            "--data-root",
            str(tmp_path),
            "--port",
            "0",
        ],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 2
    assert "no admin account" in done.stderr
    assert "telerig users add" in done.stderr


def test_telerig_serve_serves_https_with_a_generated_certificate(tmp_path: Path) -> None:
    add = [
        sys.executable,
        "-m",
        "telerig.cli.main",
        "users",
        "add",
        "ada",
        "--role",
        "admin",
        "--password-stdin",
    ]
    subprocess.run(
        [*add, "--data-root", str(tmp_path)], input=PASSWORD + "\n", text=True, check=True, timeout=60
    )
    server = subprocess.Popen(
        [sys.executable, "-m", "telerig.cli.main", "serve", "--data-root", str(tmp_path), "--port", "0"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    try:
        assert server.stdout is not None
        line = server.stdout.readline()  # printed once the socket listens, with the port it took
        found = URL_LINE.fullmatch(line.rstrip("\n"))
        assert found, f"telerig serve printed {line!r}"
        assert re.fullmatch(r"https://127\.0\.0\.1:[1-9]\d*", found[1]), found[1]
        cert = tmp_path / ".tls-server"
        deadline = time.monotonic() + 30
        while True:
            try:
                with httpx2.Client(base_url=found[1], verify=False) as c:
                    reply = c.post("/api/login", json={"user": "ada", "password": PASSWORD})
                break
            except httpx2.TransportError:
                assert time.monotonic() < deadline, "telerig serve did not answer in 30 s"
                time.sleep(0.2)
        assert reply.status_code == 200
        assert "secure" in reply.headers["set-cookie"].lower()
        assert any(cert.iterdir())
    finally:
        server.terminate()
        server.communicate(timeout=20)


def test_wait_for_url_names_a_server_that_exited_with_its_output(tmp_path: Path) -> None:
    log = tmp_path / "serve.log"
    with log.open("wb") as out:
        quitter = subprocess.Popen([sys.executable, "-c", "print('no admin account in X')"], stdout=out)
        quitter.wait(timeout=60)
    with pytest.raises(RuntimeError, match=r"(?s)telerig serve exited:.*no admin account in X"):
        wait_for_url(log, quitter, timeout_s=5.0)
    log.write_text("telerig control center on https://[::1]:40123/\nWebXR page: https://[::1]:40123/xr\n")
    assert wait_for_url(log, quitter) == "https://[::1]:40123"  # the URL is read even after the exit
