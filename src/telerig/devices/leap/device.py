"""Leap Motion hand tracker device: a WebSocket client of the tracker service emitting ``HandPose``."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import threading
from collections.abc import Mapping

from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import WebSocketException

from telerig.devices.base import SampleSink
from telerig.devices.leap.protocol import (
    DESK_MOUNT,
    LeapEvent,
    LeapFrame,
    LeapHand,
    Mounting,
    ServiceVersion,
    hand_pose,
    parse_message,
)
from telerig.devices.worker import DeviceWorker
from telerig.errors import ConfigError, WireError
from telerig.ir.clock import ClockOffsetEstimator
from telerig.ir.types import Handedness, Stamp, now_ns

__all__ = ["DEFAULT_URL", "LeapDevice"]

_log = logging.getLogger(__name__)

#: The Leap service's legacy WebSocket endpoint, protocol version 6.
DEFAULT_URL = "ws://127.0.0.1:6437/v6.json"


class LeapDevice:
    """Connects to the Leap service and emits one ``HandPose`` per tracked hand per frame.

    Samples are in ``frame_id`` (the operator frame, via ``mounting``), source id
    ``"<id>/<hand>"``; ``device_ns`` = the frame's ``timestamp`` [us] x 1000 (service clock);
    ``capture_ns`` = ``device_ns`` + an offset estimated per connection as the windowed minimum of
    (arrival - device); confidence = the hand's confidence. When the service reports two hands of
    one type, the more confident one is used. After connecting, the client sends
    ``{"enableGestures": false}`` and ``{"background": <background>}`` like the official clients.
    The asyncio client runs on its own thread and reconnects every ``reconnect_s``.

    ``stats`` counts ``messages``, ``frames``, ``samples``, ``connects``, ``connect_failures``,
    ``disconnects``, ``stale``, ``events``, and drops: ``drop_malformed`` (WireError),
    ``drop_incomplete_hand``, ``drop_low_confidence``, ``drop_hand`` (hand not configured),
    ``drop_time`` (timestamp not increasing), ``drop_duplicate_hand``, ``sink_errors``.

    Args:
        id: Device id.
        url: Service WebSocket URL.
        hands: Hands to emit.
        mounting: Leap frame -> operator frame transform.
        frame_id: Name of the frame the samples are expressed in.
        min_confidence: Hands below this confidence are dropped.
        background: Ask the service for frames while the client is not the focused app.
        reconnect_s: Delay between connection attempts [s].
        open_timeout_s: WebSocket opening handshake timeout [s].
        stale_timeout_s: Reconnect after this long without a message [s].
    """

    def __init__(
        self,
        id: str = "leap0",
        *,
        url: str = DEFAULT_URL,
        hands: tuple[Handedness, ...] = ("left", "right"),
        mounting: Mounting = DESK_MOUNT,
        frame_id: str = "operator",
        min_confidence: float = 0.0,
        background: bool = True,
        reconnect_s: float = 0.5,
        open_timeout_s: float = 2.0,
        stale_timeout_s: float = 2.0,
    ) -> None:
        if not url.startswith(("ws://", "wss://")):
            raise ConfigError(f"url must start with ws:// or wss://, got {url!r}")
        if not hands or any(h not in ("left", "right") for h in hands):
            raise ConfigError(f"hands must be a non-empty subset of ('left', 'right'), got {hands!r}")
        if not 0.0 <= min_confidence <= 1.0:
            raise ConfigError(f"min_confidence must be in [0, 1], got {min_confidence}")
        for name, value in (
            ("reconnect_s", reconnect_s),
            ("open_timeout_s", open_timeout_s),
            ("stale_timeout_s", stale_timeout_s),
        ):
            if not (math.isfinite(value) and value > 0.0):
                raise ConfigError(f"{name} must be > 0 s, got {value}")
        self._id = id
        self.url = url
        self.hands = frozenset(hands)
        self.mounting = mounting
        self.frame_id = frame_id
        self.min_confidence = min_confidence
        self.background = background
        self.reconnect_s = reconnect_s
        self.open_timeout_s = open_timeout_s
        self.stale_timeout_s = stale_timeout_s
        self.service_version: ServiceVersion | None = None
        self._stats: dict[str, int] = dict.fromkeys(
            (
                "messages",
                "frames",
                "connects",
                "connect_failures",
                "disconnects",
                "stale",
                "events",
                "drop_malformed",
                "drop_incomplete_hand",
                "drop_low_confidence",
                "drop_hand",
                "drop_time",
                "drop_duplicate_hand",
            ),
            0,
        )
        self._seq: dict[Handedness, int] = {"left": 0, "right": 0}
        self._lock = threading.Lock()  # guards _stats, _loop and _task
        self._worker = DeviceWorker(id, kind="leap", thread_name=f"telerig-leap-{id}", log=_log)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._task: asyncio.Task[None] | None = None
        self._connected = threading.Event()

    @property
    def id(self) -> str:
        """Device id."""
        return self._id

    @property
    def stats(self) -> Mapping[str, int]:
        """A snapshot of the counters (see the class docstring)."""
        worker = self._worker
        with self._lock:
            stats = dict(self._stats)
        return {**stats, "samples": worker.samples - worker.sink_errors, "sink_errors": worker.sink_errors}

    @property
    def connected(self) -> bool:
        """Whether a service connection is open."""
        return self._connected.is_set()

    def start(self, sink: SampleSink) -> None:
        """Run the client on a new thread, delivering ``HandPose`` samples to ``sink``.

        Raises:
            DeviceError: If the device is already running.
        """
        started = threading.Event()
        self._worker.start(self._run, sink, started)
        started.wait(5.0)

    def stop(self) -> None:
        """Close the connection and join the thread. Idempotent."""
        self._worker.stop(wake=self._cancel)

    def _cancel(self) -> None:
        # After the stop event is set: _run either sees it or has published its loop and task here.
        with self._lock:
            loop, task = self._loop, self._task
        if loop is not None and task is not None:
            with contextlib.suppress(RuntimeError):  # the loop already finished
                loop.call_soon_threadsafe(task.cancel)

    def _count(self, key: str, n: int = 1) -> None:
        with self._lock:
            self._stats[key] += n

    def _run(self, sink: SampleSink, started: threading.Event, stop: threading.Event) -> None:
        async def main() -> None:
            with self._lock:
                self._loop = asyncio.get_running_loop()
                self._task = asyncio.current_task()
            started.set()
            if stop.is_set():
                return
            await self._main(sink, stop)

        try:
            asyncio.run(main())
        except asyncio.CancelledError:
            pass
        finally:
            started.set()
            with self._lock:
                self._loop = self._task = None

    async def _main(self, sink: SampleSink, stop: threading.Event) -> None:
        while not stop.is_set():
            try:
                async with connect(
                    self.url,
                    open_timeout=self.open_timeout_s,
                    max_size=2**22,
                    ping_interval=None,  # the service streams continuously; staleness is the liveness check
                    compression=None,
                ) as ws:
                    self._count("connects")
                    self._connected.set()
                    _log.info("%s: connected to %s", self._id, self.url)
                    try:
                        await self._session(ws, sink, stop)
                    finally:
                        if stop.is_set():
                            # Stopping (the task may be cancelled): drop the connection now rather
                            # than wait on a close handshake that cancellation can cut short,
                            # leaving the socket open until garbage collection.
                            ws.transport.abort()
            except (OSError, TimeoutError, WebSocketException) as exc:
                if self._connected.is_set():
                    self._count("disconnects")
                    _log.info("%s: connection lost (%s)", self._id, exc)
                else:
                    self._count("connect_failures")
                    _log.debug("%s: cannot connect to %s (%s)", self._id, self.url, exc)
            finally:
                self._connected.clear()
            if not stop.is_set():
                await asyncio.sleep(self.reconnect_s)

    async def _session(self, ws: ClientConnection, sink: SampleSink, stop: threading.Event) -> None:
        await ws.send(json.dumps({"enableGestures": False}))
        await ws.send(json.dumps({"background": self.background}))
        clock = ClockOffsetEstimator(window_ns=2_000_000_000)
        last_ts = -1
        while not stop.is_set():
            try:
                message = await asyncio.wait_for(ws.recv(), self.stale_timeout_s)
            except TimeoutError:
                self._count("stale")
                _log.warning("%s: no message for %.1f s; reconnecting", self._id, self.stale_timeout_s)
                return
            arrival = now_ns()
            self._count("messages")
            try:
                msg = parse_message(message)
            except WireError as exc:
                self._count("drop_malformed")
                _log.debug("%s: dropped message: %s", self._id, exc)
                continue
            if isinstance(msg, LeapFrame):
                if msg.timestamp_us <= last_ts:
                    self._count("drop_time")
                    continue
                last_ts = msg.timestamp_us
                self._deliver(msg, arrival, clock, sink)
            elif isinstance(msg, ServiceVersion):
                self.service_version = msg
                if msg.version != 6:
                    _log.warning("%s: service speaks protocol v%d, telerig expects v6", self._id, msg.version)
            elif isinstance(msg, LeapEvent):
                self._count("events")

    def _deliver(self, frame: LeapFrame, arrival: int, clock: ClockOffsetEstimator, sink: SampleSink) -> None:
        self._count("frames")
        if frame.incomplete_hands:
            self._count("drop_incomplete_hand", frame.incomplete_hands)
        device_ns = frame.timestamp_us * 1000
        capture_ns = device_ns + clock.update(device_ns, arrival)
        best: dict[Handedness, LeapHand] = {}
        for hand in frame.hands:
            if hand.handedness not in self.hands:
                self._count("drop_hand")
                continue
            if hand.confidence < self.min_confidence:
                self._count("drop_low_confidence")
                continue
            other = best.get(hand.handedness)
            if other is not None:
                self._count("drop_duplicate_hand")
                if other.confidence >= hand.confidence:
                    continue
            best[hand.handedness] = hand
        for side, hand in best.items():
            seq = self._seq[side]
            self._seq[side] = seq + 1
            stamp = Stamp(f"{self._id}/{side}", seq, device_ns, capture_ns, arrival, hand.confidence)
            self._worker.deliver(sink, hand_pose(hand, stamp, self.mounting, self.frame_id))
