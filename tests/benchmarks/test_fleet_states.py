"""benchmarks/fleet.py: a robot's recorded state times, their skips and gaps."""

from __future__ import annotations

import subprocess
import sys
import time
from collections.abc import Callable
from types import ModuleType

import numpy as np


def test_skips_are_intervals_over_one_and_a_half_periods_and_gaps_over_two(
    load_benchmark: Callable[[str], ModuleType],
) -> None:
    state_skips = load_benchmark("fleet").state_skips
    ms = 1_000_000
    steady = np.arange(0, 100 * 10 * ms, 10 * ms, dtype=np.int64)
    assert state_skips(steady, 0.01) == (0, 0)
    # One state a wake off its turn, and a bit (a late tick, the physics waking at twice the rate):
    # 16 ms, a skip; then 4 ms.
    late = steady.copy()
    late[50] += 6 * ms
    assert state_skips(late, 0.01) == (1, 0)
    assert state_skips(steady + 5 * ms * (np.arange(steady.size) == 50), 0.01) == (0, 0)  # 15 ms: not over
    # One state never read (a tick next to a wake at the control rate): 20 ms and a bit, a gap.
    missing = np.delete(steady, 50)
    missing[50:] += ms // 10
    assert state_skips(missing, 0.01) == (1, 1)
    # Order does not matter; fewer than two states have no interval.
    assert state_skips(missing[::-1].copy(), 0.01) == (1, 1)
    assert state_skips(np.array([], dtype=np.int64), 0.01) == (0, 0)
    assert state_skips(np.array([5], dtype=np.int64), 0.01) == (0, 0)


# A stand-in robot process: its command line names the robot host, it names a thread as telerig
# does (the OS name, /proc/self/task/<tid>/comm) and spins in it until told to stop.
_CHILD = """
import sys, threading, time  # telerig.runtime.robot_host
def spin():
    with open(f"/proc/self/task/{threading.get_native_id()}/comm", "w") as comm:
        comm.write("control-test")
    end = time.monotonic() + 0.5
    while time.monotonic() < end:
        pass
thread = threading.Thread(target=spin)
thread.start()
print("ready", flush=True)
thread.join()
sys.stdin.read()
"""


def test_the_cpu_of_a_child_process_is_told_by_its_threads_os_names(
    load_benchmark: Callable[[str], ModuleType],
) -> None:
    fleet = load_benchmark("fleet")
    child = subprocess.Popen(
        [sys.executable, "-c", _CHILD], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    try:
        assert child.stdout is not None
        with fleet.CpuSampler(period_s=0.05) as cpu:
            cpu.mark_children()
            assert child.stdout.readline() == "ready\n"
            time.sleep(0.7)
        groups = cpu.groups()
    finally:
        child.communicate("", timeout=10)
    assert groups["robot host: control loop"] > 0.2  # 0.5 s of spinning in a window of about 0.7
    assert groups.get("robot host: main and other threads", 0.0) < 0.1
    assert any(name.startswith("station: ") for name in groups)  # this process, by Python names
