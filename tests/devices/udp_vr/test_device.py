"""UdpVrDevice against the fake sender on 127.0.0.1: real datagrams, impairments, clocks, config."""

from __future__ import annotations

import itertools
import threading
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest

from telerig.devices.base import Device
from telerig.devices.udp_vr.config import UdpVrConfig
from telerig.devices.udp_vr.device import UdpVrDevice
from telerig.devices.udp_vr.fake import FakeVrSender
from telerig.errors import ConfigError, DeviceError
from telerig.ir.types import ControllerState, FloatArray, HandPose, Pose, Sample
from telerig.registry import DEVICES

TIMEOUT_S = 10.0


class Collector:
    """A sink that records samples and wakes waiters."""

    def __init__(self) -> None:
        self.samples: list[Sample] = []
        self._cond = threading.Condition()

    def __call__(self, sample: Sample) -> None:
        with self._cond:
            self.samples.append(sample)
            self._cond.notify_all()

    def wait_for(self, predicate: Callable[[list[Sample]], bool]) -> None:
        with self._cond:
            assert self._cond.wait_for(lambda: predicate(self.samples), timeout=TIMEOUT_S), "timed out"

    def by_source(self, source: str) -> list[Sample]:
        with self._cond:
            return [s for s in self.samples if s.stamp.source_id == source]


def wait_until(predicate: Callable[[], bool]) -> None:
    deadline = time.monotonic() + TIMEOUT_S
    while not predicate():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.005)


@pytest.fixture
def device() -> Iterator[UdpVrDevice]:
    dev = UdpVrDevice("vr0", port=0)
    yield dev
    dev.stop()


def started(dev: UdpVrDevice) -> Collector:
    sink = Collector()
    dev.start(sink)
    return sink


def test_implements_device_protocol() -> None:
    assert isinstance(UdpVrDevice(port=0), Device)


def test_streamed_frames_become_samples_of_every_part(device: UdpVrDevice) -> None:
    sink = started(device)
    sender = FakeVrSender(device.address[1], rate_hz=200.0)
    sender.start()
    try:
        sink.wait_for(lambda s: sum(x.stamp.source_id == "vr0/right_hand" for x in s) >= 20)
    finally:
        sender.stop()
    kinds = {type(s).__name__ for s in sink.samples}
    assert kinds == {"Pose", "ControllerState", "HandPose"}
    for source in ("vr0/head", "vr0/left", "vr0/right", "vr0/left_hand", "vr0/right_hand"):
        seqs = [s.stamp.seq for s in sink.by_source(source)]
        assert seqs == list(range(len(seqs))), source


def test_stamps_map_the_device_clock_to_the_common_clock(device: UdpVrDevice) -> None:
    sink = started(device)
    sender = FakeVrSender(device.address[1], rate_hz=200.0)  # device clock: monotonic, not epoch
    sender.start()
    try:
        sink.wait_for(lambda s: len(s) >= 50)
    finally:
        sender.stop()
    for s in sink.samples:
        assert 0 < s.stamp.capture_ns <= s.stamp.arrival_ns
        assert s.stamp.device_ns != s.stamp.capture_ns
    captures = [s.stamp.capture_ns for s in sink.by_source("vr0/right")]
    assert all(b > a for a, b in itertools.pairwise(captures))


def test_duplicates_late_garbage_and_oversize_datagrams_are_counted_and_dropped(
    device: UdpVrDevice,
) -> None:
    sink = started(device)
    with FakeVrSender(device.address[1], stream_id=9, hands=False, head=False) as sender:
        frames = {seq: sender.datagram(seq * 0.01, seq, 1_000_000_000 + seq * 10_000_000) for seq in range(5)}
        for data in (frames[0], frames[1], frames[1], frames[3], frames[2], b"\x07garbage", b"\0" * 5000):
            sender.send(data)
        sender.send(frames[4])
        wait_until(lambda: device.stats["received"] == 8)
    stats = device.stats
    assert (stats["accepted"], stats["duplicate"], stats["reordered"]) == (4, 1, 1)
    assert (stats["malformed"], stats["oversize"], stats["lost"]) == (1, 1, 0)
    sink.wait_for(lambda s: len(s) == 8)
    rights = sink.by_source("vr0/right")
    assert [s.stamp.device_ns for s in rights] == [1_000_000_000 + k * 10_000_000 for k in (0, 1, 3, 4)]


def test_gap_is_counted_as_loss(device: UdpVrDevice) -> None:
    started(device)
    with FakeVrSender(device.address[1], hands=False) as sender:
        for seq in (0, 1, 5):
            sender.send(sender.datagram(0.0, seq))
        wait_until(lambda: device.stats["received"] == 3)
    assert device.stats["lost"] == 3


