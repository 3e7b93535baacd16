"""Shared fixtures of the processing tests: the local OpenAI-compatible server of chat_server.py.

The suite imports test files with ``--import-mode=importlib`` (no ``sys.path`` changes), so this
conftest loads ``chat_server.py`` by path once and registers it as ``chat_server`` for the test
modules to import.
"""

from __future__ import annotations

import importlib.util
import sys
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

import pytest


def _load(name: str) -> ModuleType:
    spec = importlib.util.spec_from_file_location(name, Path(__file__).with_name(f"{name}.py"))
    assert spec is not None
    assert spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


chat_server = sys.modules.get("chat_server") or _load("chat_server")


@pytest.fixture
def server(request: pytest.FixtureRequest) -> Iterator[object]:
    """A running ``chat_server.ChatServer`` that accepts the test module's ``KEY``."""
    srv = chat_server.ChatServer(api_key=request.module.KEY)
    with srv.running():
        yield srv
