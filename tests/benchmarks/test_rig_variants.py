"""benchmarks/rig_variants.py: the demo rig with its robot in a process of its own under SCHED_RR."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pydantic
import pytest

from telerig.config import load_rig

SCRIPT = Path(__file__).resolve().parents[2] / "benchmarks" / "rig_variants.py"


def _module():  # type: ignore[no-untyped-def]
    spec = importlib.util.spec_from_file_location("rig_variants", SCRIPT)
    assert spec is not None
    assert spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_robot_moves_to_its_own_process_and_nothing_else_changes() -> None:
    demo = load_rig("demo")
    assert demo.runtime.isolation == "threads"
    variant = _module().with_robot_processes(demo, 10)
    assert (variant.runtime.isolation, variant.runtime.realtime_priority) == ("processes", 10)
    assert variant.runtime.priorities == demo.runtime.priorities
    assert variant.model_dump(exclude={"runtime"}) == demo.model_dump(exclude={"runtime"})
    assert demo.runtime.isolation == "threads"  # the rig it was made from is left as it was


@pytest.mark.parametrize("priority", [0, 100, -1])
def test_a_priority_outside_sched_rr_is_refused(priority: int) -> None:
    with pytest.raises(pydantic.ValidationError, match="realtime_priority"):
        _module().with_robot_processes(load_rig("demo"), priority)
