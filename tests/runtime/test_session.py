"""Session coordinator: state machine, start broadcast, bus commands, and station agents."""

from __future__ import annotations

import json
import threading

import pytest
from pydantic import ValidationError

from telerig.bus.base import Inbox
from telerig.bus.memory import InMemoryBus
from telerig.runtime.session import (
    TRANSITIONS,
    Coordinator,
    EpisodeCommand,
    SessionError,
    SessionState,
    SessionStatus,
    StartReport,
    StationAgent,
    wait_until,
)

SESSION_TOPIC = "telerig/v1/demo/coordinator/session"
COMMAND_TOPIC = "telerig/v1/demo/coordinator/command"


class FakeClock:
    """A settable clock [ns]."""

    def __init__(self, t: int = 1_700_000_000_000_000_000) -> None:
        self.t = t

    def __call__(self) -> int:
        return self.t


def _statuses(inbox: Inbox) -> list[SessionStatus]:
    return [SessionStatus.model_validate_json(m.payload) for m in inbox.drain()]


def test_every_state_has_transitions_and_none_leads_to_itself() -> None:
    assert set(TRANSITIONS) == set(SessionState)
    assert all(state not in allowed for state, allowed in TRANSITIONS.items())


def test_an_invalid_transition_names_the_allowed_states() -> None:
    coordinator = Coordinator(InMemoryBus(), "demo").start()
    with pytest.raises(SessionError, match=r"cannot stop in state idle .*allowed next states are: armed$"):
        coordinator.stop()


def test_arming_publishes_a_retained_start_time_lead_after_now() -> None:
    bus, clock = InMemoryBus(), FakeClock()
    coordinator = Coordinator(bus, "demo", clock=clock, lead_s=5.0, task="pick", operator="op1").start()
    status = coordinator.arm()
    late = Inbox()
    bus.subscribe(SESSION_TOPIC, late)  # a late joiner gets the retained state
    (retained,) = _statuses(late)
    assert retained == status
    assert status.state is SessionState.ARMED
    assert status.start_at_ns == clock.t + 5_000_000_000
    assert (status.task, status.operator) == ("pick", "op1")
    assert status.episode_id is not None
    assert status.episode_id.startswith("ep-")
    coordinator.close()


def test_the_coordinator_records_at_the_start_time() -> None:
    recording = threading.Event()
    coordinator = Coordinator(
        InMemoryBus(),
        "demo",
        lead_s=0.05,
        on_status=[lambda s: recording.set() if s.state is SessionState.RECORDING else None],
    ).start()
    coordinator.arm()
    assert recording.wait(5.0)
    assert coordinator.state is SessionState.RECORDING
    assert coordinator.status.reason == "start_at"


def test_stop_before_the_start_cancels_recording() -> None:
    coordinator = Coordinator(InMemoryBus(), "demo", lead_s=0.05).start()
    coordinator.arm()
    coordinator.stop()
    threading.Event().wait(0.15)
    assert coordinator.state is SessionState.STOPPED


def test_restart_discards_the_episode_and_arms_a_new_one() -> None:
    bus = InMemoryBus()
    inbox = Inbox()
    bus.subscribe(SESSION_TOPIC, inbox)
    coordinator = Coordinator(bus, "demo", lead_s=10.0).start()
    first = coordinator.arm(task="pick")
    inbox.drain()
    second = coordinator.restart()
    stopped, armed = _statuses(inbox)
    assert (stopped.state, stopped.discarded, stopped.reason) == (SessionState.STOPPED, True, "restart")
    assert stopped.episode_id == first.episode_id
    assert armed == second
    assert second.episode_id != first.episode_id
    assert second.task == "pick"
    coordinator.close()


def test_mark_labels_the_last_episode_without_changing_state() -> None:
    coordinator = Coordinator(InMemoryBus(), "demo", lead_s=10.0).start()
    coordinator.arm(task="pick", operator="op1")
    coordinator.stop()
    status = coordinator.mark("failure", operator="op2")
    assert (status.state, status.outcome, status.operator, status.task) == (
        SessionState.STOPPED,
        "failure",
        "op2",
        "pick",
    )
    coordinator.close()


