"""Operator instructions counted from an episode's MCAP and kept beside it (instructions.json)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from telerig.errors import RecordingError
from telerig.ir.mcap_log import McapLog
from telerig.voice.instructions import (
    INSTRUCTIONS_FILE,
    eta,
    read_episode_instructions,
    write_episode_instructions,
)

R = "telerig/v1/demo"


def _episode(root: Path, messages: list[tuple[str, object]]) -> Path:
    episode = root / "ep-20261126-040000-abcd"
    episode.mkdir()
    log = McapLog(episode / "episode.mcap")
    for i, (topic, value) in enumerate(messages):
        payload = value if isinstance(value, bytes) else json.dumps(value).encode()
        log.write_json(topic, payload, log_time_ns=1_000 + i)
    log.close()
    return episode


def test_instructions_by_group_with_rejections_and_garbage(tmp_path: Path) -> None:
    episode = _episode(
        tmp_path,
        [
            (f"{R}/arm/wbc_mode_command", "whole_body"),
            (f"{R}/arm/wbc_mode_command", "ee"),
            (f"{R}/arm/fixture_command", "kind:plane"),
            (f"{R}/arm/motion_scale_command", "down"),
            (f"{R}/voice/view", {"view": "navigation", "source": "voice"}),
            (f"{R}/coordinator/command", {"command": "mark", "outcome": "success"}),
            (f"{R}/safety/command", {"command": "estop"}),
            (f"{R}/voice/feedback", {"status": "rejected", "heard": "stop"}),
            (f"{R}/voice/feedback", {"status": "done", "heard": "navigation"}),
            (f"{R}/coordinator/command", [1, 2, 3]),  # garbage: not a command
            (f"{R}/arm/fixture_command", "x" * 5000),  # oversized
            (f"{R}/arm/joint_state_json", {"q": [0.0]}),  # not an instruction stream
            ("not/a/telerig/topic", {"command": "stop"}),
            (f"{R}/coordinator/session", b"not json at all"),
        ],
    )
    record = write_episode_instructions(episode)
    assert record.by_group == {
        "constraint": 1,
        "episode": 1,
        "mode": 2,
        "perspective": 1,
        "safety": 1,
        "scale": 1,
    }
    assert (record.total, record.rejected, record.malformed) == (7, 1, 2)
    assert read_episode_instructions(episode) == record
    assert (episode / INSTRUCTIONS_FILE).is_file()


def test_bad_sidecar_and_missing_log_are_one_line_errors(tmp_path: Path) -> None:
    episode = _episode(tmp_path, [])
    assert write_episode_instructions(episode).total == 0
    (episode / INSTRUCTIONS_FILE).write_text('{"episode_id": "other", "total": 1, "by_group": {}}')
    with pytest.raises(RecordingError, match="belongs to episode 'other'"):
        read_episode_instructions(episode)
    (episode / INSTRUCTIONS_FILE).write_bytes(b"\xff" * (100 << 10))
    with pytest.raises(RecordingError, match="larger than"):
        read_episode_instructions(episode)
    (tmp_path / "empty").mkdir()
    with pytest.raises(RecordingError, match=r"has no episode\.mcap"):
        write_episode_instructions(tmp_path / "empty")


def test_eta_is_instructions_without_over_with() -> None:
    # Seed 002 Table 2: segregated planning 4 instructions, mobile-manipulation planning 1.
    assert eta(4, 1) == 4.0
    with pytest.raises(ValueError, match="with_feature > 0"):
        eta(4, 0)


def test_a_recorded_episode_carries_its_instructions(demo_recording_unchecked: Path) -> None:
    # `telerig run` of the demo rig (no operator command during its episodes): every committed
    # episode has instructions.json, counted from its own MCAP.
    episodes = sorted((demo_recording_unchecked / "episodes").iterdir())
    assert episodes
    for episode in episodes:
        record = read_episode_instructions(episode)
        assert record is not None, episode
        assert record.episode_id == episode.name
        assert record.total == 0
