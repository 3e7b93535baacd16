"""benchmarks/gc_pauses.py: the collector's pauses are noted while the block runs, and only then."""

from __future__ import annotations

import gc
import importlib.util
import sys
import time
from pathlib import Path
from typing import Any

import pytest

SCRIPT = Path(__file__).resolve().parents[2] / "benchmarks" / "gc_pauses.py"


def _gc_pauses() -> Any:
    spec = importlib.util.spec_from_file_location("gc_pauses", SCRIPT)
    assert spec is not None
    assert spec.loader is not None
    module = sys.modules[spec.name] = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.GcPauses


class _Cycle:
    def __init__(self) -> None:
        self.me = self


def test_a_full_collection_in_the_block_is_noted_with_its_generation_and_time() -> None:
    before = time.time_ns()
    with _gc_pauses()(threshold_ms=0.0) as seen:
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


def test_collections_under_the_threshold_are_counted_not_listed() -> None:
    with _gc_pauses()(threshold_ms=10_000.0) as seen:
        gc.collect()
    assert seen.pauses == []
    assert seen.counts[2] >= 1


def test_a_negative_threshold_is_refused() -> None:
    with pytest.raises(ValueError, match="threshold_ms must be >= 0"):
        _gc_pauses()(threshold_ms=-1.0)
