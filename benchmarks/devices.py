"""Device input path per family: parse + normalize time per sample, and fake-peer-to-sink latency.

Parse + normalize: the family's ``fake.typical_payload()`` through the same protocol functions
its device runs per message (decode, then conversion into IR samples), timed call by call; the
time per sample is the time per payload divided by the samples it yields. Target for pose
devices (VR, hands, mocap, markerless): p99 < 50 µs per sample. BVH is parsed once per file, so
its row is the whole shipped clip divided by its frames.

Latency, where the fake peer can send one message on demand: the time from the peer's send call
to the first sample of that message reaching the device's sink (OS transport + the device's
receive thread + parse + normalize), one message at a time.

Prints a table and writes ``benchmarks/results/devices.json``.

Usage: python benchmarks/devices.py [--seconds 0.5] [--latency-n 300] [--out PATH]
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import platform
import socket
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table

from telerig.devices.base import Device
from telerig.ir.types import ControllerState, Sample, Stamp

RESULTS = Path(__file__).parent / "results" / "devices.json"
TARGET_US = 50.0

#: One call of a family's input path on one payload; returns the number of samples produced.
Parse = Callable[[], int]


@dataclass(frozen=True)
class Family:
    """A device family's parse + normalize path.

    Attributes:
        name: Row name.
        pose: Whether it is a pose device (the 50 µs per sample target applies).
        setup: Builds the state (normalizers, payloads) and returns the timed call.
        note: What one call covers.
    """

    name: str
    pose: bool
    setup: Callable[[], Parse]
    note: str


def _stamp(source: str = "bench", confidence: float = 1.0) -> Stamp:
    return Stamp(source, 0, 1, 1, 1, confidence)


def _udp_vr() -> Parse:
    from telerig.devices.udp_vr.fake import typical_payload
    from telerig.devices.udp_vr.protocol import datagram_samples, decode_datagram

    data = typical_payload()
    return lambda: len(datagram_samples(decode_datagram(data), _stamp))


def _webxr() -> Parse:
    from telerig.devices.webxr.fake import typical_payload
    from telerig.devices.webxr.protocol import XRFrame, decode, frame_samples

    data = typical_payload()

    def run() -> int:
        frame = decode(data)
        assert isinstance(frame, XRFrame)
        return len(frame_samples(frame, "xr0", frame.client_ns, lambda _sid: 0))

    return run


def _glove() -> Parse:
    from telerig.devices.glove.fake import typical_payload
    from telerig.devices.glove.kinematics import HandModel, glove_hand_pose
    from telerig.devices.glove.protocol import GloveStreamDecoder

    data = typical_payload()
    decoder = GloveStreamDecoder()
    model = HandModel.default()

    def run() -> int:
        frames = decoder.feed(data)
        for frame in frames:
            glove_hand_pose(frame, model, _stamp())
        return len(frames)

    return run


def _leap() -> Parse:
    from telerig.devices.leap.fake import typical_payload
    from telerig.devices.leap.protocol import DESK_MOUNT, LeapFrame, hand_pose, parse_message

    data = typical_payload()

    def run() -> int:
        frame = parse_message(data)
        assert isinstance(frame, LeapFrame)
        return len([hand_pose(h, _stamp(), DESK_MOUNT) for h in frame.hands])

    return run


def _natnet() -> Parse:
    from telerig.devices.mocap.fake import FakeNatNetServer, typical_payload
    from telerig.devices.mocap.protocol import (
        FrameNormalizer,
        MocapFrame,
        NatNetVersion,
        parse_message,
    )

    data = typical_payload()
    version = NatNetVersion(4, 1)
    normalizer = FrameNormalizer("mc")
    normalizer.set_models(FakeNatNetServer().models)

    def run() -> int:
        frame = parse_message(data, version)
        assert isinstance(frame, MocapFrame)
        return len(normalizer.normalize(frame, 1, 1)[0])

    return run


def _bvh() -> Parse:
    from telerig.devices.mocap._axes import MountTransform
    from telerig.devices.mocap.bvh import detect_scale, parse_bvh
    from telerig.devices.mocap.fake import sample_bvh_path

    text = sample_bvh_path().read_text()

    def run() -> int:
        clip = parse_bvh(text)
        return len(clip.skeletons("bvh0/body", mount=MountTransform(scale=detect_scale(clip))))

    return run


def _markerless_hand() -> Parse:
    from telerig.devices.markerless.fake import typical_payload
    from telerig.devices.markerless.protocol import HandMessage, decode, hand_pose

    data = typical_payload()

    def run() -> int:
        msg = decode(data)
        assert isinstance(msg, HandMessage)
        hand_pose(msg, _stamp(), "hand")
        return 1

    return run


def _markerless_body() -> Parse:
    from telerig.devices.markerless.fake import FakeTracker
    from telerig.devices.markerless.protocol import PoseMessage, body_skeleton, decode

    with FakeTracker(("127.0.0.1", 9)) as fake:
        data = fake.pose_bytes(1, capture_ns=1_700_000_000_000_000_000)

    def run() -> int:
        msg = decode(data)
        assert isinstance(msg, PoseMessage)
        body_skeleton(msg, _stamp(), "hips")
        return 1

    return run


def _spacemouse() -> Parse:
    from telerig.devices.spacemouse.fake import typical_payload
    from telerig.devices.spacemouse.protocol import SpaceMouseNormalizer, parse_report

    data = typical_payload()
    normalizer = SpaceMouseNormalizer("sm")
    return lambda: int(normalizer.feed(parse_report(data), 1, 1) is not None)


def _gamepad() -> Parse:
    from telerig.devices.gamepad.fake import report, typical_payload
    from telerig.devices.gamepad.protocol import GamepadNormalizer, parse_events

    # Alternate two reports: the normalizer emits only what changed, as on a moving stick.
    payloads = itertools.cycle(
        (
            typical_payload(),
            report(1_700_000_000_133_456_000, {"x": -9000, "y": 15000, "rx": 2000, "rz": 100}),
        )
    )
    normalizer = GamepadNormalizer("gp")

    def run() -> int:
        return sum(len(normalizer.feed(e, 1)) for e in parse_events(next(payloads)))

    return run


def _keyboard() -> Parse:
    from telerig.devices.keyboard.fake import typical_payload
    from telerig.devices.keyboard.protocol import KeyboardNormalizer, KeyDecoder

    data = typical_payload()
    decoder = KeyDecoder()
    normalizer = KeyboardNormalizer("kb")
    t = itertools.count(1_000_000_000, 10_000_000)

    def run() -> int:
        now = next(t)
        for key in decoder.feed(data):
            normalizer.press(key, now)
        normalizer.twist(now)
        return 1 + int(normalizer.controller(now) is not None)

    return run


FAMILIES: tuple[Family, ...] = (
    Family("udp_vr", True, _udp_vr, "VrFrame datagram: head, 2 controllers, 2 hands"),
    Family("webxr", True, _webxr, "page frame: head, 2 controllers, 2 hands"),
    Family("glove", True, _glove, "TCP frame via the stream decoder -> HandPose (FK)"),
    Family("leap", True, _leap, "v6 JSON frame -> 2 HandPose"),
    Family("natnet", True, _natnet, "NatNet 4.1 frame -> 5 Pose + 21-bone skeleton"),
    Family("bvh", True, _bvh, "whole shipped clip (180 frames) -> BodySkeleton per frame"),
    Family("markerless hand", True, _markerless_hand, "hand datagram -> HandPose"),
    Family("markerless body", True, _markerless_body, "pose datagram -> BodySkeleton"),
    Family("spacemouse", False, _spacemouse, "six-axis report -> Twist"),
    Family("gamepad", False, _gamepad, "evdev read (5 records) -> Twist + ControllerState"),
    Family("keyboard", False, _keyboard, "key read -> Twist (+ ControllerState on change)"),
)


def measure_parse(family: Family, seconds: float) -> dict[str, Any]:
    """Time ``family``'s parse path call by call for about ``seconds`` (after a warm-up)."""
    run = family.setup()
    for _ in range(50):
        run()
    times: list[int] = []
    counts: list[int] = []
    clock = time.perf_counter_ns
    deadline = time.perf_counter() + seconds
    while time.perf_counter() < deadline or len(times) < 20:
        t0 = clock()
        n = run()
        times.append(clock() - t0)
        counts.append(n)
    payload_us = np.array(times) / 1e3
    per_sample = payload_us / np.maximum(np.array(counts), 1)
    return {
        "calls": len(times),
        "samples_per_payload": float(np.mean(counts)),
        "payload_us_p50": float(np.percentile(payload_us, 50)),
        "payload_us_p99": float(np.percentile(payload_us, 99)),
        "sample_us_p50": float(np.percentile(per_sample, 50)),
        "sample_us_p99": float(np.percentile(per_sample, 99)),
    }


