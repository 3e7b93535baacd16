"""Replay device: re-emits a recorded stream in order, with its timing, restamped."""

from __future__ import annotations

import dataclasses
import itertools
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from telerig.devices.base import Device
from telerig.devices.replay import ReplayDevice
from telerig.errors import DeviceError
from telerig.ir import wire
from telerig.ir.mcap_log import McapLog
from telerig.ir.types import ControllerState, GripperCommand, Sample, Stamp

CTRL = "telerig/v1/test/vr0/controller_right"
GRIP = "telerig/v1/test/control/gripper"
N = 20
PERIOD_NS = 20_000_000  # 50 Hz recording
GAP_NS = 60_000_000  # extra pause before sample N // 2
T0 = 1_700_000_000_000_000_000


def _controller(i: int) -> ControllerState:
    capture = T0 + i * PERIOD_NS + (GAP_NS if i >= N // 2 else 0)
    return ControllerState(
        Stamp("vr0/right", 100 + i, device_ns=7_000 + i, capture_ns=capture, arrival_ns=capture + 1),
        "right",
        (0.01 * i, 0.0, 1.0),
        (1.0, 0.0, 0.0, 0.0),
        "operator",
        trigger=i / N,
    )


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("replay") / "episode.mcap"
    with McapLog(path) as log:
        for i in range(N):
            s = _controller(i)
            log.write(
                CTRL, wire.encode(s), log_time_ns=s.stamp.arrival_ns, publish_time_ns=s.stamp.capture_ns
            )
            if i % 4 == 0:
                g = GripperCommand(Stamp("control", i, i, T0 + i * PERIOD_NS + 1), 0.5)
                log.write(
                    GRIP, wire.encode(g), log_time_ns=g.stamp.capture_ns, publish_time_ns=g.stamp.capture_ns
                )
    return path


class _Collector:
    def __init__(self) -> None:
        self.samples: list[Sample] = []
        self.at: list[float] = []
        self.lock = threading.Lock()

    def __call__(self, sample: Sample) -> None:
        with self.lock:
            self.at.append(time.perf_counter())
            self.samples.append(sample)


def test_replay_is_a_device(recording: Path) -> None:
    assert isinstance(ReplayDevice(recording, topic=CTRL), Device)


def test_samples_iterate_the_recorded_stream_untimed(recording: Path) -> None:
    got = list(ReplayDevice(recording, source_id="vr0/right").samples())
    assert [wire.encode(s) for s in got] == [wire.encode(_controller(i)) for i in range(N)]


def test_topic_filter_selects_the_stream(recording: Path) -> None:
    got = list(ReplayDevice(recording, topic=GRIP).samples())
    assert {type(s) for s in got} == {GripperCommand}
    assert len(got) == N // 4


def test_several_sources_need_a_filter(recording: Path) -> None:
    with pytest.raises(DeviceError, match=r"2 sources .*control, vr0/right.*set source_id or topic"):
        ReplayDevice(recording).start(lambda s: None)


def test_unknown_source_names_the_available_ones(recording: Path) -> None:
    with pytest.raises(DeviceError, match=r"no source_id 'vr9' .*Available sources: control \(.*gripper\)"):
        list(ReplayDevice(recording, source_id="vr9").samples())


def test_missing_file_is_a_device_error(tmp_path: Path) -> None:
    with pytest.raises(DeviceError, match="does not exist"):
        ReplayDevice(tmp_path / "nope.mcap")


def test_bad_speed_is_rejected(recording: Path) -> None:
    with pytest.raises(ValueError, match="speed"):
        ReplayDevice(recording, speed=0.0)


def test_timed_replay_preserves_order_timing_and_restamps(recording: Path) -> None:
    speed = 4.0
    device = ReplayDevice(recording, topic=CTRL, speed=speed)
    sink = _Collector()
    before_ns = time.time_ns()
    device.start(sink)
    assert device.wait(timeout=5.0)
    device.stop()

    recorded = list(device.samples())
    assert len(sink.samples) == N
    for got, rec in zip(sink.samples, recorded, strict=True):
        assert got.stamp.seq == rec.stamp.seq
        assert got.stamp.device_ns == rec.stamp.device_ns
        assert got.stamp.source_id == rec.stamp.source_id
        assert got.stamp.arrival_ns == 0
        assert got.stamp.capture_ns >= before_ns
        # Everything but the two restamped times is identical to the untimed iteration.
        assert wire.encode(got) == wire.encode(dataclasses.replace(rec, stamp=got.stamp))
    captures = [s.stamp.capture_ns for s in sink.samples]
    assert captures == sorted(captures)
    # Absolute schedule: total span matches the recording / speed (generous for a loaded CI box).
    expected_s = (recorded[-1].stamp.capture_ns - recorded[0].stamp.capture_ns) / 1e9 / speed
    assert expected_s - 0.02 <= sink.at[-1] - sink.at[0] <= expected_s + 0.15
    # The long pause mid-stream is reproduced: it starts no earlier than scheduled.
    long_gap = sink.at[N // 2] - sink.at[0]
    assert long_gap >= ((N // 2) * PERIOD_NS + GAP_NS) / 1e9 / speed - 0.005


def test_a_late_replay_stamps_each_sample_when_it_fell_due(recording: Path) -> None:
    """A sink that blocks for 0.25 s makes the replay late; the samples it then owes go out back to
    back, each stamped with its due time, so capture times keep the recording's spacing / speed."""
    speed = 2.0
    device = ReplayDevice(recording, topic=CTRL, speed=speed)
    sink = _Collector()

    def blocking(sample: Sample) -> None:
        sink(sample)
        if len(sink.samples) == 3:
            time.sleep(0.25)

    device.start(blocking)
    assert device.wait(timeout=5.0)
    device.stop()
    assert len(sink.samples) == N
    # The block made it late: the next samples were emitted together, not a period apart.
    assert sink.at[5] - sink.at[3] < PERIOD_NS / 1e9 / speed
    recorded = [s.stamp.capture_ns for s in device.samples()]
    got = [s.stamp.capture_ns for s in sink.samples]
    expected = np.diff(recorded) / speed
    np.testing.assert_allclose(np.diff(got), expected, rtol=0.02)


def test_loop_keeps_seq_increasing_until_stopped(recording: Path) -> None:
    device = ReplayDevice(recording, source_id="vr0/right", speed=20.0, loop=True)
    sink = _Collector()
    device.start(sink)
    deadline = time.monotonic() + 5.0
    while len(sink.samples) < 2 * N + 3 and time.monotonic() < deadline:
        time.sleep(0.005)
    device.stop()
    device.stop()
    seqs = [s.stamp.seq for s in sink.samples]
    assert len(seqs) >= 2 * N + 3
    assert seqs[:N] == list(range(100, 100 + N))
    assert all(b > a for a, b in itertools.pairwise(seqs))
    assert not device.running


def test_stop_before_start_and_restart(recording: Path) -> None:
    device = ReplayDevice(recording, topic=GRIP, speed=50.0)
    device.stop()
    sink = _Collector()
    device.start(sink)
    with pytest.raises(DeviceError, match="already running"):
        device.start(sink)
    device.wait(timeout=5.0)
    device.stop()
    device.start(sink)
    device.wait(timeout=5.0)
    device.stop()
    assert len(sink.samples) == 2 * (N // 4)