def test_impaired_stream_never_stops_the_device(device: UdpVrDevice) -> None:
    sink = started(device)
    sender = FakeVrSender(
        device.address[1], rate_hz=600.0, loss=0.1, reorder=0.1, duplicate=0.1, garbage=0.2, seed=3
    )
    sender.start()
    try:
        wait_until(lambda: device.stats["malformed"] >= 5 and device.stats["accepted"] >= 100)
    finally:
        sender.stop()
    assert device.running
    assert device.stats["duplicate"] + device.stats["reordered"] > 0
    for source in ("vr0/right", "vr0/left_hand"):
        stamps = [s.stamp for s in sink.by_source(source)]
        assert [st.seq for st in stamps] == list(range(len(stamps)))
        device_times = [st.device_ns for st in stamps]
        assert device_times == sorted(device_times)  # late datagrams never went out
    for s in sink.samples:
        arrays: tuple[FloatArray, ...]
        if isinstance(s, Pose):
            arrays = (s.position, s.orientation)
        elif isinstance(s, ControllerState):
            arrays = (s.position, s.orientation, s.joystick)
        else:
            assert isinstance(s, HandPose)
            arrays = (s.keypoints, s.wrist_orientation, s.keypoint_confidence)
        assert all(np.all(np.isfinite(a)) for a in arrays)


def test_sender_restart_with_a_new_stream_id_is_followed(device: UdpVrDevice) -> None:
    sink = started(device)
    with FakeVrSender(device.address[1], stream_id=1, hands=False, head=False) as first:
        for seq in (500, 501):
            first.send(first.datagram(0.0, seq))
    with FakeVrSender(device.address[1], stream_id=2, hands=False, head=False) as second:
        for seq in (0, 1):
            second.send(second.datagram(0.0, seq))
    sink.wait_for(lambda s: len(s) == 8)
    assert device.stats["restart"] == 1


def test_sink_errors_are_counted_not_raised(device: UdpVrDevice) -> None:
    def failing(sample: Sample) -> None:
        raise RuntimeError("consumer bug")

    device.start(failing)
    with FakeVrSender(device.address[1], hands=False, head=False, controllers=True) as sender:
        sender.send(sender.datagram(0.0, 0))
        wait_until(lambda: device.stats["sink_error"] == 2)
    assert device.running


def test_stop_is_idempotent(device: UdpVrDevice) -> None:
    started(device)
    device.stop()
    device.stop()
    assert not device.running


def test_start_twice_raises(device: UdpVrDevice) -> None:
    started(device)
    with pytest.raises(DeviceError, match="already running"):
        device.start(Collector())


def test_port_in_use_raises_device_error_naming_the_fix(device: UdpVrDevice) -> None:
    started(device)
    other = UdpVrDevice("vr1", port=device.address[1])
    with pytest.raises(DeviceError, match="pick a free port"):
        other.start(Collector())
    assert not other.running


def test_address_before_start_raises() -> None:
    with pytest.raises(DeviceError, match="not started"):
        _ = UdpVrDevice(port=0).address


def test_fake_sender_rejects_bad_probabilities() -> None:
    with pytest.raises(ConfigError, match="loss must be a probability"):
        FakeVrSender(1, loss=1.5)


def test_device_clock_window_is_a_time_window() -> None:
    assert UdpVrDevice(port=0).clock.window_ns == 6_000_000_000
    assert UdpVrDevice(port=0, clock_window_s=0.5).clock.window_ns == 500_000_000
    with pytest.raises(DeviceError, match="clock_window_s"):
        UdpVrDevice(port=0, clock_window_s=0.0)


def test_sender_restart_resets_the_clock_offset() -> None:
    dev = UdpVrDevice("vr0", port=0)
    sink = Collector()
    first = FakeVrSender(1, stream_id=1, hands=False, head=False)
    second = FakeVrSender(1, stream_id=2, hands=False, head=False)
    dev.handle(first.datagram(0.0, 7, 1_000_000_000), 5_000_000_000, sink)
    assert dev.clock.offset_ns == 4_000_000_000
    # The restarted sender's clock has a new origin: the old (smaller) minimum must not survive.
    dev.handle(second.datagram(0.0, 0, 10), 5_001_000_000, sink)
    assert dev.stats["restart"] == 1
    assert dev.clock.offset_ns == 5_001_000_000 - 10
    assert all(s.stamp.capture_ns <= s.stamp.arrival_ns for s in sink.samples)
    assert sink.samples[-1].stamp.capture_ns == 5_001_000_000


def test_config_builds_the_device() -> None:
    cfg = DEVICES.parse_config(
        {"type": "udp_vr", "id": "quest", "port": 0, "clock_window_s": 2.5}, "devices[0]"
    )
    assert isinstance(cfg, UdpVrConfig)
    dev = cfg.build()
    assert isinstance(dev, UdpVrDevice)
    assert (dev.id, dev.host, dev.port, dev.clock.window_ns) == ("quest", "127.0.0.1", 0, 2_500_000_000)
    assert UdpVrConfig.model_validate(cfg.model_dump()) == cfg


def test_config_rejects_a_bad_port() -> None:
    with pytest.raises(ValueError, match="port"):
        DEVICES.parse_config({"type": "udp_vr", "id": "quest", "port": 70000}, "devices[0]")
