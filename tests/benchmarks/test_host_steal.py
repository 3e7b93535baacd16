"""benchmarks/host_steal.py: the steal over a window, and the one warning line above 5 %."""

from __future__ import annotations

import time
from collections.abc import Callable
from types import ModuleType
from typing import Any

import pytest


@pytest.fixture
def host_steal(load_benchmark: Callable[[str], ModuleType]) -> Any:
    return load_benchmark("host_steal")


def test_a_window_reads_a_fraction_of_this_machines_cpu_time(host_steal: Any) -> None:
    with host_steal.StealMeter() as meter:
        time.sleep(0.2)
    # Linux reports steal (0 on bare metal): a fraction of the window, never negative or above all.
    assert meter.fraction is not None
    assert 0.0 <= meter.fraction <= 1.0
    assert host_steal.steal_text(meter.fraction).endswith("%")


def test_a_meter_never_started_reads_none(host_steal: Any) -> None:
    meter = host_steal.StealMeter()
    assert meter.stop() is None
    assert meter.fraction is None
    assert host_steal.steal_text(None) == "-"


def test_the_warning_names_the_worst_window_above_the_threshold_only(host_steal: Any) -> None:
    assert host_steal.steal_warning([]) is None
    assert host_steal.steal_warning([None, None]) is None
    assert host_steal.steal_warning([0.0, host_steal.STEAL_WARN]) is None
    warning = host_steal.steal_warning([0.01, None, 0.42, 0.2])
    assert warning is not None
    assert "42%" in warning
    assert "\n" not in warning
