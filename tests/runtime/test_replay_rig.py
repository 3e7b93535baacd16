"""RigRuntime.replay_devices: the next episode replays a recorded episode's device stream, whether
the device runs in the station's process or in its robot's (the demo's third episode)."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import pytest

from telerig.bus.topics import Topic
from telerig.config import load_rig
from telerig.ir.mcap_log import read_log
from telerig.runtime.rig import RigRuntime

pytestmark = [pytest.mark.sim, pytest.mark.broker, pytest.mark.slow]


@pytest.mark.parametrize("isolation", ["threads", "processes"])
def test_the_next_episode_replays_the_recorded_controller(
    tmp_path: Path, isolation: Literal["threads", "processes"]
) -> None:
    rig = load_rig("demo").with_isolation(isolation).model_copy(update={"cameras": []})
    topic = str(Topic(rig.name, "vr0", "right_controller"))
    with RigRuntime(rig, data_root=tmp_path) as runtime:
        first = runtime.run_episode(2.0)
        assert runtime.replay_devices(first) == ["vr0"]
        second = runtime.run_episode(2.0)
    recorded = [e.sample.stamp for e in read_log(first.path / "episode.mcap", topics=[topic])]
    replayed = [e.sample.stamp for e in read_log(second.path / "episode.mcap", topics=[topic])]
    assert len(replayed) > 100
    # A replayed sample keeps its recorded sequence number and device clock (the live script would
    # have stamped new device times); only the capture time is new.
    assert {(s.seq, s.device_ns) for s in replayed} <= {(s.seq, s.device_ns) for s in recorded}
    assert min(s.capture_ns for s in replayed) > max(s.capture_ns for s in recorded)
