"""Runs the reference client of a protocol (from .venv-peers) against one of telerig's fake peers."""

from __future__ import annotations

import random
import subprocess
from collections.abc import Callable
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PEERS_PYTHON = ROOT / ".venv-peers" / "bin" / "python"
CLIENTS = Path(__file__).resolve().parent / "clients"

#: Runs ``clients/<script>`` with arguments in the peers venv; returns its stdout (fails the test on error).
RunClient = Callable[..., str]


@pytest.fixture
def run_client() -> RunClient:
    if not PEERS_PYTHON.exists():
        pytest.fail(
            f"{PEERS_PYTHON} is missing: the reference clients live in their own venv; "
            "run `make .venv-peers/.installed` (make unit does it)"
        )

    def run(script: str, *args: object, timeout: float = 8.0) -> str:
        proc = subprocess.run(
            [str(PEERS_PYTHON), str(CLIENTS / script), *map(str, args)],
            capture_output=True,
            text=True,
            timeout=timeout,
            check=False,
        )
        if proc.returncode != 0:
            pytest.fail(f"{script} exited {proc.returncode}\nstdout:\n{proc.stdout}\nstderr:\n{proc.stderr}")
        return proc.stdout

    return run


@pytest.fixture
def loopback_host() -> str:
    """A random 127.x.y.z address, for a fake that must listen on the port a client hard-codes."""
    rng = random.Random()
    return f"127.{rng.randint(1, 254)}.{rng.randint(1, 254)}.{rng.randint(1, 254)}"
