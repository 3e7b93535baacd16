"""The NatNet client against the fake Motive server on 127.0.0.1: real UDP bytes, names, stamps, drops."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator

import numpy as np
import pytest

from telerig.devices.base import Device
from telerig.devices.mocap import NatNetClient
from telerig.devices.mocap.config import BvhConfig, NatNetConfig
from telerig.devices.mocap.fake import RIGID_BODY_NAMES, FakeNatNetServer, sample_bvh_path
from telerig.devices.mocap.protocol import NAT_CONNECT, NAT_REQUEST_MODELDEF
from telerig.errors import DeviceError
from telerig.ir.types import BodySkeleton, Pose, Sample, now_ns
from telerig.registry import DEVICES

TIMEOUT_S = 5.0


class Collector:
    """Sink that records samples and signals once ``want`` samples matched ``predicate``."""

    def __init__(self, want: int, predicate: Callable[[Sample], bool] = lambda s: True) -> None:
        self.samples: list[Sample] = []
        self.want = want
        self.predicate = predicate
        self.done = threading.Event()
        self._lock = threading.Lock()

    def __call__(self, sample: Sample) -> None:
        with self._lock:
            self.samples.append(sample)
            if sum(map(self.predicate, self.samples)) >= self.want:
                self.done.set()


@pytest.fixture
def server() -> Iterator[FakeNatNetServer]:
    with FakeNatNetServer(invalid_every=4) as running:
        yield running


def client(server: FakeNatNetServer, **kwargs: object) -> NatNetClient:
    host, port = server.address
    return NatNetClient(
        "mc",
        server=host,
        command_port=port,
        multicast_group=None,
        local_address="127.0.0.1",
        data_port=0,
        **kwargs,
    )  # type: ignore[arg-type]


def _stream(dev: NatNetClient, sink: Collector) -> None:
    """Run ``dev`` into ``sink`` until the sink has what it wants (or the timeout), then stop it."""
    dev.start(sink)
    try:
        assert sink.done.wait(TIMEOUT_S)
    finally:
        dev.stop()


def test_implements_device_protocol() -> None:
    assert isinstance(NatNetClient(), Device)


def test_streams_named_poses_and_a_skeleton_from_unicast_frames(server: FakeNatNetServer) -> None:
    dev = client(server)
    sink = Collector(60, lambda s: isinstance(s, BodySkeleton))
    _stream(dev, sink)
    sources = {s.stamp.source_id for s in sink.samples}
    assert sources == {f"mc/{n}" for n in RIGID_BODY_NAMES} | {"mc/operator"}
    skeletons = [s for s in sink.samples if isinstance(s, BodySkeleton)]
    assert skeletons[0].joint_names[:2] == ("Hips", "LeftUpLeg")
    assert len(skeletons[0].joint_names) == 21
    assert all(s.frame_id == "mocap" for s in skeletons)
    hips_height = skeletons[-1].positions[0, 2]
    assert 0.85 < hips_height < 1.0  # Motive Y up -> z up, metres
    assert server.requests[NAT_CONNECT] >= 1
    assert server.requests[NAT_REQUEST_MODELDEF] >= 1


def test_seq_increases_by_one_and_device_clock_is_mid_exposure(server: FakeNatNetServer) -> None:
    dev = client(server)
    sink = Collector(40, lambda s: s.stamp.source_id == "mc/head")
    _stream(dev, sink)
    head = [s for s in sink.samples if s.stamp.source_id == "mc/head"]
    assert [s.stamp.seq for s in head] == list(range(len(head)))
    device = np.array([s.stamp.device_ns for s in head])
    assert np.all(np.diff(device) > 0)
    periods = np.diff(device) / (1e9 / 120)  # fake server: 120 Hz, 10 MHz clock
    np.testing.assert_allclose(periods, np.round(periods), atol=1e-3)
    capture = np.array([s.stamp.capture_ns for s in head])
    assert np.all(capture <= now_ns())
    assert np.all(now_ns() - capture < 10e9)


def test_frames_to_an_explicit_data_port_are_received(server: FakeNatNetServer) -> None:
    dev = client(server)
    sink = Collector(10, lambda s: isinstance(s, Pose))
    dev.start(sink)
    try:
        assert dev.data_address is not None
        server.data_target = dev.data_address
        assert sink.done.wait(TIMEOUT_S)
    finally:
        dev.stop()
    assert dev.stats["frames"] > 0


def test_untracked_bodies_are_dropped_and_counted(server: FakeNatNetServer) -> None:
    dev = client(server)
    sink = Collector(30, lambda s: s.stamp.source_id == "mc/tool")
    _stream(dev, sink)
    assert dev.stats["tracking_invalid"] > 0
    right = sum(s.stamp.source_id == "mc/right_wrist" for s in sink.samples)
    tool = sum(s.stamp.source_id == "mc/tool" for s in sink.samples)
    assert right < tool  # every 4th frame drops the first body


def test_garbage_datagrams_are_counted_and_streaming_continues(server: FakeNatNetServer) -> None:
    dev = client(server)
    first = Collector(5, lambda s: isinstance(s, Pose))
    dev.start(first)
    try:
        assert first.done.wait(TIMEOUT_S)
        for junk in (
            b"",
            b"\x07\x00",
            b"\x07\x00\xff\x00" + b"\x01" * 40,
            b"\x05\x00\x04\x00\xff\xff\xff\xff",
        ):
            server.send_raw(junk)
        more = len(first.samples) + 20
        first.want, first.predicate = more, lambda s: True
        first.done.clear()
        assert first.done.wait(TIMEOUT_S)
    finally:
        dev.stop()
    assert dev.stats["malformed"] >= 2


def test_stop_is_idempotent_and_double_start_raises(server: FakeNatNetServer) -> None:
    dev = client(server)
    dev.start(lambda s: None)
    with pytest.raises(DeviceError, match="already running"):
        dev.start(lambda s: None)
    dev.stop()
    dev.stop()


def test_sink_exception_does_not_stop_the_stream(server: FakeNatNetServer) -> None:
    dev = client(server)
    seen = threading.Event()
    count = [0]

    def sink(sample: Sample) -> None:
        count[0] += 1
        if count[0] > 20:
            seen.set()
        raise RuntimeError("consumer bug")

    dev.start(sink)
    try:
        assert seen.wait(TIMEOUT_S)
    finally:
        dev.stop()


def test_client_clock_offset_uses_a_5_s_window_and_restarts_on_1_s_jumps() -> None:
    clock = NatNetClient()._offset
    assert (clock.window_ns, clock.reset_ns) == (5_000_000_000, 1_000_000_000)
    assert clock.update(1_000, 6_000) == 5_000
    assert clock.update(2_000, 6_500) == 4_500
    assert clock.update(3_000, 9_000) == 4_500
    # A frame 2 s late (a stalled receiver): the server clock went on, so the offset holds.
    assert clock.update(4_000, 2_000_004_000) == 4_500
    assert clock.update(500, 5_000_000_500) == 5_000_000_000  # server restart: start over


def test_frames_the_network_lost_are_counted_from_frame_numbers() -> None:
    with FakeNatNetServer(lose_every=5) as lossy:
        dev = client(lossy)
        sink = Collector(200, lambda s: s.stamp.source_id == "mc/tool")
        _stream(dev, sink)
    frames, missed = dev.stats["frames"], dev.stats["frames_missed"]
    assert missed > 0
    assert abs(missed - frames / 4) <= 2  # one lost after every four received


def test_natnet_config_builds_a_client() -> None:
    cfg = DEVICES.parse_config(
        {"type": "natnet", "id": "mocap0", "server": "10.0.0.5", "multicast_group": None, "version": "4.1"},
        "devices[0]",
    )
    assert isinstance(cfg, NatNetConfig)
    dev = cfg.build()
    assert isinstance(dev, NatNetClient)
    assert dev.id == "mocap0"
    assert dev.version is not None
    assert str(dev.version) == "4.1"
    assert NatNetConfig(id="m").multicast_group == "239.255.42.99"


def test_natnet_config_rejects_parallel_axes() -> None:
    with pytest.raises(ValueError, match="orthogonal"):
        DEVICES.parse_config(
            {"type": "natnet", "id": "m", "up_axis": "+y", "forward_axis": "-y"}, "devices[0]"
        )


def test_bvh_config_builds_a_player() -> None:
    cfg = DEVICES.parse_config({"type": "bvh", "id": "b", "path": str(sample_bvh_path())}, "devices[0]")
    assert isinstance(cfg, BvhConfig)
    assert cfg.scale == "auto"
    dev = cfg.build()
    assert dev.id == "b"
