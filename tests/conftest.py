"""Shared fixtures: a real Mosquitto on 127.0.0.1 and connected MQTT clients."""

from __future__ import annotations

import os

# Headless offscreen rendering with Mesa; must be set before MuJoCo is first imported.
os.environ.setdefault("MUJOCO_GL", "osmesa")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])

from collections.abc import Callable, Iterator
from typing import Any

import pytest

from telerig.bus.broker import MosquittoBroker
from telerig.bus.mqtt import MqttBus


@pytest.fixture
def broker() -> Iterator[MosquittoBroker]:
    """A fresh Mosquitto per test on a free port (starting one takes ~30 ms)."""
    with MosquittoBroker() as running:
        yield running


@pytest.fixture
def make_bus(broker: MosquittoBroker) -> Iterator[Callable[..., MqttBus]]:
    """Factory of connected :class:`MqttBus` clients of ``broker``, closed at teardown."""
    buses: list[MqttBus] = []

    def make(client_id: str, **options: Any) -> MqttBus:
        bus = MqttBus(broker.url, client_id=client_id, **options).connect()
        buses.append(bus)
        return bus

    yield make
    for bus in buses:
        bus.close()
