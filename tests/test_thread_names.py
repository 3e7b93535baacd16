"""Threads named at the OS level (telerig.thread_names): what top -H, perf and ftrace show."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from telerig import priority, thread_names
from telerig.thread_names import COMM_BYTES, os_name


def _comm(tid: int | None) -> str:
    return Path(f"/proc/self/task/{tid}/comm").read_text().rstrip("\n")


@contextmanager
def _parked(name: str, first: Callable[[], object] | None = None) -> Iterator[threading.Thread]:
    """A thread called ``name`` that runs ``first`` (if given) and waits until the block ends."""
    release, ready = threading.Event(), threading.Event()

    def body() -> None:
        if first is not None:
            first()
        ready.set()
        release.wait(10.0)

    thread = threading.Thread(target=body, name=name, daemon=True)
    thread.start()
    assert ready.wait(10.0)
    try:
        yield thread
    finally:
        release.set()
        thread.join(10.0)


@pytest.mark.parametrize(
    ("name", "expected"),
    [
        ("control-ur5e", "control-ur5e"),
        ("tiago0-physics", "tiago0-physics"),
        ("encoder-scene.mp4", "encoder-scene.m"),  # cut at 15 bytes, as the kernel would
        ("paho-mqtt-client-tiago_wbc-ctl-tiago0", "mqtt-ctl-tiago0"),
        ("paho-mqtt-client-fleet-recorder", "mqtt-recorder"),
        ("paho-mqtt-client-glove", "mqtt-glove"),  # a client id of one part stays whole
        ("paho-mqtt-client-", "mqtt-"),
        ("abcdefghijklmnü", "abcdefghijklmn"),  # cut on a character boundary: 14 bytes, not 15
        ("kamera-ß-überwachung", "kamera-ß-über"),
        ("\udcff-surrogate", "?-surrogate"),
        ("", ""),
    ],
)
def test_the_kernel_form_of_a_name_fits_its_15_bytes(name: str, expected: str) -> None:
    assert os_name(name) == expected
    assert len(os_name(name).encode()) <= COMM_BYTES


def test_a_thread_names_itself_and_enter_names_the_role_thread() -> None:
    with _parked("telerig-test-own", thread_names.name_current) as thread:
        assert _comm(thread.native_id) == "telerig-test-ow"
    # priority.enter names the calling thread even where scheduling is off.
    off = priority.Priorities(enabled=False)
    with _parked("control-test", lambda: priority.enter("control", off)) as thread:
        assert _comm(thread.native_id) == "control-test"


def test_name_all_names_every_thread_but_the_main_one(monkeypatch: pytest.MonkeyPatch) -> None:
    main_before = _comm(threading.main_thread().native_id)
    with _parked("telerig-a-physics") as a, _parked("paho-mqtt-client-rig-dev-sm0") as b:
        assert _comm(a.native_id) != "telerig-a-physi"  # Python 3.11 names threads for Python only
        assert thread_names.name_all() >= 2
        assert _comm(a.native_id) == "telerig-a-physi"
        assert _comm(b.native_id) == "mqtt-dev-sm0"
        # Called again, it writes only what changed: a thread renamed since.
        writes: list[str] = []
        write = thread_names._write
        monkeypatch.setattr(
            thread_names, "_write", lambda path, name: writes.append(name) or write(path, name)
        )
        thread_names.name_all()
        assert not {"telerig-a-physics", "paho-mqtt-client-rig-dev-sm0"} & set(writes)
        a.name = "telerig-a-renamed"
        thread_names.name_all()
        assert "telerig-a-renamed" in writes
        assert _comm(a.native_id) == "telerig-a-renam"
    assert _comm(threading.main_thread().native_id) == main_before  # the process keeps its name in ps
    assert thread_names.name_current() is False  # called on the main thread: left alone


def test_hostile_names_never_raise() -> None:
    for name in ("line\nbreak", "x" * 100_000, "\x00nul", "\udcff lone surrogate"):
        with _parked(name, thread_names.name_current) as thread:
            assert len(_comm(thread.native_id).encode(errors="surrogateescape")) <= COMM_BYTES
    # A thread that ended before its name was written: nothing to name, no error.
    gone = threading.Thread(target=lambda: None, name="gone")
    gone.start()
    gone.join()
    assert thread_names.name_all() >= 0
