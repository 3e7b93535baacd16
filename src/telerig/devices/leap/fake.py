"""A fake Leap Motion service: a local WebSocket server speaking the legacy v6 JSON protocol (test aid)."""

from __future__ import annotations

import asyncio
import json
import logging
import math
import time
from collections.abc import Callable
from types import TracebackType
from typing import Any

import numpy as np
from websockets.asyncio.server import ServerConnection, serve
from websockets.datastructures import Headers
from websockets.exceptions import ConnectionClosed
from websockets.http11 import Request, Response

from telerig.bus.peer_loop import PeerLoop
from telerig.errors import ConfigError, DeviceError
from telerig.ir.types import FloatArray, Handedness

__all__ = ["SERVICE_VERSION", "FakeLeapService", "synthetic_frame", "typical_payload"]

_log = logging.getLogger(__name__)

SERVICE_VERSION = "2.3.1+33747"

# Right-hand geometry in the hand frame [mm] (x toward the fingers, y left, z dorsal; wrist origin).
_CARP = ((20.0, 15.0, -8.0), (12.0, 12.0, 0.0), (12.0, 2.0, 0.0), (12.0, -8.0, 0.0), (12.0, -18.0, 0.0))
_MCP = ((28.0, 20.0, -12.0), (92.0, 24.0, 0.0), (94.0, 3.0, 0.0), (88.0, -16.0, -2.0), (80.0, -34.0, -5.0))
_LEN = ((46.0, 32.0, 27.0), (42.0, 25.0, 20.0), (46.0, 28.0, 21.0), (43.0, 27.0, 21.0), (34.0, 20.0, 19.0))
_YAW = (0.75, 0.08, 0.0, -0.08, -0.18)
_PALM_OFFSET_MM = 55.0  # palm centre ahead of the wrist


def _rot_y(a: float) -> FloatArray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rot_x(a: float) -> FloatArray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


# Hand frame -> Leap frame at rest: fingers toward -z (away from the user), back of the hand up,
# hand-frame y (left) -> Leap -x.
_REST = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]])


def _vec(v: FloatArray) -> list[float]:
    return [round(float(x), 4) for x in v]


def synthetic_hand(hand: Handedness, t_s: float, hand_id: int) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """One smooth synthetic hand at ``t_s``: its ``hands`` entry and its five ``pointables`` (v6 fields)."""
    side = 1.0 if hand == "right" else -1.0
    mirror = np.diag([1.0, side, 1.0])
    # Palm circles 150..250 mm above the device, 80 mm to the hand's side; wrist sways.
    centre = np.array([side * 80.0 + 40.0 * math.cos(0.8 * t_s), 200.0 + 50.0 * math.sin(0.8 * t_s), 20.0])
    rot = _REST @ _rot_y(0.25 * math.sin(0.5 * t_s)) @ _rot_x(side * 0.3 * math.sin(0.35 * t_s))
    curl = 0.5 - 0.5 * math.cos(2.0 * math.pi * 0.25 * t_s)  # 0 open .. 1 fist, 4 s period
    wrist = centre - rot @ np.array([_PALM_OFFSET_MM, 0.0, 0.0])

    def to_leap(p: FloatArray) -> FloatArray:
        out: FloatArray = wrist + rot @ (mirror @ p)
        return out

    pointables = []
    for f in range(5):
        flex = (0.5 * curl, 0.4 * curl, 0.3 * curl) if f == 0 else (1.4 * curl, 1.6 * curl, 0.9 * curl)
        yaw = _YAW[f]
        base = np.array(_MCP[f])
        joints = [base]
        c = 0.0
        p = base.copy()
        for length, a in zip(_LEN[f], flex, strict=True):
            c += a
            p = p + length * np.array(
                [math.cos(yaw) * math.cos(c), math.sin(yaw) * math.cos(c), -math.sin(c)]
            )
            joints.append(p)
        carp = np.array(_CARP[f]) if f else base  # the thumb's metacarpal has zero length
        leap = [to_leap(j) for j in (carp, *joints)]
        tip_dir = (leap[4] - leap[3]) / np.linalg.norm(leap[4] - leap[3])
        basis = [_vec(rot[:, 0]), _vec(rot[:, 1]), _vec(rot[:, 2])]
        pointables.append(
            {
                "bases": [basis] * 4,
                "btipPosition": _vec(leap[4]),
                "carpPosition": _vec(leap[0]),
                "dipPosition": _vec(leap[3]),
                "direction": _vec(tip_dir),
                "extended": curl < 0.4,
                "handId": hand_id,
                "id": hand_id * 10 + f,
                "length": sum(_LEN[f]),
                "mcpPosition": _vec(leap[1]),
                "pipPosition": _vec(leap[2]),
                "timeVisible": round(t_s, 4),
                "tipPosition": _vec(leap[4]),
                "type": f,
                "width": 18.0,
            }
        )
    normal = -rot[:, 2]
    entry = {
        "armBasis": [_vec(rot[:, 0]), _vec(rot[:, 1]), _vec(rot[:, 2])],
        "armWidth": 60.0,
        "confidence": round(0.9 + 0.1 * math.sin(t_s), 4),
        "direction": _vec(rot[:, 0]),
        "elbow": _vec(wrist - rot[:, 0] * 250.0),
        "grabAngle": round(curl * math.pi, 4),
        "grabStrength": round(curl, 4),
        "id": hand_id,
        "palmNormal": _vec(normal),
        "palmPosition": _vec(centre),
        "palmVelocity": [0.0, 0.0, 0.0],
        "palmWidth": 85.0,
        "pinchDistance": 40.0,
        "pinchStrength": round(curl, 4),
        "timeVisible": round(t_s, 4),
        "type": hand,
        "wrist": _vec(wrist),
    }
    return entry, pointables


