"""benchmarks/rt_blackout.py: a probe above every real-time thread notes the moments it was held up."""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Callable
from types import ModuleType
from typing import Any

import pytest


@pytest.fixture
def rt(load_benchmark: Callable[[str], ModuleType]) -> Any:
    return load_benchmark("rt_blackout")


def test_each_cpus_probe_reports_a_stall_of_its_own_process_and_nothing_else(rt: Any) -> None:
    if os.geteuid() != 0:
        pytest.skip("SCHED_FIFO needs root or CAP_SYS_NICE")
    with rt.RtBlackoutProbe(period_ms=5.0, threshold_ms=10.0) as probe:
        assert sorted(probe.pids) == sorted(os.sched_getaffinity(0))
        time.sleep(0.3)
        # Held up the way the kernel holds a CPU's real-time threads: not scheduled for 80 ms.
        cpu, pid = max(probe.pids.items())
        stopped = time.time_ns()
        os.kill(pid, signal.SIGSTOP)
        time.sleep(0.08)
        os.kill(pid, signal.SIGCONT)
        time.sleep(0.3)
    assert not probe.running
    [blackout] = probe.blackouts
    assert blackout.cpu == cpu
    assert 60 <= blackout.ms <= 500  # 80 ms stopped, less the part of a period it was asleep anyway
    assert abs(blackout.start_ns - stopped) < 30e6
    assert probe.overlapping(stopped, stopped + 10_000_000) == [blackout]
    assert probe.overlapping(stopped - 200_000_000, stopped - 100_000_000) == []
    text = rt.blackout_text(probe, stopped - 10**9, stopped + 10**9)
    assert text.startswith(f"real-time blackouts: 1 (CPU {cpu}), longest ")


def test_a_probe_with_impossible_settings_is_refused(rt: Any) -> None:
    with pytest.raises(ValueError, match=r"priority must be 1\.\.99"):
        rt.RtBlackoutProbe(priority=0)


def test_a_probe_that_died_makes_the_report_say_not_measured(rt: Any) -> None:
    if os.geteuid() != 0:
        pytest.skip("SCHED_FIFO needs root or CAP_SYS_NICE")
    with rt.RtBlackoutProbe() as probe:
        cpu, pid = min(probe.pids.items())
        os.kill(pid, signal.SIGKILL)  # no result file: its CPU was not watched to the end
        time.sleep(0.1)
    assert probe.not_measured == f"the probe on CPU {cpu} ended without its result (exit -9)"
    now = time.time_ns()
    assert rt.blackout_text(probe, now - 10**9, now).startswith("real-time blackouts: not measured (")
