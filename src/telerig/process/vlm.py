"""A client for OpenAI-compatible chat-completions APIs that describes a clip as validated JSON.

Speaks ``POST {url}/chat/completions`` (vLLM, Ollama, Qwen-VL's compatible endpoint) with the
clip as base64 ``image_url`` stills or one ``video_url`` part, streaming off, and asks for
:class:`ClipDescription` through a JSON-schema ``response_format``; a server that answers 400 to
that gets ``json_object``, then the prompt alone. Every answer is validated against the same
pydantic model the schema is generated from. Built on ``httpx2`` (the HTTP client the project
already pins) rather than the ``openai`` package: ten lines of request building replace a large
SDK whose own retry loop would hide the retry and usage counts the pipeline reports.

Failures of one clip are returned, not raised (:class:`Completion` ``.error``, one line): the
pipeline records them and goes on. The API key is sent only in the ``Authorization`` header and
is redacted from every message this module logs or returns.
"""

from __future__ import annotations

import base64
import contextlib
import email.utils
import fcntl
import hashlib
import importlib
import json
import logging
import os
import random
import re
import threading
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, StringConstraints, ValidationError

from telerig.config.process import SCENE_TYPES, AnnotateSettings, SceneType
from telerig.errors import DependencyError, ProcessError

if TYPE_CHECKING:
    import httpx2

__all__ = [
    "PROMPT_VERSION",
    "RESPONSE_SCHEMA",
    "ActionDescription",
    "ClipDescription",
    "Completion",
    "EndpointLimiter",
    "ObjectEntry",
    "VlmClient",
    "cache_key",
    "image_part",
    "video_part",
]

_log = logging.getLogger("telerig.process.vlm")

PROMPT_VERSION = "1"
"""Bump when the prompt or the schema changes: it is part of every cache key."""

_RETRY_STATUS = frozenset({429, 500, 502, 503, 504})
_AUTH_STATUS = frozenset({401, 403})
_Name = Annotated[str, StringConstraints(strip_whitespace=True, min_length=1, max_length=120)]
_Attribute = Annotated[str, StringConstraints(strip_whitespace=True, min_length=1, max_length=120)]


class ObjectEntry(BaseModel):
    """One kind of object seen in the clip."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: _Name
    quantity: int = Field(ge=0, le=10_000)
    """How many are visible [1]."""
    attributes: list[_Attribute] = Field(max_length=16)
    """Key attributes: colour, material, state (``red``, ``plastic``, ``open``)."""


class ActionDescription(BaseModel):
    """What happens in the clip, in words."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    description: Annotated[str, StringConstraints(strip_whitespace=True, min_length=1, max_length=1000)]
    agent: Annotated[str, StringConstraints(strip_whitespace=True, min_length=1, max_length=200)]
    """Who acts: ``a robot arm``, ``a person's right hand``."""
    objects: list[_Name] = Field(max_length=32)
    """The objects acted on."""
    interaction: Annotated[str, StringConstraints(strip_whitespace=True, min_length=1, max_length=200)]
    """The verb phrase: ``picks up``, ``screws in``, ``wipes``."""


