"""Message bus: MQTT transport, embedded Mosquitto, topic schema and an in-memory bus for tests."""

from telerig.bus.base import Bus, BusStats, Inbox, Message, Subscription
from telerig.bus.broker import MosquittoBroker
from telerig.bus.memory import InMemoryBus
from telerig.bus.mqtt import MqttBus, connect_bus
from telerig.bus.topics import Topic, qos_for

__all__ = [
    "Bus",
    "BusStats",
    "InMemoryBus",
    "Inbox",
    "Message",
    "MosquittoBroker",
    "MqttBus",
    "Subscription",
    "Topic",
    "connect_bus",
    "qos_for",
]
