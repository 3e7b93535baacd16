"""PreviewPublisher: pacing by capture time, drop-when-busy, JPEG output, topic and QoS."""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import av
import numpy as np
import pytest

from telerig.bus.base import BusStats, Message, MessageHandler, Subscription
from telerig.cameras.preview import PreviewPublisher, encode_jpeg, preview_size

T0_NS = 1_700_000_000_000_000_000
FRAME_NS = 33_333_333


class _Bus:
    """Records publishes; ``gate`` (when given) holds each publish until it is set."""

    def __init__(self, gate: threading.Event | None = None) -> None:
        self.published: list[tuple[str, bytes, int, bool]] = []
        self.gate = gate
        self.entered = threading.Event()

    @property
    def stats(self) -> BusStats:
        return BusStats()

    def publish(self, topic: str, payload: bytes, *, qos: int = 0, retain: bool = False) -> None:
        self.entered.set()
        if self.gate is not None:
            self.gate.wait(10.0)
        self.published.append((topic, payload, qos, retain))

    def subscribe(self, pattern: str, handler: MessageHandler, *, qos: int = 0) -> Subscription:
        raise NotImplementedError

    def close(self) -> None:
        pass


def _image(width: int = 640, height: int = 480) -> np.ndarray:
    y, x = np.mgrid[0:height, 0:width]
    return np.stack([x * 255 // width, y * 255 // height, (x + y) % 256], axis=-1).astype(np.uint8)


def _decode_jpeg(data: bytes) -> Any:
    context: Any = av.CodecContext.create("mjpeg", "r")
    (frame,) = context.decode(av.Packet(data))
    return frame


def test_preview_size_keeps_aspect_within_box() -> None:
    assert preview_size(640, 480, 320, 240) == (320, 240)
    assert preview_size(1280, 720, 320, 240) == (320, 180)


def test_preview_size_never_upscales() -> None:
    assert preview_size(100, 50, 320, 240) == (100, 50)


def test_encode_jpeg_gives_a_decodable_jpeg_of_the_requested_size() -> None:
    data = encode_jpeg(_image(), width=320, height=240)
    assert data[:2] == b"\xff\xd8"
    assert data[-2:] == b"\xff\xd9"
    frame = _decode_jpeg(data)
    assert (frame.width, frame.height) == (320, 240)


def test_previews_are_paced_by_capture_time() -> None:
    bus = _Bus()
    with PreviewPublisher(bus, "demo", "wrist", rate_hz=2.0) as preview:
        for i in range(30):  # one second of 30 fps
            preview.offer(_image(), T0_NS + i * FRAME_NS)
    stats = preview.stats
    # Wanted at 0 s and 0.5 s (frame 15); the rest are not due.
    assert stats.rate_skipped == 28
    assert stats.published + stats.dropped == 2


def test_wanted_frame_is_dropped_and_counted_while_worker_is_busy() -> None:
    gate = threading.Event()
    bus = _Bus(gate)
    preview = PreviewPublisher(bus, "demo", "wrist", rate_hz=2.0)
    assert preview.offer(_image(), T0_NS)
    assert bus.entered.wait(10.0)  # the worker is publishing the first preview
    assert not preview.offer(_image(), T0_NS + 1_000_000_000)
    gate.set()
    preview.close()
    assert (preview.stats.published, preview.stats.dropped) == (1, 1)


def test_preview_goes_on_the_preview_topic_at_qos0_not_retained() -> None:
    bus = _Bus()
    with PreviewPublisher(bus, "demo", "wrist", max_width=160, max_height=120) as preview:
        preview.offer(_image(), T0_NS)
    ((topic, payload, qos, retain),) = bus.published
    assert topic == "telerig/v1/demo/wrist/preview"
    assert (qos, retain) == (0, False)
    frame = _decode_jpeg(payload)
    assert (frame.width, frame.height) == (160, 120)
    assert preview.stats.last_capture_ns == T0_NS


def test_offer_after_close_is_refused() -> None:
    preview = PreviewPublisher(_Bus(), "demo", "wrist")
    preview.close()
    assert not preview.offer(_image(), T0_NS)


def test_offer_rejects_non_rgb_images() -> None:
    with pytest.raises(ValueError, match=r"uint8 of shape \(H, W, 3\)"):
        PreviewPublisher(_Bus(), "demo", "wrist").offer(np.zeros((48, 64), np.uint8), T0_NS)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"rate_hz": 0.0}, "rate_hz must be positive"),
        ({"quality": 1}, "quality must be an MJPEG qscale"),
        ({"max_width": 1}, "at least 2x2"),
    ],
)
def test_bad_preview_settings_are_refused(kwargs: dict[str, Any], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        PreviewPublisher(_Bus(), "demo", "wrist", **kwargs)


@pytest.mark.broker
def test_preview_reaches_a_subscriber_through_mosquitto(make_bus: Callable[..., Any]) -> None:
    received: list[Message] = []
    got = threading.Event()

    def handler(message: Message) -> None:
        received.append(message)
        got.set()

    make_bus("dashboard").subscribe("telerig/v1/demo/+/preview", handler)
    with PreviewPublisher(make_bus("camera"), "demo", "wrist") as preview:
        preview.offer(_image(), T0_NS)
    assert got.wait(10.0)
    assert received[0].topic == "telerig/v1/demo/wrist/preview"
    assert received[0].payload[:2] == b"\xff\xd8"