class ClipDescription(BaseModel):
    """The structured answer asked of the model for each clip (its JSON schema is sent along)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    objects: list[ObjectEntry] = Field(max_length=64)
    scene: SceneType
    action: ActionDescription


RESPONSE_SCHEMA: dict[str, Any] = ClipDescription.model_json_schema()

_SYSTEM_PROMPT = (
    "You annotate short video clips for a robot-learning dataset. Answer with one JSON object and "
    "nothing else, matching this JSON schema:\n"
    + json.dumps(RESPONSE_SCHEMA, separators=(",", ":"))
    + "\nobjects: every distinct kind of object that is handled or clearly visible, with how many "
    "and up to a few key attributes (colour, material, state). scene: one of "
    + ", ".join(SCENE_TYPES)
    + ". action: one sentence of what happens (description), who acts (agent), the objects acted "
    "on (objects) and the interaction as a short verb phrase."
)


def image_part(jpeg: bytes) -> dict[str, Any]:
    """A chat content part carrying one JPEG still as a base64 data URL."""
    url = "data:image/jpeg;base64," + base64.b64encode(jpeg).decode("ascii")
    return {"type": "image_url", "image_url": {"url": url}}


def video_part(mp4: bytes) -> dict[str, Any]:
    """A chat content part carrying a whole MP4 clip as a base64 data URL (vLLM / Qwen-VL)."""
    url = "data:video/mp4;base64," + base64.b64encode(mp4).decode("ascii")
    return {"type": "video_url", "video_url": {"url": url}}


@dataclass(frozen=True)
class Completion:
    """The outcome of describing one clip: an answer or a one-line reason, and what it cost."""

    description: ClipDescription | None
    error: str = ""
    """One line, empty on success."""
    prompt_tokens: int = 0
    """Summed over every attempt the server billed (``usage.prompt_tokens``) [tokens]."""
    completion_tokens: int = 0
    requests: int = 0
    """HTTP requests sent for this clip, retries included [1]."""
    retries: int = 0
    """Requests repeated after a retryable status, timeout or invalid answer [1]."""
    backoff_s: float = 0.0
    """Time slept before retries [s]."""
    response_format: str = ""
    """The ``response_format`` type of the last request (``json_schema`` | ``json_object`` | ``none``)."""


class EndpointLimiter:
    """Concurrency and request-rate limits for one endpoint, shared by every process on this host.

    The pipeline runs items on a process pool (or Dask workers), each with its own client, so an
    in-process semaphore would multiply the limit by the number of workers. Slots are ``flock``
    locks on files in ``directory`` (one per allowed request in flight); the rate is a "next free
    time" stamp in a file updated under a lock, which spaces requests evenly.

    Args:
        directory: Where the lock files live (created); one directory per endpoint.
        concurrency: Requests in flight at once [1].
        requests_per_minute: Request rate [1/min].
    """

    def __init__(self, directory: Path, concurrency: int, requests_per_minute: float) -> None:
        if concurrency < 1 or requests_per_minute <= 0:
            raise ValueError("concurrency must be >= 1 and requests_per_minute > 0")
        self._dir = Path(directory)
        self._concurrency = concurrency
        self._interval_s = 60.0 / requests_per_minute

    @contextlib.contextmanager
    def slot(self) -> Iterator[None]:
        """Hold one of the ``concurrency`` slots (blocks, polling every few ms, until one is free)."""
        self._dir.mkdir(parents=True, exist_ok=True)
        while True:
            for i in range(self._concurrency):
                fd = os.open(self._dir / f"slot-{i}.lock", os.O_CREAT | os.O_RDWR, 0o644)
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except BlockingIOError:
                    os.close(fd)
                    continue
                try:
                    yield
                finally:
                    fcntl.flock(fd, fcntl.LOCK_UN)
                    os.close(fd)
                return
            time.sleep(0.005 + random.random() * 0.01)

    def wait_turn(self) -> None:
        """Sleep until this host's next request may start at the configured rate."""
        self._dir.mkdir(parents=True, exist_ok=True)
        fd = os.open(self._dir / "rate", os.O_CREAT | os.O_RDWR, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
            raw = os.pread(fd, 64, 0)
            try:
                next_free = float(raw.decode("ascii")) if raw else 0.0
            except ValueError:
                next_free = 0.0
            now = time.time()
            start = max(now, min(next_free, now + self._interval_s * 1000))
            stamp = f"{start + self._interval_s:.6f}".encode("ascii").ljust(32)
            os.pwrite(fd, stamp, 0)
        finally:
            os.close(fd)  # releases the lock
        if start > now:
            time.sleep(start - now)


class _Secret:
    """A string that never shows in a repr or a traceback's locals (``value`` reads it)."""

    __slots__ = ("value",)

    def __init__(self, value: str) -> None:
        self.value = value

    def __repr__(self) -> str:
        return "_Secret('***')"


class _OversizedError(Exception):
    pass


_NO_REPLY = -1
"""Status of a request that got no answer (timeout, refused or dropped connection)."""
_OVERSIZED = -2
"""Status of an answer cut off at ``max_response_mb``."""


@dataclass(frozen=True)
class _Reply:
    status: int
    headers: dict[str, str]
    raw: bytes
    reason: str = ""


@dataclass
class _Tally:
    prompt_tokens: int = 0
    completion_tokens: int = 0
    requests: int = 0
    retries: int = 0
    backoff_s: float = 0.0


class VlmClient:
    """Describes clips through one OpenAI-compatible endpoint; thread-safe (call from a pool).

    Args:
        settings: The endpoint, model, limits and retry policy (``settings.model`` must be set).
        limits_dir: Directory of the host-wide :class:`EndpointLimiter` for this endpoint.
        api_key: Bearer token; default: the environment variable ``settings.api_key_env``.
        rng: Jitter source (tests may seed it).
    """

    def __init__(
        self,
        settings: AnnotateSettings,
        *,
        limits_dir: Path,
        api_key: str | None = None,
        rng: random.Random | None = None,
    ) -> None:
        if settings.model is None or settings.url is None:
            raise ProcessError("no vision-language model configured (annotate.model and annotate.url)")
        self.settings = settings
        self.model: str = settings.model
        key = api_key if api_key is not None else os.environ.get(settings.api_key_env, "")
        self._key = _Secret(key.strip())
        self._limiter = EndpointLimiter(limits_dir, settings.concurrency, settings.requests_per_minute)
        self._rng = rng or random.Random()
        self._rng_lock = threading.Lock()
        self._format_lock = threading.Lock()
        self._format: Literal["json_schema", "json_object", "none"] = (
            "json_schema" if settings.response_format == "auto" else settings.response_format
        )
        self._fatal = ""
        headers = {"Accept": "application/json"}
        if self._key.value:
            headers["Authorization"] = f"Bearer {self._key.value}"
        self._httpx = _httpx2()
        self._http: httpx2.Client = self._httpx.Client(
            base_url=settings.url + "/",
            headers=headers,
            timeout=self._httpx.Timeout(settings.timeout_s),
            limits=self._httpx.Limits(max_connections=settings.concurrency),
            follow_redirects=False,
            trust_env=False,
        )

    def close(self) -> None:
        """Close the connection pool (idempotent)."""
        self._http.close()

    def __enter__(self) -> VlmClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def response_format(self) -> str:
        """The ``response_format`` type requests use now (after any fallback)."""
        return self._format

    def redact(self, text: str) -> str:
        """``text`` with the API key replaced by ``***`` (for anything logged or returned)."""
        key = self._key.value
        return text.replace(key, "***") if key else text

    def describe(self, parts: Sequence[dict[str, Any]], *, context: str = "") -> Completion:
        """Ask the model to describe one clip given as content parts (:func:`image_part`...).

        Args:
            parts: The clip's stills or video as chat content parts.
            context: Known facts put before the question (segment label, episode task); may be empty.

        Returns:
            The validated description, or ``None`` and a one-line ``error`` after the retries.
        """
        tally = _Tally()
        user: list[dict[str, Any]] = [{"type": "text", "text": _question(context)}, *parts]
        transport_tries = 0
        invalid_tries = 0
        while True:
            if self._fatal:
                return self._finish(tally, None, self._fatal)
            fmt = self._format
            reply = self._send(self._body(user, fmt), tally)
            status = reply.status
            if status == _NO_REPLY or status in _RETRY_STATUS:
                reason = reply.reason or f"HTTP {status}: {_snippet(reply.raw)}"
                if transport_tries >= self.settings.max_retries:
                    return self._finish(tally, None, f"{reason} (after {transport_tries + 1} tries)")
                self._wait_to_retry(transport_tries, reply, reason, tally)
                transport_tries += 1
                continue
            if status == 400 and fmt != "none" and self.settings.response_format == "auto":
                self._downgrade(fmt, _snippet(reply.raw))
                continue
            if status in _AUTH_STATUS:
                env = self.settings.api_key_env
                self._fatal = f"HTTP {status}: the server refused the API key (set {env})"
                return self._finish(tally, None, self._fatal)
            if status == _OVERSIZED:
                description, problem = None, reply.reason
            elif status != 200:
                return self._finish(tally, None, f"HTTP {status}: {_snippet(reply.raw)}")
            else:
                description, problem = self._parse(reply.raw, tally)
            if description is not None:
                return self._finish(tally, description, "")
            if invalid_tries >= self.settings.invalid_retries:
                return self._finish(tally, None, f"invalid answer: {problem}")
            invalid_tries += 1
            tally.retries += 1
            _log.info("%s: invalid answer (%s); asking again", self.model, self.redact(problem))

    # -- one request ------------------------------------------------------------------------------

    def _body(self, user: list[dict[str, Any]], fmt: str) -> dict[str, Any]:
        body: dict[str, Any] = {
            "model": self.model,
            "messages": [
                {"role": "system", "content": _SYSTEM_PROMPT},
                {"role": "user", "content": user},
            ],
            "stream": False,
            "max_tokens": self.settings.max_tokens,
            "temperature": self.settings.temperature,
        }
        if fmt == "json_schema":
            body["response_format"] = {
                "type": "json_schema",
                "json_schema": {"name": "clip_annotation", "schema": RESPONSE_SCHEMA, "strict": True},
            }
        elif fmt == "json_object":
            body["response_format"] = {"type": "json_object"}
        return body

    def _send(self, body: dict[str, Any], tally: _Tally) -> _Reply:
        """One request; a timeout, dropped connection or oversized answer becomes a status code."""
        try:
            return self._post(body, tally)
        except self._httpx.TimeoutException:
            return _Reply(_NO_REPLY, {}, b"", f"timed out after {self.settings.timeout_s:g} s")
        except self._httpx.TransportError as exc:
            return _Reply(_NO_REPLY, {}, b"", f"connection failed ({type(exc).__name__})")
        except _OversizedError:
            return _Reply(_OVERSIZED, {}, b"", f"larger than {self.settings.max_response_mb:g} MiB")

    def _post(self, body: dict[str, Any], tally: _Tally) -> _Reply:
        """Send one request under the host-wide limits; the answer is read up to the size cap."""
        cap = int(self.settings.max_response_mb * (1 << 20))
        with self._limiter.slot():
            self._limiter.wait_turn()
            tally.requests += 1
            with self._http.stream("POST", "chat/completions", json=body) as reply:
                data = bytearray()
                for chunk in reply.iter_bytes():
                    data += chunk
                    if len(data) > cap:
                        raise _OversizedError
                headers = {k.lower(): v for k, v in reply.headers.items()}
                return _Reply(reply.status_code, headers, bytes(data))

    def _parse(self, raw: bytes, tally: _Tally) -> tuple[ClipDescription | None, str]:
        """Usage into ``tally``; the validated description, or ``None`` and the first problem."""
        try:
            doc = json.loads(raw)
        except (ValueError, RecursionError):
            return None, "the response body is not JSON"
        if not isinstance(doc, dict):
            return None, "the response body is not a JSON object"
        usage = doc.get("usage")
        if isinstance(usage, dict):
            tally.prompt_tokens += _count(usage.get("prompt_tokens"))
            tally.completion_tokens += _count(usage.get("completion_tokens"))
        choices = doc.get("choices")
        if not isinstance(choices, list) or not choices or not isinstance(choices[0], dict):
            return None, "no choices in the response"
        message = choices[0].get("message")
        content = message.get("content") if isinstance(message, dict) else None
        if isinstance(content, list):  # some servers return content parts
            content = "".join(p.get("text", "") for p in content if isinstance(p, dict))
        if not isinstance(content, str) or not content.strip():
            return None, "the answer is empty"
        if choices[0].get("finish_reason") == "length":
            return None, f"the answer was cut at max_tokens={self.settings.max_tokens}"
        try:
            answer = json.loads(_strip_fence(content))
        except (ValueError, RecursionError):
            return None, "the answer is not JSON"
        try:
            return ClipDescription.model_validate(answer), ""
        except ValidationError as exc:
            first = exc.errors()[0]
            where = ".".join(str(p) for p in first["loc"]) or "answer"
            return None, f"{where}: {first['msg']}"

    # -- policy -----------------------------------------------------------------------------------

    def _backoff(self, tries: int, retry_after: str | None) -> float:
        """Exponential backoff with 50-100 % jitter, or the server's Retry-After if longer [s]."""
        s = self.settings
        with self._rng_lock:
            delay = min(s.backoff_max_s, s.backoff_base_s * 2.0**tries) * (0.5 + 0.5 * self._rng.random())
        wanted = _retry_after_s(retry_after)
        if wanted is not None:
            delay = max(delay, min(wanted, s.backoff_max_s))
        return delay

    def _wait_to_retry(self, tries: int, reply: _Reply, reason: str, tally: _Tally) -> None:
        delay = self._backoff(tries, reply.headers.get("retry-after"))
        tally.retries += 1
        tally.backoff_s += delay
        _log.info("%s: %s; retrying in %.2f s", self.model, self.redact(reason), delay)
        time.sleep(delay)

    def _downgrade(self, fmt: str, why: str) -> None:
        with self._format_lock:
            if self._format != fmt:
                return  # another thread already fell back
            self._format = "json_object" if fmt == "json_schema" else "none"
        _log.warning(
            "%s: the server refused response_format %s (%s); using %s",
            self.model,
            fmt,
            self.redact(why),
            self._format,
        )

    def _finish(self, tally: _Tally, description: ClipDescription | None, error: str) -> Completion:
        if error:
            _log.warning("%s: %s", self.model, self.redact(error))
        return Completion(
            description=description,
            error=self.redact(error),
            prompt_tokens=tally.prompt_tokens,
            completion_tokens=tally.completion_tokens,
            requests=tally.requests,
            retries=tally.retries,
            backoff_s=tally.backoff_s,
            response_format=self._format,
        )


def _httpx2() -> ModuleType:
    """The HTTP client module, imported on first use: the offline annotator does without it."""
    try:
        return importlib.import_module("httpx2")
    except ImportError:
        raise DependencyError(
            "the vision-language annotation client needs httpx2: pip install 'telerig[process]'"
        ) from None


def _question(context: str) -> str:
    ask = "Describe this clip (the images are stills in time order) as the JSON object."
    return f"Known about this clip: {context}\n{ask}" if context else ask


def _strip_fence(text: str) -> str:
    """The JSON inside a Markdown code fence, which prompt-only answers often add."""
    m = re.fullmatch(r"\s*```(?:json)?\s*(.*?)\s*```\s*", text, flags=re.DOTALL)
    return m.group(1) if m else text


def _count(value: Any) -> int:
    return value if isinstance(value, int) and not isinstance(value, bool) and 0 <= value < 1 << 40 else 0


def _snippet(raw: bytes) -> str:
    """The first line of an error body, for a one-line reason (at most 160 characters)."""
    text = raw[:2048].decode("utf-8", "replace").strip()
    try:
        doc = json.loads(text)
        if isinstance(doc, dict):
            err = doc.get("error")
            msg = err.get("message") if isinstance(err, dict) else err
            text = str(msg or doc.get("detail") or doc.get("message") or text)
    except ValueError:
        pass
    line = " ".join(text.split())
    return (line[:157] + "...") if len(line) > 160 else (line or "(empty body)")


def _retry_after_s(value: str | None) -> float | None:
    """Seconds from a Retry-After header (delta-seconds or an HTTP date); ``None`` if absent/bad."""
    if not value:
        return None
    value = value.strip()
    try:
        return max(0.0, float(value))
    except ValueError:
        pass
    try:
        when = email.utils.parsedate_to_datetime(value)
    except (TypeError, ValueError):
        return None
    return max(0.0, when.timestamp() - time.time())


def cache_key(clip_sha256: str, model: str, request: dict[str, Any]) -> str:
    """sha256 (hex) naming one answer: clip bytes, model, prompt version and request shape."""
    ident = {"clip": clip_sha256, "model": model, "prompt": PROMPT_VERSION, "request": request}
    return hashlib.sha256(json.dumps(ident, sort_keys=True).encode()).hexdigest()
