"""Tests never read or write the user's data root: each runs in its temp dir, and an absolute path into
a real ``telerig-data`` is refused and fails the test (issue 11, finding 10)."""

from __future__ import annotations

import os
import socket
from pathlib import Path

import pytest

from telerig.config import load_rig
from telerig.runtime.rig import RigRuntime

Guard = tuple[tuple[Path, ...], list[tuple[str, str]]]


def test_each_test_runs_in_its_tmp_path(tmp_path: Path) -> None:
    assert Path.cwd() == tmp_path


def test_the_default_data_root_resolves_inside_the_tests_tmp_path(tmp_path: Path) -> None:
    default = load_rig("demo").recording.data_root
    assert not default.is_absolute()
    assert default.resolve().is_relative_to(tmp_path)


def test_the_repos_data_root_is_refused_and_recorded(data_root_guard: Guard) -> None:
    roots, accesses = data_root_guard
    repo_root = roots[0]
    assert repo_root == Path(__file__).resolve().parents[1] / "telerig-data"
    with pytest.raises(PermissionError, match="tests must not touch the user's data root"):
        (repo_root / "index.sqlite").open("rb")
    with pytest.raises(PermissionError):
        os.listdir(repo_root)
    assert [event for event, _ in accesses] == ["open", "os.listdir"]
    accesses.clear()  # seen: this test only proves the guard


def test_a_runtime_without_data_root_writes_into_the_tmp_path(tmp_path: Path) -> None:
    # The binding test that opened ./telerig-data after `make demo` (fingerprint refusal) ran this way.
    with RigRuntime(load_rig("demo").model_copy(update={"cameras": []})) as runtime:
        assert runtime is not None
    assert (tmp_path / "telerig-data").is_dir()


def test_a_socket_finalized_unclosed_names_the_test_and_the_line_that_made_it() -> None:
    sock = socket.socket()
    with pytest.warns(ResourceWarning) as seen:
        sock.__del__()  # what the collector calls on a socket leaked in a reference cycle
    [warning] = seen
    text = str(warning.message)
    assert text.startswith("unclosed <socket.socket fd=")
    assert "made in tests/test_isolation.py::test_a_socket_finalized_unclosed_names_the_test" in text
    assert 'test_isolation.py", line' in text
    assert "_pytest" not in text  # pytest's own frames left out
    assert sock.fileno() == -1  # closed: its own finalizer stays silent


def test_a_closed_socket_is_finalized_silently() -> None:
    sock = socket.socket()
    sock.close()
    sock.__del__()  # no warning (the suite turns warnings into errors)
