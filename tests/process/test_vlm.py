"""The OpenAI-compatible client against a real local chat-completions server (chat_server.py)."""

from __future__ import annotations

import json
import logging
import sys
import threading
from pathlib import Path
from typing import Any

import chat_server
import pytest

from telerig.config.process import AnnotateSettings
from telerig.process.annotate import sample_stills
from telerig.process.vlm import RESPONSE_SCHEMA, ClipDescription, VlmClient, image_part

KEY = "sk-test-0123456789abcdef-SECRET"


@pytest.fixture(scope="module")
def parts(tmp_path_factory: pytest.TempPathFactory) -> list[dict[str, Any]]:
    clip = chat_server.make_clip(tmp_path_factory.mktemp("clip") / "c.mp4", seconds=1.0)
    return [image_part(j) for j in sample_stills(clip, 3, max_side_px=128)]


def _settings(url: str, **over: Any) -> AnnotateSettings:
    base: dict[str, Any] = {
        "url": url,
        "model": "qwen2.5-vl-test",
        "backoff_base_s": 0.01,
        "backoff_max_s": 1.0,
        "timeout_s": 2.0,
        "requests_per_minute": 60_000,
        "max_retries": 3,
    }
    return AnnotateSettings(**(base | over))


def _client(tmp_path: Path, settings: AnnotateSettings, key: str | None = KEY) -> VlmClient:
    return VlmClient(settings, limits_dir=tmp_path / "limits", api_key=key)


def test_describes_a_clip_from_stills_with_a_json_schema_response_format(
    server: Any, parts: list[dict[str, Any]], tmp_path: Path
) -> None:
    with _client(tmp_path, _settings(server.url)) as client:
        done = client.describe(parts, context="segment label 'grasp'")
    assert done.error == ""
    assert isinstance(done.description, ClipDescription)
    assert done.description.objects[0].quantity == 3  # the server counted three JPEG image_url parts
    assert done.description.scene == "assembly_station"
    assert (done.prompt_tokens, done.completion_tokens, done.requests) == (250, 40, 1)
    (seen,) = server.seen
    assert server.shape_errors == []
    assert seen.authorization == f"Bearer {KEY}"
    assert seen.response_format == "json_schema"
    assert seen.body["response_format"]["json_schema"]["schema"] == RESPONSE_SCHEMA
    assert seen.body["stream"] is False
    assert "segment label 'grasp'" in seen.body["messages"][-1]["content"][0]["text"]


def test_429_is_retried_after_its_retry_after(
    server: Any, parts: list[dict[str, Any]], tmp_path: Path
) -> None:
    server.retry_after = "0.3"
    server.queue("429", "429")
    with _client(tmp_path, _settings(server.url)) as client:
        done = client.describe(parts)
    assert done.description is not None
    assert (done.requests, done.retries) == (3, 2)
    assert done.backoff_s >= 0.6  # Retry-After 0.3 s twice, over a 0.01 s backoff base
    gaps = [b - a for a, b in zip(server.times, server.times[1:], strict=False)]
    assert min(gaps) >= 0.29


@pytest.mark.parametrize("fault", ["500", "502", "503", "timeout"])
def test_server_errors_and_timeouts_are_retried_with_backoff(
    server: Any, parts: list[dict[str, Any]], tmp_path: Path, fault: str
) -> None:
    server.stall_s = 1.0
    server.queue(fault, fault)
    with _client(tmp_path, _settings(server.url, timeout_s=0.3)) as client:
        done = client.describe(parts)
    assert done.description is not None, done.error
    assert (done.requests, done.retries) == (3, 2)
    assert 0.01 * 0.5 + 0.02 * 0.5 <= done.backoff_s <= 0.01 + 0.02  # base 0.01 s doubling, 50-100 % jitter


def test_retries_give_up_with_a_one_line_reason(
    server: Any, parts: list[dict[str, Any]], tmp_path: Path
) -> None:
    server.queue("503", "503", "503", "503")
    with _client(tmp_path, _settings(server.url, max_retries=2)) as client:
        done = client.describe(parts)
    assert done.description is None
    assert done.error == "HTTP 503: 503 (after 3 tries)"
    assert done.requests == 3


@pytest.mark.parametrize(
    ("fault", "reason"),
    [
        ("malformed", "invalid answer: the response body is not JSON"),
        ("invalid", "invalid answer: objects.0.quantity: Input should be greater than or equal to 0"),
        ("oversized", "invalid answer: larger than 0.1 MiB"),
        ("truncated", "invalid answer: the answer was cut at max_tokens=1024"),
    ],
)
def test_an_invalid_answer_is_retried_then_recorded_as_failed(
    server: Any, parts: list[dict[str, Any]], tmp_path: Path, fault: str, reason: str
) -> None:
    settings = _settings(server.url, max_response_mb=0.1, invalid_retries=1)
    server.queue(fault)
    with _client(tmp_path, settings) as client:
        recovered = client.describe(parts)
        server.queue(fault, fault)
        failed = client.describe(parts)
    assert recovered.description is not None
    assert (recovered.requests, recovered.retries) == (2, 1)
    assert failed.description is None
    assert failed.error == reason
    assert failed.requests == 2


