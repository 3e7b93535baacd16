"""Real-time process set-up: heap behaviour of glibc and the scheduling policy, in child processes."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import textwrap

import pytest

from telerig.runtime import realtime

pytestmark = pytest.mark.skipif(
    sys.platform != "linux" or realtime._glibc("mallopt") is None, reason="glibc on Linux only"
)

# Allocates 64 MiB in 64 KiB blocks (below the mmap threshold, so from the heap), frees them
# newest first so the free space gathers at the top of the heap, and reports the resident set
# size [MiB] after the frees and after release_heap().
_HEAP_PROBE = textwrap.dedent(
    """
    import ctypes, json, sys
    import psutil
    from telerig.runtime import realtime

    if sys.argv[1] == "keep":
        assert realtime.keep_heap()
    libc = ctypes.CDLL(None)
    libc.malloc.restype = ctypes.c_void_p
    libc.free.argtypes = [ctypes.c_void_p]
    rss = lambda: psutil.Process().memory_info().rss / 2**20
    base = rss()
    blocks = [libc.malloc(64 * 1024) for _ in range(1024)]
    for b in blocks:
        ctypes.memset(b, 1, 64 * 1024)
    full = rss()
    for b in reversed(blocks):
        libc.free(b)
    freed = rss()
    assert realtime.release_heap()
    print(json.dumps({"grown": full - base, "kept": freed - base, "released": rss() - base}))
    """
)


def _heap_probe(mode: str) -> dict[str, float]:
    out = subprocess.run(
        [sys.executable, "-c", _HEAP_PROBE, mode], capture_output=True, text=True, check=True, timeout=60
    )
    result: dict[str, float] = json.loads(out.stdout)
    return result


def test_keep_heap_keeps_freed_memory_until_release_heap_returns_it() -> None:
    default = _heap_probe("default")
    kept = _heap_probe("keep")
    assert default["grown"] > 60
    assert kept["grown"] > 60
    # By default glibc trims the top of the heap inside free(): the 64 MiB go back at once.
    assert default["kept"] < 8
    # With keep_heap nothing goes back inside free() ...
    assert kept["kept"] > 56
    # ... until release_heap() trims, outside the control loop.
    assert kept["released"] < 8


def test_set_realtime_priority_applies_round_robin_to_the_process() -> None:
    if os.geteuid() != 0:
        pytest.skip("needs root or CAP_SYS_NICE")
    code = (
        "import os; from telerig.runtime import realtime; "
        "ok = realtime.set_realtime_priority(7, 'probe'); "
        "print(ok, os.sched_getscheduler(0) == os.SCHED_RR, os.sched_getparam(0).sched_priority)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=60)
    assert out.stdout.split() == ["True", "True", "7"]


def test_set_realtime_priority_refused_warns_with_the_fix(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    def refuse(*_: object) -> None:
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    with caplog.at_level(logging.WARNING, logger="telerig.runtime.realtime"):
        assert not realtime.set_realtime_priority(10, "robot ur5e")
    [record] = caplog.records
    assert "robot ur5e runs at normal priority" in record.getMessage()
    assert "CAP_SYS_NICE" in record.getMessage()


def test_a_station_of_a_real_time_rig_runs_at_its_robots_priority_inside_the_block_only() -> None:
    if os.geteuid() != 0:
        pytest.skip("needs root or CAP_SYS_NICE")
    code = (
        "import os, threading; from telerig.runtime.process_settings import control_process\n"
        "seen = []\n"
        "with control_process(realtime_priority=7):\n"
        "    t = threading.Thread(target=lambda: seen.append(os.sched_getparam(0).sched_priority))\n"
        "    t.start(); t.join()\n"
        "print(seen[0], os.sched_getscheduler(0) == os.SCHED_OTHER)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=60)
    assert out.stdout.split() == ["7", "True"]  # a thread started inside inherits it; restored after


def test_a_control_process_freezes_what_start_up_made_until_it_ends() -> None:
    # In a child: freezing is process-wide state.
    code = (
        "import gc; from telerig.runtime.process_settings import control_process, settle_heap\n"
        "settle_heap(); outside = gc.get_freeze_count()\n"
        "with control_process():\n"
        "    settle_heap(); inside = gc.get_freeze_count()\n"
        "after = gc.get_freeze_count()\n"
        "with control_process(freeze_after_start=False):\n"
        "    settle_heap(); opted_out = gc.get_freeze_count()\n"
        "print(outside, inside > 1000, after, opted_out)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=60)
    assert out.stdout.split() == ["0", "True", "0", "0"]
