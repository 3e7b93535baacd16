"""A local OpenAI-compatible chat-completions server for the annotation tests, and short test clips.

:class:`ChatServer` listens on 127.0.0.1 (a real HTTP server on its own threads), checks every
request's shape the way vLLM / Ollama would reject it (model, messages, ``stream: false``, text and
``image_url`` / ``video_url`` parts holding real base64 JPEG / MP4 data, the bearer key), answers
with structured JSON derived from what it received, and plays a script of injected faults: 429 with
Retry-After, 500/503, a stall past the client's timeout, a non-JSON body, an answer that violates
the schema, an oversized body, a 400 to ``response_format``. It counts requests and the most in
flight at once.
"""

from __future__ import annotations

import base64
import binascii
import json
import sys
import threading
import time
from collections import deque
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from fractions import Fraction
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import numpy as np

#: Faults a script may hold, one per request, in order; "ok" answers normally.
FAULTS = (
    "ok",
    "429",
    "500",
    "502",
    "503",
    "timeout",
    "malformed",
    "invalid",
    "oversized",
    "fenced",
    "truncated",
    "echo-key-500",
    "raw",
)


@dataclass
class Seen:
    """What one request carried (for assertions)."""

    path: str
    authorization: str | None
    body: dict[str, Any]
    images: int
    videos: int
    response_format: str
    status: int = 0
    fault: str = "ok"