# ---------------------------------------------------------------------------------------------
# Latency: fake peer send -> first sample of that message in the sink


class _FirstArrival:
    """A sink that records when the first matching sample after :meth:`arm` arrives."""

    def __init__(self, accept: Callable[[Sample], bool] = lambda s: True) -> None:
        self.accept = accept
        self.at = 0
        self.event = threading.Event()

    def arm(self) -> None:
        self.at = 0
        self.event.clear()

    def __call__(self, sample: Sample) -> None:
        if not self.event.is_set() and self.accept(sample):
            self.at = time.perf_counter_ns()
            self.event.set()


def _round_trips(sink: _FirstArrival, sends: Iterator[Callable[[], None]], n: int) -> list[float]:
    """Latencies [µs] of ``n`` sends, one at a time, with a pause between them."""
    out: list[float] = []
    misses = 0
    for send in itertools.islice(sends, n + 20):
        sink.arm()
        t0 = time.perf_counter_ns()
        send()
        if sink.event.wait(0.25):
            out.append((sink.at - t0) / 1e3)
        else:
            misses += 1
        time.sleep(0.002)
    if misses > n // 10:
        raise RuntimeError(f"{misses} sends never reached the sink")
    return out[20:]  # the first ones include connection set-up and clock-offset learning


@contextlib.contextmanager
def _running(device: Device, sink: _FirstArrival) -> Iterator[Device]:
    device.start(sink)
    try:
        yield device
    finally:
        device.stop()


