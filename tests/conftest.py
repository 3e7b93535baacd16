"""Shared fixtures: a real Mosquitto on 127.0.0.1 and connected MQTT clients; every test runs in its
own temp dir and may not touch the user's data root."""

from __future__ import annotations

import os

# Headless offscreen rendering with Mesa; must be set before MuJoCo is first imported.
os.environ.setdefault("MUJOCO_GL", "osmesa")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])

import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from telerig.bus.broker import MosquittoBroker
from telerig.bus.mqtt import MqttBus

# --- isolation from the user's files -----------------------------------------------------------------
# Default data roots are relative (``telerig-data`` in the rig schema, the CLI, calibration profiles)
# and MuJoCo writes MUJOCO_LOG.TXT into the working directory on a warning: every test (and every
# higher-scoped fixture) runs with its working directory in a temp dir. An audit hook records any
# access by absolute path to a ``telerig-data`` outside the temp dirs (the repo's, the user's home's)
# and fails the test that made it.

_REPO = Path(__file__).resolve().parents[1]
FORBIDDEN_DATA_ROOTS = tuple(
    dict.fromkeys(p / "telerig-data" for p in (_REPO, Path.cwd().resolve(), Path.home().resolve()))
)
_PATH_EVENTS = frozenset(
    {"open", "os.mkdir", "os.listdir", "os.scandir", "os.rename", "os.remove", "os.rmdir", "os.chdir",
     "shutil.rmtree", "shutil.copytree", "sqlite3.connect", "os.truncate", "os.utime"}
)  # fmt: skip
#: Forbidden accesses seen since the current test started: (event, path).
data_root_accesses: list[tuple[str, str]] = []


def _forbidden(path: object) -> str | None:
    if isinstance(path, int):
        return None
    try:
        text = os.fsdecode(path)  # type: ignore[arg-type]
    except TypeError:
        return None
    if "telerig-data" not in text or not os.path.isabs(text):
        return None  # relative paths resolve in the test's temp dir
    resolved = os.path.normpath(text)
    for root in FORBIDDEN_DATA_ROOTS:
        if resolved == str(root) or resolved.startswith(str(root) + os.sep):
            return resolved
    return None


def _audit(event: str, args: tuple[Any, ...]) -> None:
    if event not in _PATH_EVENTS or not args:
        return
    for arg in args[:2]:  # rename and copytree: source and destination
        hit = _forbidden(arg)
        if hit is not None:
            data_root_accesses.append((event, hit))
            raise PermissionError(f"tests must not touch the user's data root: {event} {hit}")


sys.addaudithook(_audit)


@pytest.fixture(scope="session", autouse=True)
def _session_cwd(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """Session- and module-scoped fixtures run in a temp dir too (they start before ``_test_cwd``)."""
    before = Path.cwd()
    os.chdir(tmp_path_factory.mktemp("cwd"))
    yield
    os.chdir(before)


@pytest.fixture
def data_root_guard() -> tuple[tuple[Path, ...], list[tuple[str, str]]]:
    """The forbidden data roots and the accesses recorded in this test (a test of the guard clears them)."""
    return FORBIDDEN_DATA_ROOTS, data_root_accesses


@pytest.fixture(autouse=True)
def _test_cwd(tmp_path: Path) -> Iterator[None]:
    """Run each test in its ``tmp_path``; fail it if it touched a forbidden data root."""
    before = Path.cwd()
    os.chdir(tmp_path)
    data_root_accesses.clear()
    yield
    os.chdir(before)
    if data_root_accesses:
        seen = ", ".join(f"{event} {path}" for event, path in data_root_accesses[:3])
        data_root_accesses.clear()
        pytest.fail(f"the test touched the user's data root ({seen}); use tmp_path", pytrace=False)


@pytest.fixture
def broker() -> Iterator[MosquittoBroker]:
    """A fresh Mosquitto per test on a free port (starting one takes ~30 ms)."""
    with MosquittoBroker() as running:
        yield running


@pytest.fixture
def make_bus(broker: MosquittoBroker) -> Iterator[Callable[..., MqttBus]]:
    """Factory of connected :class:`MqttBus` clients of ``broker``, closed at teardown."""
    buses: list[MqttBus] = []

    def make(client_id: str, **options: Any) -> MqttBus:
        bus = MqttBus(broker.url, client_id=client_id, **options).connect()
        buses.append(bus)
        return bus

    yield make
    for bus in buses:
        bus.close()
