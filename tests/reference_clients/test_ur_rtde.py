"""The fake UR controller serves ur_rtde (the most-used RTDE client, from PyPI) as a controller does."""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator

import pytest

from telerig.robots.ur.fake import FakeURController

RunClient = Callable[..., str]

HOME = (0.1, -1.5, 1.4, -1.3, -1.6, 0.2)


@pytest.fixture
def controller(loopback_host: str) -> Iterator[FakeURController]:
    # ur_rtde always dials port 30004, so the fake gets a loopback address of its own.
    with FakeURController(host=loopback_host, script_port=0, home=HOME) as fake:
        yield fake


def test_receive_interface_with_chosen_variables(controller: FakeURController, run_client: RunClient) -> None:
    # ur_rtde sends this recipe as "timestamp,actual_q,robot_mode,safety_mode," (trailing comma).
    variables = "timestamp,actual_q,robot_mode,safety_mode"
    out = json.loads(run_client("ur_rtde_receive.py", controller.host, variables))
    assert out["connected"]
    assert out["actual_q"] == pytest.approx(HOME)
    assert out["timestamps"][1] > out["timestamps"][0] >= 1000.0
    assert (out["robot_mode"], out["safety_mode"]) == (7, 1)
    assert controller.malformed_packets == 0


def test_receive_and_io_interfaces_with_library_defaults(
    controller: FakeURController, run_client: RunClient
) -> None:
    out = json.loads(run_client("ur_rtde_receive.py", controller.host))
    assert out["connected"]
    assert out["actual_q"] == pytest.approx(HOME)
    assert out["speed_slider"]
    assert out["int_register_18"]
    assert out["double_register_19"]
    assert controller.input_int_registers[18] == 42
    assert controller.input_double_registers[19] == 2.5
    assert controller.malformed_packets == 0
