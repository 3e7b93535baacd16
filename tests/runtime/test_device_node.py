"""Device node: only valid samples reach the bus, and health counters are published retained."""

from __future__ import annotations

import json
import math
import threading
import time
from collections.abc import Sequence

import pytest

from telerig.bus.base import Message
from telerig.bus.memory import InMemoryBus
from telerig.bus.topics import Topic
from telerig.devices.base import SampleSink, on_change_streams
from telerig.devices.scripted_twist.device import ScriptedTwistDevice, TwistSegment
from telerig.devices.validate import DROP_REASONS, SampleValidator, ValidationConfig
from telerig.ir import wire
from telerig.ir.types import ControllerState, Sample, Stamp
from telerig.runtime.device_node import DeviceNode

T0 = 1_700_000_000_000_000_000
PERIOD = 10_000_000
HEALTH = str(Topic("t", "vr0", "health"))
DATA = str(Topic("t", "vr0", "right_controller"))


def sample(
    i: int, position: tuple[float, float, float] = (0.4, 0.0, 1.1), ns: int | None = None
) -> ControllerState:
    t = T0 + i * PERIOD if ns is None else ns
    return ControllerState(Stamp("vr0/right", i, t, t), "right", position, (1.0, 0.0, 0.0, 0.0), "operator")


class ListDevice:
    """Delivers a fixed list of samples synchronously from ``start``; counts like a real device."""

    def __init__(self, samples: Sequence[Sample]) -> None:
        self.samples = list(samples)
        self.stats = {"malformed": 2}
        self.stopped = 0

    @property
    def id(self) -> str:
        return "vr0"

    def start(self, sink: SampleSink) -> None:
        for s in self.samples:
            sink(s)

    def stop(self) -> None:
        self.stopped += 1


class FakeClock:
    def __init__(self) -> None:
        self.ns = 0

    def __call__(self) -> int:
        return self.ns


def collect(bus: InMemoryBus, pattern: str) -> list[Message]:
    got: list[Message] = []
    bus.subscribe(pattern, got.append)
    return got


def test_invalid_samples_are_not_published() -> None:
    bus = InMemoryBus()
    data = collect(bus, DATA)
    good = [sample(i) for i in range(5)]
    bad = sample(5, position=(math.nan, 0.0, 0.0))
    node = DeviceNode("t", ListDevice([*good, bad, sample(6)]), bus, health_period_s=None)
    node.start()
    seqs = [wire.decode(m.payload).stamp.seq for m in data]
    assert seqs == [0, 1, 2, 3, 4, 6]
    assert node.published == 6


def test_health_is_published_retained_on_stop() -> None:
    bus = InMemoryBus()
    clock = FakeClock()
    samples = [sample(i) for i in range(10)] + [sample(10, ns=T0)]  # last one is non-monotonic
    node = DeviceNode("t", ListDevice(samples), bus, health_period_s=None, clock=clock)
    node.start()
    clock.ns = 2_000_000_000
    node.stop()
    late = collect(bus, HEALTH)  # a late joiner still gets it
    assert len(late) == 1
    health = json.loads(late[0].payload)
    assert health == {
        "received": 11,
        "published": 10,
        "dropped": {**dict.fromkeys(DROP_REASONS, 0), "non_monotonic": 1},
        "rate_hz": 5.0,
        "device": {"malformed": 2},
    }


def test_health_rate_covers_the_window_since_the_last_report() -> None:
    bus = InMemoryBus()
    clock = FakeClock()
    node = DeviceNode("t", ListDevice([sample(i) for i in range(20)]), bus, health_period_s=None, clock=clock)
    node.start()
    clock.ns = 1_000_000_000
    assert node.publish_health().rate_hz == 20.0
    clock.ns = 2_000_000_000
    assert node.publish_health().rate_hz == 0.0


def test_health_is_reported_periodically_while_running() -> None:
    bus = InMemoryBus()
    reported = threading.Event()
    bus.subscribe(HEALTH, lambda m: reported.set())
    node = DeviceNode("t", ListDevice([sample(0)]), bus, health_period_s=0.01)
    node.start()
    try:
        assert reported.wait(timeout=5.0)
    finally:
        node.stop()


def test_stop_and_start_are_idempotent() -> None:
    bus = InMemoryBus()
    device = ListDevice([sample(0)])
    node = DeviceNode("t", device, bus, health_period_s=None)
    node.start()
    node.start()
    node.stop()
    node.stop()
    assert device.stopped == 1
    assert node.published == 1


def test_restart_after_a_pause_is_not_an_abnormal_gap() -> None:
    bus = InMemoryBus()
    device = ListDevice([sample(i) for i in range(10)])
    node = DeviceNode("t", device, bus, validator=SampleValidator.default(), health_period_s=None)
    node.start()
    node.stop()
    device.samples = [sample(i) for i in range(1000, 1005)]  # 10 s later
    node.start()
    node.stop()
    assert node.published == 15
    assert node.health().dropped["gap"] == 0


@pytest.mark.parametrize("explicit", [True, False], ids=["rig_validator", "default_validator"])
def test_every_button_press_of_a_device_that_sends_on_change_is_published(explicit: bool) -> None:
    # The fleet soak lost one TIAGo mode-button press per episode: the gap check had learned a
    # "period" from the first presses. The scripted twist device, run for real: five short pauses
    # between changes, then a long one (10x), then one more press and release.
    press, release = frozenset({"left"}), frozenset()
    segments = [
        TwistSegment(0.03),
        *(TwistSegment(0.03, buttons=press if i % 2 == 0 else release) for i in range(5)),
    ]
    segments += [TwistSegment(0.3), TwistSegment(0.03, buttons=press), TwistSegment(0.2)]
    device = ScriptedTwistDevice("twist", segments=segments, rate_hz=200.0, loop=False)
    assert device.on_change_streams == {"right_controller"}
    bus = InMemoryBus()
    buttons = collect(bus, str(Topic("t", "twist", "right_controller")))
    # What the rig's nodes build (runtime.nodes), or the node's own default.
    validator = (
        SampleValidator.from_config(ValidationConfig(), on_change_streams=on_change_streams(device))
        if explicit
        else None
    )
    node = DeviceNode("t", device, bus, validator=validator, health_period_s=None)
    node.start()
    deadline = time.monotonic() + 10.0
    while len(buttons) < 8 and time.monotonic() < deadline:
        time.sleep(0.01)
    node.stop()
    assert [wire.decode(m.payload).stamp.seq for m in buttons] == list(range(8))
    assert node.health().dropped["gap"] == 0