def _lat_udp_vr(n: int, tmp: Path) -> list[float]:
    from telerig.devices.udp_vr.device import UdpVrDevice
    from telerig.devices.udp_vr.fake import FakeVrSender

    sink = _FirstArrival()
    with _running(UdpVrDevice("vr0", port=0), sink) as dev, FakeVrSender(dev.address[1]) as sender:  # type: ignore[attr-defined]
        frames = [sender.datagram(k / 90.0, seq=k, device_ns=time.monotonic_ns()) for k in range(n + 20)]
        return _round_trips(sink, (lambda d=d: sender.send(d) for d in frames), n)


def _lat_webxr(n: int, tmp: Path) -> list[float]:
    # The device alone, fed as telerig serve's relay feeds it (LocalRelay, in-process): the
    # server's WebSocket and the bus hop to the station are not in this number.
    from telerig.devices.webxr.device import WebXRDevice
    from telerig.devices.webxr.fake import LocalRelay, XRControllerInput, XRHandInput, encode_frame

    sink = _FirstArrival()
    dev = WebXRDevice("xr0")
    relay = LocalRelay(dev)
    with _running(dev, sink):
        page = relay.open()
        hand = XRHandInput.flat()

        def send(k: int) -> None:
            page.send(
                encode_frame(
                    k,
                    relay.now_ms(),
                    head=((0.0, 1.6, 0.0), (0.0, 0.0, 0.0, 1.0)),
                    left=XRControllerInput(),
                    right=XRControllerInput(),
                    left_hand=hand,
                    right_hand=hand,
                )
            )

        return _round_trips(sink, (lambda k=k: send(k) for k in itertools.count()), n)


def _lat_markerless(n: int, tmp: Path) -> list[float]:
    from telerig.devices.markerless.device import MarkerlessDevice
    from telerig.devices.markerless.fake import FakeTracker

    sink = _FirstArrival()
    with _running(MarkerlessDevice("cam0"), sink) as dev, FakeTracker(dev.address) as fake:  # type: ignore[attr-defined]
        messages = [fake.hand_bytes(k + 1) for k in range(n + 20)]
        return _round_trips(sink, (lambda m=m: fake.send(m) for m in messages), n)


def _lat_glove(n: int, tmp: Path) -> list[float]:
    from telerig.devices.glove.device import GloveDevice
    from telerig.devices.glove.fake import FakeGloveBridge
    from telerig.devices.glove.protocol import encode_frame

    # A bridge that sends one frame on demand (the fake one streams on its own clock).
    server = socket.create_server(("127.0.0.1", 0))
    bridge = FakeGloveBridge()
    frames = [
        encode_frame(bridge.frame_at(k / 120.0, seq=k, device_ns=1_000_000 * (k + 1))) for k in range(n + 20)
    ]
    sink = _FirstArrival()
    with server, _running(GloveDevice("glove0", port=server.getsockname()[1], gestures=False), sink):
        server.settimeout(5.0)
        conn, _ = server.accept()
        with conn:
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            return _round_trips(sink, (lambda f=f: conn.sendall(f) for f in frames), n)


def _lat_spacemouse(n: int, tmp: Path) -> list[float]:
    from telerig.devices.spacemouse.device import SpaceMouseDevice
    from telerig.devices.spacemouse.fake import FakeSpaceMouse

    path = tmp / "hidraw0"
    sink = _FirstArrival()
    with (
        FakeSpaceMouse(path) as fake,
        _running(SpaceMouseDevice("sm", path=str(path), layout="combined"), sink),
    ):
        fake.connect()
        sends = (lambda k=k: fake.motion(k % 300, 0, 0, 0, 0, 0) for k in itertools.count())
        return _round_trips(sink, sends, n)


