"""Tests of the Modbus driver configs registered in ROBOTS."""

from __future__ import annotations

import pytest

from telerig.registry import ROBOTS
from telerig.robots.modbus import DHGripper, FakeInspireHand, InspireHand


def test_both_types_are_registered() -> None:
    assert {"inspire_hand", "dh_gripper"} <= set(ROBOTS.names())


def test_inspire_config_builds_a_driver_that_reaches_the_fake() -> None:
    with FakeInspireHand() as fake:
        config = ROBOTS.parse_config(
            {
                "type": "inspire_hand",
                "id": "left_hand",
                "host": "127.0.0.1",
                "port": fake.port,
                "joint_prefix": "left_",
            },
            "robots[0]",
        )
        driver = config.build()
        assert isinstance(driver, InspireHand)
        with driver:
            assert driver.read_state().names[0] == "left_little"
            assert driver.read_state().stamp.source_id == "left_hand"


def test_dh_config_builds_a_serial_driver_without_io() -> None:
    config = ROBOTS.parse_config({"type": "dh_gripper", "id": "g0", "device": "/dev/ttyUSB3"}, "robots[1]")
    driver = config.build()
    assert isinstance(driver, DHGripper)
    assert not driver.connected


def test_rtu_over_tcp_needs_a_host() -> None:
    with pytest.raises(ValueError, match="host: required when transport is 'rtu_over_tcp'"):
        ROBOTS.parse_config({"type": "dh_gripper", "id": "g0", "transport": "rtu_over_tcp"}, "robots[1]")


def test_out_of_range_force_names_the_field() -> None:
    with pytest.raises(ValueError, match=r"robots\[1\]\.force_percent"):
        ROBOTS.parse_config({"type": "dh_gripper", "id": "g0", "force_percent": 5}, "robots[1]")