def test_a_fenced_answer_to_a_prompt_only_request_is_accepted(
    server: Any, parts: list[dict[str, Any]], tmp_path: Path
) -> None:
    server.queue("fenced")
    with _client(tmp_path, _settings(server.url, response_format="none")) as client:
        done = client.describe(parts)
    assert done.description is not None, done.error
    assert "response_format" not in server.seen[0].body


def test_response_format_falls_back_when_the_server_refuses_it(
    server: Any, parts: list[dict[str, Any]], tmp_path: Path
) -> None:
    server.json_schema = False
    server.json_object = False
    with _client(tmp_path, _settings(server.url)) as client:
        first = client.describe(parts)
        second = client.describe(parts)
    assert first.description is not None
    assert second.description is not None
    assert [s.response_format for s in server.seen] == ["json_schema", "json_object", "none", "none"]
    assert [s.status for s in server.seen] == [400, 400, 200, 200]
    assert (first.response_format, first.retries) == ("none", 0)


def test_a_refused_key_fails_at_once_and_stops_further_requests(
    server: Any, parts: list[dict[str, Any]], tmp_path: Path
) -> None:
    with _client(tmp_path, _settings(server.url), key="sk-wrong") as client:
        first = client.describe(parts)
        second = client.describe(parts)
    assert first.error == "HTTP 401: the server refused the API key (set TELERIG_VLM_API_KEY)"
    assert second.error == first.error
    assert len(server.seen) == 1


