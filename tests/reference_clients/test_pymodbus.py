"""The Modbus fakes serve a plain pymodbus client and the vendor manuals' own frames as the hardware does.

Addresses and frames here are written as the manuals print them (not read from telerig's register
maps), so a misreading shared by the driver and the fake shows up.
"""

from __future__ import annotations

import os
import select
import time
import tty
from collections.abc import Callable, Iterator

import pytest
from pymodbus.client import ModbusSerialClient, ModbusTcpClient

from telerig.robots.modbus import FakeDHGripper, FakeInspireHand


def _until(read: Callable[[], bool], timeout: float = 3.0) -> None:
    deadline = time.monotonic() + timeout
    while not read():
        if time.monotonic() > deadline:
            raise AssertionError("condition not met within the timeout")
        time.sleep(0.02)


@pytest.fixture
def hand() -> Iterator[FakeInspireHand]:
    with FakeInspireHand(full_stroke_s=0.2) as fake:
        yield fake


def test_inspire_hand_serves_pymodbus_like_the_rh56_manual(hand: FakeInspireHand) -> None:
    # RH56DFX manual: ANGLE_SET 1486, SPEED_SET 1522, ANGLE_ACT 1546, STATUS 1612 (two fingers a register).
    client = ModbusTcpClient(hand.host, port=hand.port, timeout=2)
    assert client.connect()
    try:
        assert client.read_holding_registers(1546, count=6, device_id=1).registers == [1000] * 6
        assert not client.write_registers(1522, [1000] * 6, device_id=1).isError()
        assert not client.write_registers(1486, [500, 500, 500, 500, 1000, 1000], device_id=1).isError()
        assert not client.write_register(1486, 0, device_id=1).isError()  # fc 6: little finger closes
        _until(
            lambda: (
                client.read_holding_registers(1546, count=6, device_id=1).registers[:4] == [0, 500, 500, 500]
            )
        )
        status = client.read_holding_registers(1612, count=3, device_id=1).registers
        assert [status[0] & 0xFF, status[0] >> 8] == [2, 2]  # little, ring: position reached
        assert client.read_holding_registers(1800, count=1, device_id=1).isError()  # outside the map
    finally:
        client.close()


@pytest.fixture
def dh() -> Iterator[FakeDHGripper]:
    with FakeDHGripper(full_stroke_s=0.2, init_s=0.05) as fake:
        yield fake


def test_dh_gripper_serves_pymodbus_rtu_like_the_manual(dh: FakeDHGripper) -> None:
    # DH manual: 0x0100 initialize, 0x0103 position (permille), 0x0200 init state, 0x0202 position feedback.
    client = ModbusSerialClient(dh.device, baudrate=115200, timeout=1)
    assert client.connect()
    try:
        assert not client.write_register(0x0100, 1, device_id=1).isError()
        _until(lambda: client.read_holding_registers(0x0200, count=1, device_id=1).registers == [1])
        assert not client.write_register(0x0103, 300, device_id=1).isError()
        _until(lambda: client.read_holding_registers(0x0202, count=1, device_id=1).registers == [300])
        assert client.read_holding_registers(0x0400, count=1, device_id=1).isError()  # not in the map
    finally:
        client.close()


def _transact(fd: int, request: str, reply_len: int) -> str:
    os.write(fd, bytes.fromhex(request))
    data = b""
    deadline = time.monotonic() + 2
    while len(data) < reply_len and time.monotonic() < deadline:
        ready, _, _ = select.select([fd], [], [], 0.1)
        if ready:
            data += os.read(fd, 256)
    return data.hex(" ").upper()


def test_dh_gripper_answers_the_manuals_example_frames(dh: FakeDHGripper) -> None:
    fd = os.open(dh.device, os.O_RDWR | os.O_NOCTTY)
    tty.setraw(fd)
    try:
        # Write replies echo the request (manual: "Initialize", "Set position 500").
        assert _transact(fd, "01 06 01 00 00 01 49 F6", 8) == "01 06 01 00 00 01 49 F6"
        time.sleep(0.1)
        assert _transact(fd, "01 03 02 00 00 01 85 B2", 7) == "01 03 02 00 01 79 84"  # initialized
        assert _transact(fd, "01 06 01 03 01 F4 78 21", 8) == "01 06 01 03 01 F4 78 21"
    finally:
        os.close(fd)
