"""The runtime runs every episode through the session coordinator: armed with a global start time,
started on the station at that time, clock estimate stored, and stoppable by a command on the bus."""

from __future__ import annotations

import json
import sys
import threading
from pathlib import Path

import pytest

from telerig.bus.topics import Topic
from telerig.cli.main import main
from telerig.config import load_rig
from telerig.config.schema import SessionCommand
from telerig.runtime.process_settings import DEFAULT_SWITCH_INTERVAL_S
from telerig.runtime.rig import RigRuntime
from telerig.store.episodes import EpisodeStore

pytestmark = [pytest.mark.sim, pytest.mark.broker, pytest.mark.slow]


def test_episode_carries_the_session_and_station_clock(tmp_path: Path) -> None:
    rig = load_rig("demo").model_copy(update={"cameras": []})
    sys.setswitchinterval(0.004)
    try:
        with RigRuntime(rig, data_root=tmp_path) as runtime:
            # Process-wide settings are the entry points' (issue 12): the runtime leaves them alone.
            assert sys.getswitchinterval() == 0.004
            result = runtime.run_episode(1.0)
            assert runtime.coordinator is not None
            assert runtime.coordinator.state.value == "stopped"
    finally:
        sys.setswitchinterval(DEFAULT_SWITCH_INTERVAL_S)
    manifest = EpisodeStore(tmp_path).get(result.episode_id)
    clock = manifest.extra["clock"]
    assert isinstance(clock, dict)
    assert clock["station"] == "station0"
    assert isinstance(manifest.extra["session_id"], str)


def test_a_stop_command_on_the_bus_ends_the_episode_and_keeps_it(tmp_path: Path) -> None:
    rig = load_rig("demo").model_copy(update={"cameras": []})
    with RigRuntime(rig, data_root=tmp_path) as runtime:
        topic = str(Topic(rig.name, "coordinator", "command"))
        timer = threading.Timer(
            1.5, lambda: runtime.recorder.bus.publish(topic, json.dumps({"command": "stop"}).encode(), qos=1)
        )
        timer.start()
        result = runtime.run_episode(10.0)
        timer.join()
    assert result.command is SessionCommand.STOP_EPISODE  # the episode ends, the session goes on
    assert result.status == "complete"
    assert result.duration_s < 5.0


def test_mark_success_from_the_command_line_is_stored_in_the_manifest(tmp_path: Path) -> None:
    rig = load_rig("demo").model_copy(update={"cameras": []})
    with RigRuntime(rig, data_root=tmp_path) as runtime:
        url = runtime.broker_url or ""
        base = ["session", "--url", url, "--rig", rig.name]
        mark = threading.Timer(0.8, lambda: main([*base[:1], "mark", *base[1:], "--outcome", "success"]))
        stop = threading.Timer(1.6, lambda: main([*base[:1], "stop", *base[1:]]))
        mark.start()
        stop.start()
        result = runtime.run_episode(10.0)
        mark.join()
        stop.join()
    manifest = EpisodeStore(tmp_path).get(result.episode_id)
    assert manifest.extra["outcome"] == "success"
    assert result.command is SessionCommand.STOP_EPISODE


def test_session_stop_and_discard_end_only_the_running_episode_and_end_ends_the_session(
    tmp_path: Path,
) -> None:
    # Issue 11 finding 5: `telerig session stop` / `discard` ended the whole run.
    rig = load_rig("demo").model_copy(update={"cameras": []})
    results = []
    with RigRuntime(rig, data_root=tmp_path) as runtime:
        base = ["--url", runtime.broker_url or "", "--rig", rig.name]
        for command in ("stop", "discard", "end"):
            timer = threading.Timer(1.0, lambda c=command: main(["session", c, *base]))
            timer.start()
            results.append(runtime.run_episode(10.0))
            timer.join()
    stopped, discarded, ended = results
    assert (stopped.command, stopped.status) == (SessionCommand.STOP_EPISODE, "complete")
    assert (discarded.command, discarded.status) == (SessionCommand.DISCARD_EPISODE, "incomplete")
    assert (ended.command, ended.status) == (SessionCommand.END_SESSION, "complete")
    assert all(r.duration_s < 5.0 for r in results)


def test_the_run_goes_on_after_an_episode_stop_or_discard_and_ends_with_the_session() -> None:
    from telerig.cli.main import run_goes_on

    assert run_goes_on(SessionCommand.STOP_EPISODE)
    assert run_goes_on(SessionCommand.DISCARD_EPISODE)
    assert run_goes_on(None)
    assert not run_goes_on(SessionCommand.END_SESSION)
    assert not run_goes_on(SessionCommand.STOP_COLLECTION)
