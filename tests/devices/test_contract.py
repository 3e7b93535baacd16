"""Contract of every registered device type, built from its config against its fake peer and run
through a DeviceNode on an InMemoryBus: topics, wire round trip, stamps, validation, threads.

Each registered ``type`` needs an entry in :data:`CASES`; a type without one fails
:func:`test_every_registered_type_has_a_contract_case` and its own parametrized tests.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import math
import subprocess
import sys
import threading
import time
from collections import defaultdict
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from telerig.bus.base import Message
from telerig.bus.catalogue import CATALOGUE, DEVICE_SAMPLE, NodeRole
from telerig.bus.memory import InMemoryBus
from telerig.config.schema import DeviceConfig
from telerig.devices.base import Device, on_change_streams
from telerig.devices.config import ReplayConfig, ScriptedVRConfig
from telerig.devices.fake_glove.config import FakeGloveConfig
from telerig.devices.gamepad.config import GamepadConfig
from telerig.devices.gamepad.fake import FakeGamepad
from telerig.devices.glove.config import GloveConfig
from telerig.devices.glove.fake import FakeGloveBridge
from telerig.devices.keyboard.config import KeyboardConfig
from telerig.devices.keyboard.fake import FakeTerminal
from telerig.devices.leap.config import LeapConfig
from telerig.devices.leap.fake import FakeLeapService
from telerig.devices.markerless.config import MarkerlessConfig
from telerig.devices.markerless.device import MarkerlessDevice
from telerig.devices.markerless.fake import FakeTracker
from telerig.devices.mocap.config import BvhConfig, NatNetConfig
from telerig.devices.mocap.fake import RIGID_BODY_NAMES, FakeNatNetServer, sample_bvh_path
from telerig.devices.pick_place.config import RetargetedReplayConfig, ScriptedPickPlaceConfig
from telerig.devices.policy.config import PolicyConfig
from telerig.devices.policy.device import PolicyDevice
from telerig.devices.scripted_twist.config import ScriptedTwistConfig, TwistSegmentConfig
from telerig.devices.spacemouse.config import SpaceMouseConfig
from telerig.devices.spacemouse.fake import FakeSpaceMouse
from telerig.devices.udp_vr.config import UdpVrConfig
from telerig.devices.udp_vr.device import UdpVrDevice
from telerig.devices.udp_vr.fake import FakeVrSender
from telerig.devices.webxr.config import WebXRConfig
from telerig.devices.webxr.device import WebXRDevice
from telerig.devices.webxr.fake import XRControllerInput, XRHandInput, encode_frame
from telerig.devices.webxr.relay import MESSAGE, OPEN, encode_event, open_body
from telerig.ir import wire
from telerig.ir.mcap_log import McapLog
from telerig.ir.observation import encode_observation
from telerig.ir.types import ControllerState, GripperCommand, JointState, Pose, Sample, Stamp
from telerig.registry import DEVICES
from telerig.runtime.device_node import HEALTH, DeviceNode

RIG = "contract"
#: How long a device may take to deliver the samples its case asks for [s].
TIMEOUT_S = 5.0
#: Allowed lead of a capture time over the moment its sample was published [ns].
CAPTURE_TOLERANCE_NS = 1_000_000
#: Samples each continuous stream publishes before a run ends (about 0.5 s at 100 Hz).
N = 50


# ---------------------------------------------------------------------------------------------
# Cases: one per registered type. A case builds the fake peer, returns the device config that
# points at it and, once the device is started, starts feeding it.

Feed = Callable[[Device, contextlib.ExitStack], None]


def _no_feed(device: Device, stack: contextlib.ExitStack) -> None:
    """The peer streams on its own (or the device is its own source)."""


@dataclass(frozen=True)
class Case:
    """A device config pointing at its fake peer and what a clean run must publish.

    Attributes:
        config: The device's config (its ``id`` is the topic's node level).
        streams: Stream name -> samples each must publish before the run ends.
        feed: Starts the peer once the device runs (for peers that need the device's address).
        allowed_drops: Validator drop reason -> why a clean run of this family may produce it.
    """

    config: DeviceConfig
    streams: Mapping[str, int]
    feed: Feed = _no_feed
    allowed_drops: Mapping[str, str] = field(default_factory=dict)


class _Pacer:
    """Calls ``step(k)`` for k = 0, 1, ... at ``rate_hz`` on a thread until :meth:`close` (a peer
    without its own streaming loop). Ends quietly when the peer fails, e.g. after the device closed
    the connection."""

    def __init__(self, step: Callable[[int], None], rate_hz: float) -> None:
        self._step = step
        self._period = 1.0 / rate_hz
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="contract-fake-pacer", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        t0 = time.perf_counter()
        for k in itertools.count():
            delay = t0 + k * self._period - time.perf_counter()
            if self._stop.wait(max(delay, 0.0)):
                return
            try:
                self._step(k)
            except Exception:  # the device went away first; nothing left to feed
                return

    def close(self) -> None:
        self._stop.set()
        self._thread.join()


def _scripted_vr(stack: contextlib.ExitStack, tmp: Path) -> Case:
    return Case(ScriptedVRConfig(id="vr0", rate_hz=100.0), {"right_controller": N})


def _replay(stack: contextlib.ExitStack, tmp: Path) -> Case:
    path = tmp / "episode.mcap"
    t0 = 1_700_000_000_000_000_000
    with McapLog(path) as log:
        for i in range(2 * N):
            capture = t0 + i * 10_000_000  # 100 Hz
            sample = ControllerState(
                Stamp("vr0/right", 100 + i, device_ns=5_000 + i, capture_ns=capture, arrival_ns=capture + 1),
                "right",
                (0.4 + 0.002 * i, 0.0, 1.0),
                (1.0, 0.0, 0.0, 0.0),
                "operator",
                trigger=i / (2 * N),
            )
            log.write(
                "telerig/v1/rec/vr0/right_controller",
                wire.encode(sample),
                log_time_ns=capture + 1,
                publish_time_ns=capture,
            )
    return Case(ReplayConfig(id="replay", path=path, source_id="vr0/right"), {"right_controller": N})


def _bvh(stack: contextlib.ExitStack, tmp: Path) -> Case:
    return Case(BvhConfig(id="bvh0", path=sample_bvh_path(), speed=2.0), {"body": N})


def _natnet(stack: contextlib.ExitStack, tmp: Path) -> Case:
    server = stack.enter_context(FakeNatNetServer(rate_hz=120.0))
    host, port = server.address
    config = NatNetConfig(
        id="mc",
        server=host,
        command_port=port,
        multicast_group=None,
        local_address="127.0.0.1",
        data_port=0,
    )
    return Case(config, dict.fromkeys((*RIGID_BODY_NAMES, "operator"), N))


def _udp_vr(stack: contextlib.ExitStack, tmp: Path) -> Case:
    def feed(device: Device, stack: contextlib.ExitStack) -> None:
        assert isinstance(device, UdpVrDevice)
        sender = FakeVrSender(device.address[1], rate_hz=100.0)
        stack.callback(sender.stop)
        sender.start()

    streams = ("head", "left_controller", "right_controller", "left_hand", "right_hand")
    return Case(UdpVrConfig(id="vr0", port=0), dict.fromkeys(streams, N), feed)


def _webxr(stack: contextlib.ExitStack, tmp: Path) -> Case:
    def feed(device: Device, stack: contextlib.ExitStack) -> None:
        # Plays telerig serve's relay: a logged-in page's envelopes, as they arrive on page_in.
        assert isinstance(device, WebXRDevice)
        device.page_message(encode_event(OPEN, 1, open_body("otto", "127.0.0.1")))

        def step(k: int) -> None:
            sway = 0.05 * math.sin(k / 20.0)
            frame = encode_frame(
                k,
                time.time_ns() / 1e6,
                head=((0.0, 1.6, 0.0), (0.0, 0.0, 0.0, 1.0)),
                left=XRControllerInput((-0.2 + sway, 1.0, -0.3), trigger=0.2),
                right=XRControllerInput((0.2 + sway, 1.0, -0.3), trigger=0.7, squeeze=1.0),
                left_hand=XRHandInput.flat((-0.2 + sway, 1.0, -0.3)),
                right_hand=XRHandInput.flat((0.2 + sway, 1.0, -0.3)),
            )
            device.page_message(encode_event(MESSAGE, 1, frame))

        stack.callback(_Pacer(step, 100.0).close)

    streams = ("head", "left_controller", "right_controller", "left_hand", "right_hand")
    config = WebXRConfig(id="xr0", ping_interval_s=0.05)
    return Case(config, dict.fromkeys(streams, N), feed)


def _glove(stack: contextlib.ExitStack, tmp: Path) -> Case:
    bridge = stack.enter_context(FakeGloveBridge(hand="right", rate_hz=120.0))
    return Case(GloveConfig(id="glove0", port=bridge.port, hand="right"), {"right_hand": N})


def _leap(stack: contextlib.ExitStack, tmp: Path) -> Case:
    service = stack.enter_context(FakeLeapService(rate_hz=110.0))
    return Case(LeapConfig(id="leap0", url=service.url), {"left_hand": N, "right_hand": N})


def _markerless(stack: contextlib.ExitStack, tmp: Path) -> Case:
    def feed(device: Device, stack: contextlib.ExitStack) -> None:
        assert isinstance(device, MarkerlessDevice)
        tracker = stack.enter_context(FakeTracker(device.address))
        stack.callback(_Pacer(lambda k: tracker.send_frame(k, hands=("right", "left")), 60.0).close)

    config = MarkerlessConfig(id="cam0", listen_port=0)
    return Case(config, {"right_hand": N, "left_hand": N, "body": N}, feed)


def _spacemouse(stack: contextlib.ExitStack, tmp: Path) -> Case:
    fifo = tmp / "hidraw0"
    fake = stack.enter_context(FakeSpaceMouse(fifo, combined=True))

    def feed(device: Device, stack: contextlib.ExitStack) -> None:
        fake.connect()
        fake.buttons(0b01)
        fake.play(duration_s=2.0, rate_hz=100.0)

    config = SpaceMouseConfig(id="sm", path=str(fifo), layout="combined")
    return Case(
        config,
        {"twist": N, "right_controller": 1},
        feed,
        allowed_drops={
            "non_monotonic": "a FIFO loses report boundaries: reports coalesced into one read share its "
            "capture time, and the second is not newer than the first (hidraw returns one report per read)"
        },
    )


def _gamepad(stack: contextlib.ExitStack, tmp: Path) -> Case:
    fifo = tmp / "event0"
    fake = stack.enter_context(FakeGamepad(fifo))

    def feed(device: Device, stack: contextlib.ExitStack) -> None:
        fake.connect()
        fake.play(duration_s=2.0, rate_hz=100.0)

    config = GamepadConfig(id="gp", path=str(fifo))
    return Case(config, {"twist": N, "left_controller": N, "right_controller": N}, feed)


def _keyboard(stack: contextlib.ExitStack, tmp: Path) -> Case:
    term = stack.enter_context(FakeTerminal())

    def feed(device: Device, stack: contextlib.ExitStack) -> None:
        term.type("space")  # toggles the trigger: a ControllerState
        term.hold("w", 2.0, repeat_delay_s=0.05, repeat_hz=30.0)

    config = KeyboardConfig(id="kb", path=term.slave_name, rate_hz=100.0)
    return Case(config, {"twist": N, "right_controller": 2}, feed)


def _fake_glove(stack: contextlib.ExitStack, tmp: Path) -> Case:
    return Case(FakeGloveConfig(id="glove0", hand="right", rate_hz=120.0), {"right_hand": N})


def _scripted_twist(stack: contextlib.ExitStack, tmp: Path) -> Case:
    segments = [
        TwistSegmentConfig(duration_s=0.2, linear=(0.05, 0.0, 0.0), buttons=["left"]),
        TwistSegmentConfig(duration_s=0.2, angular=(0.0, 0.0, 0.2)),
    ]
    config = ScriptedTwistConfig(id="sm0", rate_hz=100.0, segments=segments)
    return Case(config, {"twist": N, "right_controller": 2})


#: The task cube at rest on the table (world frame [m]), as the task robot's object_pose reports it.
_CUBE_AT = np.array([0.5, 0.13, 0.825])


def _feed_cube_at_rest(device: Device, stack: contextlib.ExitStack) -> None:
    """Report the cube at rest on ``arm0/object_pose`` at 50 Hz, as a task robot's node would."""
    observe = device.observe

    def step(k: int) -> None:
        now = time.time_ns()
        observe(Pose(Stamp("arm0/cube", k, now, now), _CUBE_AT, np.array([1.0, 0.0, 0.0, 0.0]), "world"))

    stack.callback(_Pacer(step, 50.0).close)


def _scripted_pick_place(stack: contextlib.ExitStack, tmp: Path) -> Case:
    config = ScriptedPickPlaceConfig(id="op0", robot="arm0", rate_hz=100.0)
    return Case(config, {"right_controller": N}, _feed_cube_at_rest)


def _replay_retargeted(stack: contextlib.ExitStack, tmp: Path) -> Case:
    """A recorded 1 s demonstration (controller at 100 Hz and the cube it picked) bent to a cube
    5 cm away."""
    path = tmp / "demo.mcap"
    topic = "telerig/v1/task/vr0/right_controller"
    t0 = 1_700_000_000_000_000_000
    with McapLog(path) as log:
        for i in range(2 * N):
            ns = t0 + i * 10_000_000
            cube = Pose(
                Stamp("arm0/cube", i, ns, ns), _CUBE_AT - (0.05, 0.0, 0.0), np.array([1.0, 0, 0, 0]), "world"
            )
            log.write(
                "telerig/v1/task/arm0/object_pose", wire.encode(cube), log_time_ns=ns, publish_time_ns=ns
            )
            hand = ControllerState(
                Stamp("vr0/right", i, device_ns=i, capture_ns=ns, arrival_ns=ns + 1),
                "right",
                (0.4, 0.0, 1.1 - 0.002 * i),
                (0.0, 1.0, 0.0, 0.0),
                "operator",
                trigger=1.0 if i >= N else 0.0,
            )
            log.write(topic, wire.encode(hand), log_time_ns=ns + 1, publish_time_ns=ns)
    config = RetargetedReplayConfig(id="rp0", path=path, topic=topic, robot="arm0")
    return Case(config, {"right_controller": N}, _feed_cube_at_rest)


_POLICY_CHECKPOINT: list[Path] = []


def _policy(stack: contextlib.ExitStack, tmp: Path) -> Case:
    """A real tiny checkpoint (written once, in a child process: torch stays out of this one), fed
    the robot state and observation frames its device node would hand it."""
    if not _POLICY_CHECKPOINT:
        path = tmp / "tiny.pt"
        code = (
            "import sys; from telerig.policy.checkpoint import tiny_for_tests; "
            "tiny_for_tests(sys.argv[1], state_names=('j0', 'j1', 'gripper'), camera_keys=('scene',), "
            "image_size=(8, 8))"
        )
        subprocess.run([sys.executable, "-c", code, str(path)], check=True, timeout=300)
        _POLICY_CHECKPOINT.append(path)

    def feed(device: Device, stack: contextlib.ExitStack) -> None:
        assert isinstance(device, PolicyDevice)
        stack.callback(device.close)  # ends its inference process
        frame = np.zeros((8, 8, 3), np.uint8)

        def step(k: int) -> None:
            now = time.time_ns()
            device.observe(JointState(Stamp("arm0", k, now, now), ("j0", "j1"), np.zeros(2), np.zeros(2)))
            device.observe(GripperCommand(Stamp("arm0/gripper", k, now, now), 1.0))
            device.observe_frame("scene", encode_observation(frame, now, k))

        stack.callback(_Pacer(step, 50.0).close)

    config = PolicyConfig(id="pi0", checkpoint=_POLICY_CHECKPOINT[0], robot="arm0", rate_hz=50.0)
    return Case(config, {"joints": N}, feed)


CASES: dict[str, Callable[[contextlib.ExitStack, Path], Case]] = {
    "bvh": _bvh,
    "fake_glove": _fake_glove,
    "gamepad": _gamepad,
    "glove": _glove,
    "keyboard": _keyboard,
    "leap": _leap,
    "markerless": _markerless,
    "natnet": _natnet,
    "policy": _policy,
    "replay": _replay,
    "replay_retargeted": _replay_retargeted,
    "scripted_pick_place": _scripted_pick_place,
    "scripted_twist": _scripted_twist,
    "scripted_vr": _scripted_vr,
    "spacemouse": _spacemouse,
    "udp_vr": _udp_vr,
    "webxr": _webxr,
}

TYPES = DEVICES.names()


def _case(name: str, stack: contextlib.ExitStack, tmp: Path) -> Case:
    factory = CASES.get(name)
    if factory is None:
        pytest.fail(
            f"device type {name!r} is registered but has no contract case; add one to CASES in {__file__}"
        )
    return factory(stack, tmp)


# ---------------------------------------------------------------------------------------------
# One run per type: start the node, wait for the samples, stop, record what happened.


@dataclass
class Run:
    """What one run of a device through a DeviceNode left behind.

    Attributes:
        case: The case that was run.
        messages: Every sample message published on the bus, in order.
        dropped: Validator drops per reason (only reasons with a count).
        device_threads: Names of the threads ``DeviceNode.start`` left running (the device's).
        alive_after_stop: Those of ``device_threads`` still alive after ``DeviceNode.stop``.
        leaked: Threads started during the case (device or peer) alive after everything closed.
        stop_errors: Exceptions raised by ``device.stop()`` called again after the node stopped.
        frames_missed: Frames the device saw the transport lose (its ``stats["frames_missed"]``,
            e.g. a full UDP receive buffer after the host stalled), 0 where it cannot tell.
    """

    case: Case
    messages: list[Message]
    dropped: dict[str, int]
    device_threads: list[str]
    alive_after_stop: list[str]
    leaked: list[str]
    stop_errors: list[str]
    frames_missed: int = 0

    def decoded(self) -> list[tuple[Message, Sample]]:
        return [(m, wire.decode(m.payload)) for m in self.messages]


def _topic(config: DeviceConfig, stream: str) -> str:
    return f"telerig/v1/{RIG}/{config.id}/{stream}"


#: Device streams that carry no samples (the catalogue's, besides the health the test reads).
NOT_SAMPLES = frozenset(
    s.name for s in CATALOGUE if s.role is NodeRole.DEVICE and s.name not in (DEVICE_SAMPLE, HEALTH)
)


def _run(name: str, tmp: Path) -> Run:
    before = set(threading.enumerate())
    bus = InMemoryBus()
    messages: list[Message] = []
    counts: dict[str, int] = defaultdict(int)
    arrived = threading.Condition()
    with contextlib.ExitStack() as stack:
        case = _case(name, stack, tmp)
        health = _topic(case.config, HEALTH)

        def on_message(message: Message) -> None:
            stream = message.topic.rsplit("/", 1)[-1]
            if message.topic == health or stream in NOT_SAMPLES:  # e.g. a WebXR device's pings
                return
            with arrived:
                messages.append(message)
                counts[message.topic] += 1
                arrived.notify_all()

        bus.subscribe(f"telerig/v1/{RIG}/#", on_message)
        want = {_topic(case.config, s): n for s, n in case.streams.items()}
        device = case.config.build()
        node = DeviceNode(RIG, device, bus, health_period_s=None)
        idle = set(threading.enumerate())
        node.start()
        try:
            # The glove bridge may start serving the new connection before this snapshot.
            started = [t for t in threading.enumerate() if t not in idle and "fake" not in t.name]
            case.feed(device, stack)
            with arrived:
                arrived.wait_for(lambda: all(counts[t] >= n for t, n in want.items()), TIMEOUT_S)
        finally:
            node.stop()
        node.stop()
        stop_errors = []
        for _ in range(2):
            try:
                device.stop()
            except Exception as exc:
                stop_errors.append(repr(exc))
        alive = [t.name for t in started if t.is_alive()]
        dropped = {k: v for k, v in node.validator.stats().dropped.items() if v}
        stats = getattr(device, "stats", None)
        missed = int(stats.get("frames_missed", 0)) if isinstance(stats, Mapping) else 0
    for thread in set(threading.enumerate()) - before:
        thread.join(timeout=1.0)
    leaked = [t.name for t in threading.enumerate() if t not in before and t.is_alive()]
    bus.close()
    return Run(case, messages, dropped, [t.name for t in started], alive, leaked, stop_errors, missed)


@pytest.fixture(scope="module", params=TYPES)
def run(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Run:
    """One run of each registered device type (shared by the checks below)."""
    name: str = request.param
    return _run(name, tmp_path_factory.mktemp(name))


# ---------------------------------------------------------------------------------------------
# Registration and lifecycle (no I/O)


def test_every_registered_type_has_a_contract_case() -> None:
    missing = sorted(set(TYPES) - set(CASES))
    assert not missing, f"registered device types without a contract case: {missing}"


@pytest.mark.parametrize("name", TYPES)
def test_config_builds_a_device_with_the_config_id(name: str, tmp_path: Path) -> None:
    with contextlib.ExitStack() as stack:
        config = _case(name, stack, tmp_path).config
        device = config.build()
        assert isinstance(device, Device)
        assert device.id == config.id


@pytest.mark.parametrize("name", TYPES)
def test_stop_before_start_is_a_safe_no_op(name: str, tmp_path: Path) -> None:
    with contextlib.ExitStack() as stack:
        case = _case(name, stack, tmp_path)
        device = case.config.build()
        idle = set(threading.enumerate())
        device.stop()
        device.stop()
        started = [t.name for t in set(threading.enumerate()) - idle if t.is_alive()]
        assert not started, f"stop() before start() started threads: {started}"
        # ... and it left the device able to start and deliver.
        delivered = threading.Event()
        device.start(lambda sample: delivered.set())
        try:
            case.feed(device, stack)
            assert delivered.wait(TIMEOUT_S), "no sample after stop() before start()"
        finally:
            device.stop()


@pytest.mark.parametrize("name", TYPES)
def test_streams_sent_on_a_change_are_streams_the_device_sends(name: str, tmp_path: Path) -> None:
    # What a device declares exempt from the gap check (ChangeDrivenDevice) must be one of its streams:
    # a misspelt name would exempt nothing and the next press after a pause would be dropped again.
    with contextlib.ExitStack() as stack:
        case = _case(name, stack, tmp_path)
        declared = on_change_streams(case.config.build())
        assert declared <= set(case.streams), f"{name}: {sorted(declared - set(case.streams))}"
        if name in ("spacemouse", "gamepad", "keyboard", "scripted_twist"):  # buttons on a change
            assert declared


# ---------------------------------------------------------------------------------------------
# What a run publishes


def test_samples_arrive_on_the_expected_topics(run: Run) -> None:
    got: dict[str, int] = defaultdict(int)
    for m in run.messages:
        got[m.topic] += 1
    want = {_topic(run.case.config, s): n for s, n in run.case.streams.items()}
    assert set(got) == set(want), f"published on {sorted(got)}, expected {sorted(want)}"
    short = {t: got[t] for t, n in want.items() if got[t] < n}
    assert not short, f"too few samples within {TIMEOUT_S} s: {short} (want {want})"


def test_every_published_sample_decodes_to_a_sample_of_its_stream(run: Run) -> None:
    for message, sample in run.decoded():
        assert message.topic.rsplit("/", 1)[1] in run.case.streams
        assert sample.stamp.source_id


def _non_finite(sample: object, path: str = "") -> list[str]:
    bad: list[str] = []
    for f in dataclasses.fields(sample):  # type: ignore[arg-type]
        value = getattr(sample, f.name)
        where = f"{path}{f.name}"
        if dataclasses.is_dataclass(value):
            bad += _non_finite(value, where + ".")
        elif isinstance(value, np.ndarray) and value.dtype.kind == "f":
            if not np.all(np.isfinite(value)):
                bad.append(where)
        elif isinstance(value, float) and not math.isfinite(value):
            bad.append(where)
    return bad


def test_published_values_are_finite(run: Run) -> None:
    bad = {(m.topic, s.stamp.seq): fields for m, s in run.decoded() if (fields := _non_finite(s))}
    assert not bad


def test_capture_time_is_set_and_not_after_publication(run: Run) -> None:
    for message, sample in run.decoded():
        capture = sample.stamp.capture_ns
        assert capture > 0, f"{message.topic} seq {sample.stamp.seq}: capture_ns {capture}"
        lead = capture - message.received_ns
        assert lead <= CAPTURE_TOLERANCE_NS, (
            f"{message.topic} seq {sample.stamp.seq}: captured {lead / 1e6:.3f} ms after it was published"
        )


def test_seq_strictly_increases_per_source(run: Run) -> None:
    seqs: dict[str, list[int]] = defaultdict(list)
    for _, sample in run.decoded():
        seqs[sample.stamp.source_id].append(sample.stamp.seq)
    for source, values in seqs.items():
        assert all(b > a for a, b in itertools.pairwise(values)), f"{source}: {values}"


def test_confidence_is_within_zero_and_one(run: Run) -> None:
    for message, sample in run.decoded():
        assert 0.0 <= sample.stamp.confidence <= 1.0, f"{message.topic}: {sample.stamp.confidence}"


def test_validator_drops_nothing_from_a_clean_stream(run: Run) -> None:
    allowed = set(run.case.allowed_drops)
    if run.frames_missed:
        allowed.add("gap")  # the transport lost frames (a stalled host): the gap is real
    unexpected = {k: v for k, v in run.dropped.items() if k not in allowed}
    assert not unexpected, f"validator dropped {unexpected} from the fake's clean stream"


# ---------------------------------------------------------------------------------------------
# Threads and stop


def test_device_thread_ends_on_stop(run: Run) -> None:
    assert run.device_threads, "start() left no thread running; where are samples produced?"
    assert not run.alive_after_stop


def test_stop_after_stop_is_a_no_op(run: Run) -> None:
    assert not run.stop_errors


def test_no_thread_outlives_the_device_and_its_peer(run: Run) -> None:
    assert not run.leaked