def test_the_key_never_appears_in_errors_or_logs(
    server: Any, parts: list[dict[str, Any]], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    server.queue("echo-key-500", "echo-key-500")
    caplog.set_level(logging.DEBUG)
    with _client(tmp_path, _settings(server.url, max_retries=1)) as client:
        done = client.describe(parts)
        assert KEY not in repr(client.__dict__)
    assert "Authorization: Bearer ***" in done.error
    assert KEY not in done.error
    assert "Bearer ***" in caplog.text
    assert KEY not in caplog.text


def test_the_key_comes_from_the_environment_variable_named_in_settings(
    server: Any, parts: list[dict[str, Any]], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("MY_VLM_KEY", KEY)
    settings = _settings(server.url, api_key_env="MY_VLM_KEY")
    with VlmClient(settings, limits_dir=tmp_path / "limits") as client:
        done = client.describe(parts)
    assert done.description is not None
    assert server.seen[0].authorization == f"Bearer {KEY}"


def test_requests_per_minute_spaces_requests(
    server: Any, parts: list[dict[str, Any]], tmp_path: Path
) -> None:
    with _client(tmp_path, _settings(server.url, requests_per_minute=600, concurrency=4)) as client:
        threads = [threading.Thread(target=client.describe, args=(parts,)) for _ in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(timeout=10)
    assert len(server.times) == 4
    # 600/min: sends start 0.1 s apart, so four span >= 0.3 s (arrivals jitter by a few ms on a
    # loaded host; without the limit all four arrive within milliseconds).
    assert server.times[-1] - server.times[0] >= 0.25


def test_an_unreachable_server_fails_after_the_retries(parts: list[dict[str, Any]], tmp_path: Path) -> None:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # closed again: nothing listens there
    with _client(tmp_path, _settings(f"http://127.0.0.1:{port}/v1", max_retries=1)) as client:
        done = client.describe(parts)
    assert done.description is None
    assert done.error == "connection failed (ConnectError) (after 2 tries)"


def test_a_missing_http_client_names_the_extra(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from telerig.errors import DependencyError

    monkeypatch.setitem(sys.modules, "httpx2", None)  # what an install without the extra looks like
    with pytest.raises(DependencyError, match=r"pip install 'telerig\[process\]'"):
        VlmClient(_settings("http://127.0.0.1:9/v1"), limits_dir=tmp_path)


_WORKER = """
import sys, threading
from pathlib import Path
from telerig.config.process import AnnotateSettings
from telerig.process.vlm import VlmClient, image_part
url, limits, jpeg = sys.argv[1], Path(sys.argv[2]), Path(sys.argv[3]).read_bytes()
settings = AnnotateSettings(url=url, model="m", concurrency=2, requests_per_minute=60000, backoff_base_s=0.01)
with VlmClient(settings, limits_dir=limits, api_key="k") as client:
    print("ready", flush=True)
    sys.stdin.readline()
    done = []
    work = lambda: done.append(client.describe([image_part(jpeg)]))
    threads = [threading.Thread(target=work) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
print(sum(d.description is not None for d in done), flush=True)
"""


def test_concurrency_limit_holds_across_worker_processes(
    server: Any, parts: list[dict[str, Any]], tmp_path: Path
) -> None:
    import base64
    import subprocess

    server.api_key = "k"
    server.hold_s = 0.3
    jpeg = tmp_path / "still.jpg"
    jpeg.write_bytes(base64.b64decode(parts[0]["image_url"]["url"].split(",", 1)[1]))
    args = [sys.executable, "-c", _WORKER, server.url, str(tmp_path / "limits"), str(jpeg)]
    other = subprocess.Popen(args, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert other.stdout is not None
    assert other.stdin is not None
    assert other.stdout.readline().strip() == "ready"
    with _client(tmp_path, _settings(server.url, concurrency=2), key="k") as client:
        threads = [threading.Thread(target=client.describe, args=(parts,)) for _ in range(3)]
        other.stdin.write("go\n")
        other.stdin.flush()
        for t in threads:
            t.start()
        for t in threads:
            t.join(timeout=20)
    out, _ = other.communicate(timeout=20)
    assert out.strip() == "3"
    assert [s.status for s in server.seen] == [200] * 6
    # Both processes had requests waiting at once (3 threads each, 0.3 s per request): without
    # the shared limit 4 or more would be in flight.
    assert server.max_in_flight == 2


def _completion(content: Any, usage: Any = None) -> bytes:
    doc: dict[str, Any] = {"choices": [{"message": {"role": "assistant", "content": content}}]}
    if usage is not None:
        doc["usage"] = usage
    return json.dumps(doc).encode()


_VALID = json.dumps(
    {
        "objects": [],
        "scene": "kitchen",
        "action": {"description": "d", "agent": "a", "objects": [], "interaction": "i"},
    }
)


@pytest.mark.parametrize(
    ("body", "error"),
    [
        (b"[]", "invalid answer: the response body is not a JSON object"),
        (b"null", "invalid answer: the response body is not a JSON object"),
        (b'{"choices": []}', "invalid answer: no choices in the response"),
        (b'{"choices": ["x"]}', "invalid answer: no choices in the response"),
        (_completion(None), "invalid answer: the answer is empty"),
        (_completion(42), "invalid answer: the answer is empty"),
        (_completion("[" * 100_000), "invalid answer: the answer is not JSON"),
        (b'{"a":' * 100_000, "invalid answer: the response body is not JSON"),
        (
            _completion("[1, 2]"),
            "invalid answer: answer: Input should be a valid dictionary or instance of ClipDescription",
        ),
        (
            _completion(_VALID.replace('"d"', json.dumps("x" * 5000))),
            "invalid answer: action.description: String should have at most 1000 characters",
        ),
        (
            _completion(_VALID.replace('"kitchen"', '"kitchen", "extra": 1')),
            "invalid answer: extra: Extra inputs are not permitted",
        ),
        (_completion("\x00\ud800"), "invalid answer: the answer is not JSON"),
    ],
)
def test_garbage_answers_are_one_line_failures(
    server: Any, parts: list[dict[str, Any]], tmp_path: Path, body: bytes, error: str
) -> None:
    server.raw_bodies.append(body)
    server.queue("raw")
    with _client(tmp_path, _settings(server.url, invalid_retries=0)) as client:
        done = client.describe(parts)
    assert done.description is None
    assert done.error == error
    assert done.requests == 1


@pytest.mark.parametrize(
    "usage",
    [{"prompt_tokens": -5, "completion_tokens": "many"}, {"prompt_tokens": 1e300}, "nope", [1, 2]],
)
def test_garbage_usage_counts_nothing(
    server: Any, parts: list[dict[str, Any]], tmp_path: Path, usage: Any
) -> None:
    server.raw_bodies.append(_completion([{"type": "text", "text": _VALID}], usage))
    server.queue("raw")
    with _client(tmp_path, _settings(server.url)) as client:
        done = client.describe(parts)
    assert done.description is not None, done.error  # content given as parts is read too
    assert (done.prompt_tokens, done.completion_tokens) == (0, 0)


@pytest.mark.parametrize(
    ("retry_after", "low", "high"),
    [
        ("99999", 0.2, 0.2),  # capped at backoff_max_s
        ("soon", 0.005, 0.01),  # unreadable: the backoff alone (base 0.01 s, 50-100 %)
        ("-3", 0.005, 0.01),
        ("Wed, 21 Oct 2015 07:28:00 GMT", 0.005, 0.01),  # a date in the past
        ("x" * 5000, 0.005, 0.01),
    ],
)
def test_an_odd_retry_after_is_bounded(
    server: Any, parts: list[dict[str, Any]], tmp_path: Path, retry_after: str, low: float, high: float
) -> None:
    server.retry_after = retry_after
    server.queue("429")
    with _client(tmp_path, _settings(server.url, backoff_max_s=0.2)) as client:
        done = client.describe(parts)
    assert done.description is not None
    assert low <= done.backoff_s <= high
