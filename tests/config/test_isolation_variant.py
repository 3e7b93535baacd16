"""RigConfig.with_isolation and with_runtime: the same rig with its robots in the station's process or
their own, and other runtime settings changed, validated."""

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


def test_with_runtime_changes_only_the_fields_named() -> None:
    demo = load_rig("demo")
    polled = demo.with_runtime(idle_poll=not demo.runtime.idle_poll, priorities={"control_realtime": 11})
    assert polled.runtime.idle_poll is not demo.runtime.idle_poll
    assert polled.runtime.priorities.control_realtime == 11
    # The other priorities are the rig's, field by field; isolation and the rest untouched.
    assert polled.runtime.priorities.model_dump(exclude={"control_realtime"}) == (
        demo.runtime.priorities.model_dump(exclude={"control_realtime"})
    )
    assert polled.runtime.model_dump(exclude={"idle_poll", "priorities"}) == (
        demo.runtime.model_dump(exclude={"idle_poll", "priorities"})
    )
    assert polled.model_dump(exclude={"runtime"}) == demo.model_dump(exclude={"runtime"})
    assert demo.runtime.priorities.control_realtime is None


@pytest.mark.parametrize(
    ("changes", "match"),
    [
        ({"idle_pol": True}, "idle_pol"),
        ({"priorities": {"control_realtime": 100}}, "control_realtime"),
        ({"priorities": {"work_policy": "idle"}}, "work_policy"),
        ({"idle_poll": "sometimes"}, "idle_poll"),
        ({"priorities": None}, "priorities"),
        ({"priorities": 5}, "priorities"),
    ],
)
def test_with_runtime_refuses_what_the_rig_file_would(changes: dict[str, object], match: str) -> None:
    with pytest.raises(pydantic.ValidationError, match=match):
        load_rig("demo").with_runtime(**changes)