def test_mark_without_an_episode_is_refused() -> None:
    with pytest.raises(SessionError, match="no episode yet"):
        Coordinator(InMemoryBus(), "demo").start().mark("success")


def test_pause_resume_and_end_walk_the_state_machine() -> None:
    recording = threading.Event()
    coordinator = Coordinator(
        InMemoryBus(),
        "demo",
        lead_s=0.0,
        on_status=[lambda s: recording.set() if s.state is SessionState.RECORDING else None],
    ).start()
    coordinator.arm()
    assert recording.wait(5.0)
    assert coordinator.pause().state is SessionState.PAUSED
    assert coordinator.resume().state is SessionState.RECORDING
    assert coordinator.end().state is SessionState.IDLE


def test_commands_from_the_bus_are_validated_counted_and_applied() -> None:
    bus = InMemoryBus()
    coordinator = Coordinator(bus, "demo", lead_s=10.0).start()
    bus.publish(COMMAND_TOPIC, b"{not json")
    bus.publish(COMMAND_TOPIC, json.dumps({"command": "explode"}).encode())
    bus.publish(COMMAND_TOPIC, json.dumps({"command": "mark"}).encode())  # no outcome
    assert coordinator.stats.malformed == 3
    assert coordinator.status.seq == 0  # nothing applied
    bus.publish(COMMAND_TOPIC, json.dumps({"command": "stop", "source": "web"}).encode())
    assert coordinator.stats.refused == 1
    assert coordinator.last_refusal is not None
    start = {"command": "start", "task": "fold towel", "operator": "op3", "source": "cli"}
    bus.publish(COMMAND_TOPIC, json.dumps(start).encode())
    bus.publish(COMMAND_TOPIC, json.dumps({"command": "mark", "outcome": "success"}).encode())
    assert coordinator.stats.accepted == 2
    assert coordinator.state is SessionState.ARMED
    assert (coordinator.status.task, coordinator.status.outcome) == ("fold towel", "success")
    coordinator.close()


def test_outcome_is_only_allowed_with_mark() -> None:
    with pytest.raises(ValidationError, match="only allowed there"):
        EpisodeCommand(command="stop", outcome="success")


def test_wait_until_returns_false_when_cancelled() -> None:
    cancel = threading.Event()
    cancel.set()
    assert not wait_until(2**62, FakeClock(), cancel=cancel)


def test_a_station_starts_once_at_the_start_time_and_acks() -> None:
    bus = InMemoryBus()
    coordinator = Coordinator(bus, "demo", lead_s=0.2).start()
    started = threading.Event()
    reports: list[StartReport] = []

    def on_start(status: SessionStatus, report: StartReport) -> None:
        reports.append(report)
        started.set()

    acks = Inbox()
    bus.subscribe("telerig/v1/demo/s1/session", acks)
    with StationAgent(bus, "demo", "s1", on_start=on_start) as agent:
        assert agent.sync.wait_synced(2.0)
        status = coordinator.arm()
        assert started.wait(5.0)
        threading.Event().wait(0.1)  # a retained "recording" must not start it again
    (report,) = reports
    assert report.episode_id == status.episode_id
    assert report.start_at_ns == status.start_at_ns
    assert report.started_ns >= report.start_at_ns
    (ack,) = acks.drain()
    assert json.loads(ack.payload)["episode_id"] == status.episode_id
    coordinator.close()


def test_a_stop_before_the_start_cancels_the_station_start() -> None:
    bus = InMemoryBus()
    coordinator = Coordinator(bus, "demo", lead_s=0.3).start()
    reports: list[StartReport] = []
    seen_stop = threading.Event()
    with StationAgent(
        bus,
        "demo",
        "s1",
        on_start=lambda s, r: reports.append(r),
        on_status=lambda s: seen_stop.set() if s.state is SessionState.STOPPED else None,
    ):
        coordinator.arm()
        coordinator.discard()
        assert seen_stop.wait(5.0)
        threading.Event().wait(0.4)
    assert reports == []
    coordinator.close()