@dataclass
class ChatServer:
    """Chat-completions API on 127.0.0.1; see the module docstring.

    Attributes:
        api_key: Required bearer token (``None``: none required).
        json_schema: Whether ``response_format: json_schema`` is accepted (else 400).
        json_object: Whether ``response_format: json_object`` is accepted (else 400).
        hold_s: How long each answered request stays in flight (so overlaps can be counted) [s].
        stall_s: How long a ``timeout`` fault stalls before answering [s].
        retry_after: The Retry-After header value of a ``429`` fault.
        oversized_bytes: Body size of an ``oversized`` fault [bytes].
        scene: Scene the answers name.
    """

    api_key: str | None = None
    json_schema: bool = True
    json_object: bool = True
    hold_s: float = 0.0
    stall_s: float = 2.0
    retry_after: str = "0.2"
    oversized_bytes: int = 2 << 20
    scene: str = "assembly_station"
    script: deque[str] = field(default_factory=deque)
    raw_bodies: deque[bytes] = field(default_factory=deque)
    """Bodies the ``raw`` faults answer with (200, application/json), in order."""
    seen: list[Seen] = field(default_factory=list)
    shape_errors: list[str] = field(default_factory=list)
    in_flight: int = 0
    max_in_flight: int = 0
    times: list[float] = field(default_factory=list)
    hangups: int = 0
    """Connections the client closed or reset before or while they were answered (its timeout, its
    cut-off of an oversized body, its pool closing): expected, counted, not printed."""
    _lock: threading.Lock = field(default_factory=threading.Lock)
    _httpd: ThreadingHTTPServer | None = None

    @property
    def url(self) -> str:
        assert self._httpd is not None
        return f"http://127.0.0.1:{self._httpd.server_address[1]}/v1"

    def queue(self, *faults: str) -> None:
        """Append faults for the next requests (each request takes one; then ``ok``)."""
        for f in faults:
            assert f in FAULTS, f
        with self._lock:
            self.script.extend(faults)

    def _next_fault(self) -> str:
        with self._lock:
            return self.script.popleft() if self.script else "ok"

    @contextmanager
    def running(self) -> Iterator[ChatServer]:
        server = self

        class Handler(BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"

            def log_message(self, format: str, *args: Any) -> None:
                pass

            def do_POST(self) -> None:
                server._handle(self)

        class Server(ThreadingHTTPServer):
            def handle_error(self, request: Any, client_address: Any) -> None:
                if isinstance(sys.exc_info()[1], ConnectionError):
                    with server._lock:
                        server.hangups += 1
                else:  # anything else is the fake's own bug: print it as socketserver does
                    super().handle_error(request, client_address)

        self._httpd = Server(("127.0.0.1", 0), Handler)
        self._httpd.daemon_threads = True
        thread = threading.Thread(target=self._httpd.serve_forever, kwargs={"poll_interval": 0.05})
        thread.start()
        try:
            yield self
        finally:
            self._httpd.shutdown()
            self._httpd.server_close()
            thread.join(timeout=5)

    # -- one request ------------------------------------------------------------------------------

    def _handle(self, h: BaseHTTPRequestHandler) -> None:
        with self._lock:
            self.in_flight += 1
            self.max_in_flight = max(self.max_in_flight, self.in_flight)
            self.times.append(time.monotonic())
        try:
            self._answer(h)
        except (BrokenPipeError, ConnectionResetError):
            pass  # the client gave up (timeout fault)
        finally:
            with self._lock:
                self.in_flight -= 1

    def _reply(self, h: BaseHTTPRequestHandler, status: int, body: bytes, headers: dict[str, str]) -> None:
        h.send_response(status)
        for k, v in headers.items():
            h.send_header(k, v)
        h.send_header("Content-Length", str(len(body)))
        h.end_headers()
        h.wfile.write(body)

    def _json(
        self, h: BaseHTTPRequestHandler, status: int, doc: Any, seen: Seen | None = None, **headers: str
    ) -> None:
        """Reply ``doc``; ``seen.status`` is set first, so a client that has the reply sees it there."""
        if seen is not None:
            seen.status = status
        self._reply(h, status, json.dumps(doc).encode(), {"Content-Type": "application/json", **headers})

    def _answer(self, h: BaseHTTPRequestHandler) -> None:
        length = int(h.headers.get("Content-Length", "0"))
        raw = h.rfile.read(length)
        auth = h.headers.get("Authorization")
        try:
            body = json.loads(raw)
        except ValueError:
            self.shape_errors.append("body is not JSON")
            self._json(h, 400, {"error": {"message": "body is not JSON"}})
            return
        seen = Seen(h.path, auth, body, 0, 0, "none")
        self.seen.append(seen)
        if h.path != "/v1/chat/completions":
            self._json(h, 404, {"error": {"message": f"no route {h.path}"}}, seen)
            return
        if self.api_key is not None and auth != f"Bearer {self.api_key}":
            self._json(h, 401, {"error": {"message": "invalid api key"}}, seen)
            return
        problem = self._check_shape(body, seen)
        if problem:
            self.shape_errors.append(problem)
            self._json(h, 400, {"error": {"message": problem}}, seen)
            return
        fmt = seen.response_format
        if (fmt == "json_schema" and not self.json_schema) or (fmt == "json_object" and not self.json_object):
            msg = f"response_format {fmt} is not supported"
            self._json(h, 400, {"error": {"message": msg}}, seen)
            return
        fault = seen.fault = self._next_fault()
        if self.hold_s:
            time.sleep(self.hold_s)
        if fault in ("429", "500", "502", "503", "echo-key-500"):
            status = 500 if fault == "echo-key-500" else int(fault)
            headers = {"Retry-After": self.retry_after} if fault == "429" else {}
            text = (
                f"upstream failed for request with Authorization: {auth}"
                if fault == "echo-key-500"
                else fault
            )
            self._json(h, status, {"error": {"message": text}}, seen, **headers)
            return
        if fault == "timeout":
            time.sleep(self.stall_s)
        if fault == "malformed":
            seen.status = 200
            self._reply(
                h, 200, b'{"choices": [{"message": {"content": "{\\"obj', {"Content-Type": "application/json"}
            )
            return
        if fault == "raw":
            seen.status = 200
            self._reply(h, 200, self.raw_bodies.popleft(), {"Content-Type": "application/json"})
            return
        if fault == "oversized":
            seen.status = 200
            self._reply(
                h, 200, b"{" + b" " * self.oversized_bytes + b"}", {"Content-Type": "application/json"}
            )
            return
        answer = self.describe(seen)
        if fault == "invalid":
            answer["scene"] = "spaceship"
            answer["objects"][0]["quantity"] = -3
        content = json.dumps(answer)
        if fault == "fenced":
            content = f"```json\n{content}\n```"
        finish = "stop"
        if fault == "truncated":
            content, finish = content[: len(content) // 2], "length"
        doc = {
            "id": "chatcmpl-test",
            "object": "chat.completion",
            "created": int(time.time()),
            "model": body["model"],
            "choices": [
                {"index": 0, "message": {"role": "assistant", "content": content}, "finish_reason": finish}
            ],
            "usage": {
                "prompt_tokens": 100 + 50 * (seen.images + seen.videos),
                "completion_tokens": 40,
                "total_tokens": 140 + 50 * (seen.images + seen.videos),
            },
        }
        self._json(h, 200, doc, seen)

    def describe(self, seen: Seen) -> dict[str, Any]:
        """The structured answer: one object entry whose quantity is the number of stills received."""
        return {
            "objects": [
                {"name": "red cube", "quantity": max(seen.images, 1), "attributes": ["red", "wooden"]}
            ],
            "scene": self.scene,
            "action": {
                "description": "A robot arm picks up the red cube.",
                "agent": "robot arm",
                "objects": ["red cube"],
                "interaction": "picks up",
            },
        }

    def _check_shape(self, body: Any, seen: Seen) -> str:
        """The first way ``body`` is not a valid chat-completions request with media parts, or ""."""
        if not isinstance(body, dict) or not isinstance(body.get("model"), str) or not body["model"]:
            return "model missing"
        if body.get("stream") is not False:
            return "stream must be false"
        messages = body.get("messages")
        if not isinstance(messages, list) or not messages:
            return "messages missing"
        for m in messages:
            if not isinstance(m, dict) or m.get("role") not in ("system", "user", "assistant"):
                return "bad message role"
            content = m.get("content")
            if isinstance(content, str):
                continue
            if not isinstance(content, list):
                return "content must be a string or a list of parts"
            for part in content:
                problem = self._check_part(part, seen)
                if problem:
                    return problem
        if messages[-1]["role"] != "user" or seen.images + seen.videos == 0:
            return "the last message must be the user's, with media"
        rf = body.get("response_format")
        if rf is not None:
            if not isinstance(rf, dict) or rf.get("type") not in ("json_schema", "json_object", "text"):
                return "bad response_format"
            if rf["type"] == "json_schema":
                js = rf.get("json_schema")
                if not isinstance(js, dict) or not isinstance(js.get("schema"), dict) or not js.get("name"):
                    return "json_schema needs name and schema"
            seen.response_format = rf["type"]
        return ""

    @staticmethod
    def _check_part(part: Any, seen: Seen) -> str:
        if not isinstance(part, dict):
            return "content part is not an object"
        kind = part.get("type")
        if kind == "text":
            return "" if isinstance(part.get("text"), str) else "text part without text"
        if kind not in ("image_url", "video_url"):
            return f"unknown content part {kind!r}"
        url = part.get(kind, {}).get("url") if isinstance(part.get(kind), dict) else None
        prefix = "data:image/jpeg;base64," if kind == "image_url" else "data:video/mp4;base64,"
        if not isinstance(url, str) or not url.startswith(prefix):
            return f"{kind} is not a {prefix} URL"
        try:
            data = base64.b64decode(url[len(prefix) :], validate=True)
        except binascii.Error:
            return f"{kind} is not valid base64"
        if kind == "image_url":
            if not (data[:2] == b"\xff\xd8" and data[-2:] == b"\xff\xd9" and len(data) > 200):
                return "image_url does not hold a JPEG"
            seen.images += 1
        else:
            if data[4:8] != b"ftyp":
                return "video_url does not hold an MP4"
            seen.videos += 1
        return ""


def make_clip(
    path: Path,
    *,
    seconds: float = 1.0,
    fps: int = 10,
    width: int = 160,
    height: int = 120,
    gop: int | None = None,
    b_frames: int = 0,
) -> Path:
    """A short H.264 MP4 of a moving gradient (each frame differs), written with PyAV; a keyframe
    every ``gop`` frames (``None``: x264's default, 250)."""
    import av

    frames = round(seconds * fps)
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=Fraction(fps, 1))
        stream.width, stream.height, stream.pix_fmt = width, height, "yuv420p"
        stream.options = {"preset": "ultrafast", "bf": str(b_frames)}
        if gop is not None:
            stream.options = {**stream.options, "g": str(gop), "keyint_min": str(gop), "sc_threshold": "0"}
        yy, xx = np.mgrid[0:height, 0:width]
        for i in range(frames):
            img = np.stack(
                [(xx * 2 + i * 9) % 256, (yy * 2) % 256, np.full_like(xx, (i * 23) % 256)], axis=-1
            )
            frame = av.VideoFrame.from_ndarray(img.astype(np.uint8), format="rgb24")
            for packet in stream.encode(frame):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    return path