def synthetic_frame(
    t_s: float, frame_id: int, timestamp_us: int, hands: tuple[Handedness, ...] = ("left", "right")
) -> dict[str, Any]:
    """A complete v6 frame object with smooth synthetic hands at ``t_s`` seconds."""
    hand_entries = []
    pointables: list[dict[str, Any]] = []
    for i, hand in enumerate(hands):
        entry, fingers = synthetic_hand(hand, t_s, 100 + i)
        hand_entries.append(entry)
        pointables.extend(fingers)
    return {
        "currentFrameRate": 110.0,
        "devices": [],
        "gestures": [],
        "hands": hand_entries,
        "id": frame_id,
        "interactionBox": {"center": [0.0, 200.0, 0.0], "size": [235.2, 235.2, 147.7]},
        "pointables": pointables,
        "timestamp": timestamp_us,
    }


_GARBAGE = (
    "{not json",
    '{"id": 1, "timestamp": 5, "hands": [{"id": 1, "type": "middle"}], "pointables": []}',
    '{"id": 1, "timestamp": NaN, "hands": [], "pointables": []}',
    "[1, 2, 3]",
)


class FakeLeapService:
    """A Leap service on ``ws://127.0.0.1:<port>/v6.json`` streaming smooth synthetic hands.

    Sends the version message, then frames at ``rate_hz``; records what clients send in
    :attr:`received`. Faults for tests: ``garbage_every`` sends a malformed message after every
    N-th frame; ``disconnect_after`` closes each connection after N frames.

    Args:
        hands: Hands in every frame.
        rate_hz: Frame rate [Hz].
        port: TCP port (0 picks a free one; read :attr:`port`).
    """

    def __init__(
        self,
        *,
        hands: tuple[Handedness, ...] = ("left", "right"),
        rate_hz: float = 110.0,
        port: int = 0,
        garbage_every: int = 0,
        disconnect_after: int = 0,
    ) -> None:
        if not (math.isfinite(rate_hz) and 0.0 < rate_hz <= 1000.0):
            raise ConfigError(f"rate_hz must be in (0, 1000], got {rate_hz}")
        self.hands = hands
        self.rate_hz = rate_hz
        self.garbage_every = garbage_every
        self.disconnect_after = disconnect_after
        self._requested_port = port
        self._port = 0
        self._peer = PeerLoop(
            self._main, what="fake Leap service", thread_name="telerig-fake-leap", error=DeviceError
        )
        self.received: list[Any] = []
        self.frames_sent = 0
        self.connections = 0
        self._t0 = time.monotonic_ns()

    @property
    def port(self) -> int:
        """The listening port (valid after :meth:`start`)."""
        if not self._port:
            raise ConfigError("the fake Leap service is not started; call start() first")
        return self._port

    @property
    def url(self) -> str:
        """WebSocket URL a client connects to."""
        return f"ws://127.0.0.1:{self.port}/v6.json"

    def start(self) -> FakeLeapService:
        """Serve from a background thread; returns once listening. Idempotent.

        Raises:
            DeviceError: the server failed to start (e.g. its port is taken).
        """
        self._peer.start()
        return self

    def stop(self) -> None:
        """Close the server and all connections; idempotent."""
        self._peer.stop()
        self._port = 0

    def __enter__(self) -> FakeLeapService:
        return self.start()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()

    async def _main(self, ready: Callable[[], None], done: asyncio.Event) -> None:
        async with serve(
            self._handle, "127.0.0.1", self._requested_port, process_request=self._check_path
        ) as server:
            self._port = next(iter(server.sockets)).getsockname()[1]
            ready()
            await done.wait()

    @staticmethod
    def _check_path(connection: ServerConnection, request: Request) -> Response | None:
        if request.path.split("?")[0] not in ("/v6.json", "/"):
            return Response(404, "Not Found", Headers(), b"unknown protocol version path\n")
        return None

    async def _handle(self, ws: ServerConnection) -> None:
        self.connections += 1
        reader = asyncio.create_task(self._read(ws))
        try:
            await ws.send(json.dumps({"serviceVersion": SERVICE_VERSION, "version": 6}))
            period = 1.0 / self.rate_hz
            start = time.perf_counter()
            k = 0
            while True:
                delay = start + k * period - time.perf_counter()
                if delay > 0.0:
                    await asyncio.sleep(delay)
                t_s = k * period
                ts_us = (time.monotonic_ns() - self._t0) // 1000
                await ws.send(json.dumps(synthetic_frame(t_s, k + 1, ts_us, self.hands)))
                self.frames_sent += 1
                k += 1
                if self.garbage_every and k % self.garbage_every == 0:
                    await ws.send(_GARBAGE[(k // self.garbage_every) % len(_GARBAGE)])
                if self.disconnect_after and k >= self.disconnect_after:
                    await ws.close()
                    return
        except ConnectionClosed:
            return
        finally:
            reader.cancel()

    async def _read(self, ws: ServerConnection) -> None:
        try:
            async for message in ws:
                try:
                    self.received.append(json.loads(message))
                except ValueError:
                    self.received.append(message)
        except ConnectionClosed:
            return


def typical_payload() -> bytes:
    """One typical v6 frame with both hands, as UTF-8 JSON bytes."""
    return json.dumps(synthetic_frame(1.7, 187, 1_234_567_890)).encode()