def _lat_gamepad(n: int, tmp: Path) -> list[float]:
    from telerig.devices.gamepad.device import GamepadDevice
    from telerig.devices.gamepad.fake import FakeGamepad

    path = tmp / "event0"
    sink = _FirstArrival()
    with FakeGamepad(path) as fake, _running(GamepadDevice("gp", path=str(path)), sink):
        fake.connect()
        sends = (lambda k=k: fake.send({"x": 10_000 + 100 * (k % 100)}) for k in itertools.count())
        return _round_trips(sink, sends, n)


def _lat_keyboard(n: int, tmp: Path) -> list[float]:
    from telerig.devices.keyboard.device import KeyboardDevice
    from telerig.devices.keyboard.fake import FakeTerminal

    # Digits pick the mode: pressing 1, 2, 1, ... makes every press a ControllerState (Twists
    # tick on their own; a key pressed again at once would count as its auto-repeat).
    sink = _FirstArrival(lambda s: isinstance(s, ControllerState))
    with FakeTerminal() as term, _running(KeyboardDevice("kb", path=term.slave_name), sink):
        time.sleep(0.05)  # the first tick emits the initial ControllerState
        keys = itertools.cycle((b"2", b"1"))
        return _round_trips(sink, (lambda k=k: term.write(k) for k in keys), n)


LATENCY: dict[str, Callable[[int, Path], list[float]]] = {
    "udp_vr": _lat_udp_vr,
    "webxr": _lat_webxr,
    "glove": _lat_glove,
    "markerless hand": _lat_markerless,
    "spacemouse": _lat_spacemouse,
    "gamepad": _lat_gamepad,
    "keyboard": _lat_keyboard,
}
#: Why the other families have no latency row.
NO_LATENCY = {
    "leap": "fake service streams on its own clock",
    "natnet": "fake server streams on its own clock",
    "bvh": "file playback, no peer",
    "markerless body": "same path as the hand datagram",
}


def main(argv: Sequence[str] | None = None) -> None:
    """Run both benchmarks, print the table and write :data:`RESULTS`."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=0.5, help="timing per family [s] (default 0.5)")
    parser.add_argument("--latency-n", type=int, default=300, help="messages per latency run (default 300)")
    parser.add_argument("--out", type=Path, default=RESULTS, help=f"JSON results (default {RESULTS})")
    args = parser.parse_args(argv)
    console = Console(width=None if sys.stdout.isatty() else 130)
    rows = []
    with tempfile.TemporaryDirectory() as tmp, console.status("measuring") as status:
        for family in FAMILIES:
            status.update(f"parse + normalize: {family.name}")
            row: dict[str, Any] = {"family": family.name, "pose": family.pose, "covers": family.note}
            row.update(measure_parse(family, args.seconds))
            row["target_us"] = TARGET_US if family.pose else None
            row["meets_target"] = row["sample_us_p99"] < TARGET_US if family.pose else None
            lat = LATENCY.get(family.name)
            if lat is not None:
                status.update(f"latency: {family.name}")
                us = np.array(lat(args.latency_n, Path(tmp)))
                row.update(
                    latency_us_p50=float(np.percentile(us, 50)), latency_us_p99=float(np.percentile(us, 99))
                )
                row["latency_n"] = len(us)
            else:
                row["latency_note"] = NO_LATENCY[family.name]
            rows.append(row)
    table = Table(title="Device input path: parse + normalize per sample, and fake peer send -> sink")
    for col in (
        "family",
        "samples / msg",
        "µs/sample p50",
        "µs/sample p99",
        "target",
        "meets",
        "send→sink µs p50",
        "p99",
    ):
        table.add_column(col, justify="left" if col == "family" else "right")
    for r in rows:
        meets = (
            "—"
            if r["meets_target"] is None
            else "[green]yes[/green]"
            if r["meets_target"]
            else "[red]no[/red]"
        )
        table.add_row(
            r["family"],
            f"{r['samples_per_payload']:.1f}",
            f"{r['sample_us_p50']:.1f}",
            f"{r['sample_us_p99']:.1f}",
            f"< {TARGET_US:.0f} µs" if r["pose"] else "—",
            meets,
            f"{r['latency_us_p50']:.0f}" if "latency_us_p50" in r else "—",
            f"{r['latency_us_p99']:.0f}" if "latency_us_p99" in r else "—",
        )
    console.print(table)
    console.print(f"target: p99 per sample < {TARGET_US:.0f} µs for pose devices; '—' latency: {NO_LATENCY}")
    args.out.parent.mkdir(exist_ok=True)
    meta = {"python": platform.python_version(), "machine": platform.machine(), "seconds": args.seconds}
    args.out.write_text(json.dumps({"meta": meta, "rows": rows}, indent=2))
    console.print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
