"""The fake G1 serves a plain Cyclone DDS client using Unitree's own IDL types and CRC (unitree_sdk2py)."""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable, Iterator

import pytest

from telerig.robots.unitree.fake import FakeG1

RunClient = Callable[..., str]


@pytest.fixture
def robot() -> Iterator[FakeG1]:
    # A domain of its own, so a concurrent run of the suite does not cross-talk.
    with FakeG1(domain_id=150 + os.getpid() % 60) as fake:
        yield fake


def test_unitree_sdk_types_read_states_and_drive_the_arm(robot: FakeG1, run_client: RunClient) -> None:
    out = json.loads(run_client("unitree_g1_arm_sdk.py", robot.domain_id, 1.2, timeout=15))
    assert out["states"] >= 3
    assert out["crc_ok"]  # Unitree's CRC of every state the fake published
    assert out["mode_machine"] == 5
    assert out["left_elbow"] == pytest.approx(0.3, abs=1e-6)
    assert robot.commands > 0
    assert robot.bad_crc == 1
    assert robot.weight == 1.0
    deadline = time.monotonic() + 3.0  # the arm keeps moving to the last target after the client left
    while abs(robot.positions(("left_elbow_joint",))[0] - 1.2) > 0.01 and time.monotonic() < deadline:
        time.sleep(0.02)
    assert robot.positions(("left_elbow_joint",))[0] == pytest.approx(1.2, abs=0.01)
