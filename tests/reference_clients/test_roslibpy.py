"""The fake rosbridge serves roslibpy (the rosbridge client from PyPI) as rosbridge_server does."""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest
from websockets.sync.client import connect

from telerig.robots.rosbridge.fake import FakeRosbridge

RunClient = Callable[..., str]
NAMES = ("shoulder", "elbow")


@pytest.fixture
def fake() -> Iterator[FakeRosbridge]:
    with FakeRosbridge(NAMES, initial=(0.1, -0.1), max_velocity=3.0) as running:
        yield running


def test_roslibpy_reads_states_lists_topics_and_commands_the_robot(
    fake: FakeRosbridge, run_client: RunClient
) -> None:
    out = json.loads(run_client("roslibpy_robot.py", fake.host, fake.port, ",".join(NAMES), "0.3,-0.2"))
    assert out["state"]["name"] == list(NAMES)
    assert out["state"]["position"] == pytest.approx([0.1, -0.1], abs=0.05)
    assert set(out["state"]["header"]["stamp"]) == {"sec", "nanosec"}
    # rosapi's topic list (roslibpy's Ros.get_topics) and rosbridge's answer to a service nobody offers.
    assert fake.state_topic in out["topics"]
    assert fake.command_topic in out["topics"]
    assert out["unknown_service"] == ["Service /no_such_service does not exist"]
    assert fake.commands == 1
    np.testing.assert_allclose(fake.positions, [0.3, -0.2], atol=1e-9)
    assert fake.estopped
    assert fake.malformed == 0


def test_publish_without_advertise_uses_the_type_of_the_robots_topic(fake: FakeRosbridge) -> None:
    # rosbridge looks the type up in the ROS graph when a client publishes without advertising.
    with connect(fake.url) as ws:
        ws.send(
            json.dumps(
                {
                    "op": "publish",
                    "topic": fake.command_topic,
                    "msg": {
                        "joint_names": list(NAMES),
                        "points": [
                            {"positions": [0.2, 0.0], "time_from_start": {"sec": 0, "nanosec": 100_000_000}}
                        ],
                    },
                }
            )
        )
        ws.send(json.dumps({"op": "publish", "topic": "/nobody/listens", "msg": {"data": 1}}))
        reply = json.loads(ws.recv(timeout=2))
    assert reply["level"] == "error"
    assert "/nobody/listens" in reply["msg"]
    deadline = time.monotonic() + 2
    while fake.commands == 0 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert fake.commands == 1
