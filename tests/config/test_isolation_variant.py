"""RigConfig.with_isolation: the same rig with its robots in the station's process or their own."""

from __future__ import annotations

import pydantic
import pytest

from telerig.config import load_rig


def test_the_demo_rig_runs_its_robot_in_a_process_of_its_own() -> None:
    demo = load_rig("demo")
    assert (demo.runtime.isolation, demo.runtime.realtime_priority) == ("processes", 10)


def test_only_the_isolation_changes() -> None:
    demo = load_rig("demo")
    one = demo.with_isolation("threads")
    assert (one.runtime.isolation, one.runtime.realtime_priority) == ("threads", None)
    assert one.runtime.priorities == demo.runtime.priorities
    assert one.model_dump(exclude={"runtime"}) == demo.model_dump(exclude={"runtime"})
    back = one.with_isolation("processes", 20)
    assert (back.runtime.isolation, back.runtime.realtime_priority) == ("processes", 20)
    assert demo.runtime.realtime_priority == 10  # the rig it was made from is left as it was


@pytest.mark.parametrize("priority", [0, 100, -1])
def test_a_priority_outside_sched_rr_is_refused(priority: int) -> None:
    with pytest.raises(pydantic.ValidationError, match="realtime_priority"):
        load_rig("demo").with_isolation("processes", priority)


def test_a_priority_without_robot_processes_is_refused() -> None:
    with pytest.raises(pydantic.ValidationError, match="set isolation: processes"):
        load_rig("demo").with_isolation("threads", 10)
