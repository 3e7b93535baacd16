"""benchmarks/gc_pauses.py: the collector's pauses are noted while the block runs, and only then."""

from __future__ import annotations

import gc
import time
from collections.abc import Callable
from types import ModuleType
from typing import Any

import pytest


@pytest.fixture
def gc_pauses(load_benchmark: Callable[[str], ModuleType]) -> Any:
    return load_benchmark("gc_pauses")


class _Cycle:
    def __init__(self) -> None:
        self.me = self


def test_a_full_collection_in_the_block_is_noted_with_its_generation_and_time(gc_pauses: Any) -> None:
    before = time.time_ns()
    with gc_pauses.GcPauses(threshold_ms=0.0) as seen:
        junk = [_Cycle() for _ in range(20_000)]
        del junk
        gc.collect()
    after = time.time_ns()
    full = [p for p in seen.pauses if p.generation == 2]
    assert full, seen.pauses
    assert all(before <= p.start_ns <= after and p.ms >= 0 for p in seen.pauses)
    assert {p.thread for p in seen.pauses} == {"MainThread"}  # the thread that set them off
    assert seen.counts[2] >= 1
    assert seen.overlapping(before, after) == seen.pauses
    assert seen.overlapping(after + 10**9, after + 2 * 10**9) == []
    # The hook is gone after the block: later collections are not noted.
    count = len(seen.pauses)
    gc.collect()
    assert len(seen.pauses) == count
    assert seen._callback not in gc.callbacks


def test_collections_under_the_threshold_are_counted_not_listed(gc_pauses: Any) -> None:
    with gc_pauses.GcPauses(threshold_ms=10_000.0) as seen:
        gc.collect()
    assert seen.pauses == []
    assert seen.counts[2] >= 1


def test_a_negative_threshold_is_refused(gc_pauses: Any) -> None:
    with pytest.raises(ValueError, match="threshold_ms must be >= 0"):
        gc_pauses.GcPauses(threshold_ms=-1.0)
