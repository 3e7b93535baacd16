"""schemathesis against the control center's OpenAPI document: every documented operation, logged in
as an admin (session cookie and CSRF header on every call), answers without a server error and as
its schema says (status codes, content types, bodies).

The app is built the way ``telerig serve --rig demo`` builds it: accounts, the episode browser and
its jobs on a data root, the rig's gateway (the rig is not running: its login file is missing, so
live routes answer 503 as documented) and the rig's device registry.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Iterator
from typing import Any

import pytest
import schemathesis
from argon2 import PasswordHasher
from hypothesis import HealthCheck, Phase, given, settings
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    response_headers_conformance,
    response_schema_conformance,
    status_code_conformance,
)
from schemathesis.specs.openapi.schemas import OpenApiSchema

from telerig.config import load_rig
from telerig.server.accounts import AccountStore
from telerig.server.app import create_app
from telerig.server.auth import COOKIE, CSRF_HEADER, LoginLimiter
from telerig.server.devices import DeviceRegistry

PASSWORD = "correct horse battery"
FAST = PasswordHasher(time_cost=1, memory_cost=64, parallelism=1)
#: Examples per operation: ~30 operations x this stay well under 45 s on a loaded 2-core host.
EXAMPLES = 10


class _Served:
    def __init__(self, accounts: AccountStore, schema: OpenApiSchema) -> None:
        self.accounts = accounts
        self.schema = schema

    def credentials(self) -> tuple[dict[str, str], dict[str, str]]:
        """A fresh admin session for one call (a generated ``POST /api/logout`` may end the last)."""
        session = self.accounts.login("root", PASSWORD)
        return {CSRF_HEADER: session.csrf}, {COOKIE: session.token}


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[_Served]:
    from telerig.cli.serve import _gateway

    root = tmp_path_factory.mktemp("openapi") / "data"
    root.mkdir()
    accounts = AccountStore.open(root, hasher=FAST)
    accounts.add_user("root", "admin", PASSWORD)
    accounts.add_user("vic", "viewer", PASSWORD)
    rig = load_rig("demo")
    args = argparse.Namespace(
        rig="demo",
        data_root=root,
        broker=None,
        credentials=root / "no-such-login.json",
        ca_file=None,
        cert_file=None,
        key_file=None,
    )
    gateway = _gateway(args)
    devices = DeviceRegistry.open(root, [rig], broker_folders={rig.name: root / "broker"})
    app = create_app(accounts, limiter=LoginLimiter(failures=10_000), gateway=gateway, data_root=root)
    app.state.devices = devices
    try:
        yield _Served(accounts, schemathesis.openapi.from_asgi("/openapi.json", app))
    finally:
        gateway.close()
        devices.close()
        accounts.close()


def no_server_error_but_a_documented_503(ctx: Any, response: Any, case: Any) -> None:
    """No 5xx, except a 503 the operation documents (the rig is not running: live routes say so)."""
    code = response.status_code
    documented = "503" in case.operation.definition.raw.get("responses", {})
    if code >= 500 and not (code == 503 and documented):
        raise AssertionError(f"server error {code}: {response.text[:500]}")


def _operations(schema: OpenApiSchema) -> list[Any]:
    """Every documented operation (an operation the loader cannot read fails the test)."""
    return [r.ok() for r in schema.get_all_operations()]  # type: ignore[union-attr]


#: What every answer must satisfy. Not ``positive_data_acceptance``: a schema-valid request may still
#: be refused for what the schema cannot say (a robot the rig does not have, min above max quality),
#: with a documented 4xx that ``status_code_conformance`` and ``response_schema_conformance`` check.
CHECKS = [
    no_server_error_but_a_documented_503,
    status_code_conformance,
    content_type_conformance,
    response_headers_conformance,
    response_schema_conformance,
]


def test_the_document_lists_every_api_route(served: _Served) -> None:
    documented = {op.path for op in _operations(served.schema)}
    app = served.schema.app
    routes = {getattr(r, "path", "") for r in app.routes}
    api = {p for p in routes if p.startswith("/api/") and p != "/api/live"}  # a WebSocket: no OpenAPI
    assert api - documented == set(), "API routes missing from the OpenAPI document"
    assert len(documented) >= 20


def test_every_operation_answers_as_documented(served: _Served) -> None:
    # Each operation gets its own Hypothesis run (schemathesis' lazy pytest loader does not work
    # with this pytest); every failure is collected, so one run names them all.
    failures: list[str] = []
    operations = _operations(served.schema)
    for operation in operations:

        @given(case=operation.as_strategy())
        @settings(
            max_examples=EXAMPLES,
            deadline=None,
            suppress_health_check=list(HealthCheck),
            derandomize=True,
            phases=[Phase.explicit, Phase.generate],  # no shrinking: the curl line shows the case
            database=None,
        )
        def check(case: Any) -> None:
            headers, cookies = served.credentials()
            case.call_and_validate(
                headers=headers,
                cookies=cookies,
                checks=CHECKS,
            )

        t0 = time.monotonic()
        try:
            check()
        except (Exception, BaseExceptionGroup) as exc:  # every operation's failure, reported together
            notes = "\n".join(getattr(exc, "__notes__", []))
            failures.append(f"{operation.method.upper()} {operation.path}: {exc!r}\n{notes}")
        print(f"{operation.method.upper():6} {operation.path}: {time.monotonic() - t0:.2f} s")
    assert not failures, "\n\n".join(failures)
    assert len(operations) >= 20
