"""The chat-completions protocol, checked against the official OpenAI SDK (its request and response types).

The annotation tests run telerig's client against tests/process/chat_server.py; these show that the
server is not a private dialect: the SDK's own requests pass its shape checks and its answers parse
into the SDK's response models, and that what telerig's client sends validates as the SDK's request
types (frames mode: ``video_url`` is a vLLM / Qwen-VL extension the SDK does not type).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import chat_server
import pytest
from pydantic import TypeAdapter

try:
    import openai
    from openai.types.chat import ChatCompletionContentPartParam, ChatCompletionMessageParam
    from openai.types.chat.completion_create_params import CompletionCreateParamsNonStreaming
except ImportError:
    pytest.fail(
        "the openai SDK (dev extra) is missing: run `make` (pip install -e '.[dev]' -c constraints.txt)"
    )

from telerig.config.process import AnnotateSettings
from telerig.process.annotate import sample_stills
from telerig.process.vlm import RESPONSE_SCHEMA, ClipDescription, VlmClient, image_part

KEY = "sk-protocol-test-5d1e"


@pytest.fixture(scope="module")
def parts(tmp_path_factory: pytest.TempPathFactory) -> list[dict[str, Any]]:
    clip = chat_server.make_clip(tmp_path_factory.mktemp("clip") / "c.mp4", seconds=1.0)
    return [image_part(j) for j in sample_stills(clip, 2, max_side_px=96)]


def test_the_official_sdk_and_the_test_server_agree(server: Any, parts: list[dict[str, Any]]) -> None:
    with openai.OpenAI(base_url=server.url, api_key=KEY, max_retries=0, timeout=10) as sdk:
        reply = sdk.chat.completions.create(
            model="qwen2.5-vl-test",
            messages=[
                {"role": "system", "content": "answer in JSON"},
                {"role": "user", "content": [{"type": "text", "text": "describe"}, *parts]},
            ],
            stream=False,
            max_tokens=256,
            response_format={
                "type": "json_schema",
                "json_schema": {"name": "clip_annotation", "schema": RESPONSE_SCHEMA, "strict": True},
            },
        )
    assert server.shape_errors == []
    assert (server.seen[0].images, server.seen[0].response_format) == (2, "json_schema")
    assert reply.usage is not None
    assert (reply.usage.prompt_tokens, reply.usage.completion_tokens) == (200, 40)
    content = reply.choices[0].message.content
    assert content is not None
    assert ClipDescription.model_validate(json.loads(content)).objects[0].quantity == 2


def test_the_client_sends_what_the_sdk_types_describe(
    server: Any, parts: list[dict[str, Any]], tmp_path: Path
) -> None:
    server.json_schema = False  # one request with each response_format the client may send
    server.json_object = False
    settings = AnnotateSettings(url=server.url, model="qwen2.5-vl-test", backoff_base_s=0.01)
    with VlmClient(settings, limits_dir=tmp_path / "limits", api_key=KEY) as client:
        assert client.describe(parts).description is not None
    request = TypeAdapter(CompletionCreateParamsNonStreaming)
    message = TypeAdapter(ChatCompletionMessageParam)
    part = TypeAdapter(ChatCompletionContentPartParam)
    assert [s.response_format for s in server.seen] == ["json_schema", "json_object", "none"]
    for seen in server.seen:
        request.validate_python(seen.body)
        for m in seen.body["messages"]:
            message.validate_python(m)
            for p in m["content"] if isinstance(m["content"], list) else ():
                part.validate_python(p)  # the SDK's Iterable[...] content is not checked eagerly


def test_the_sdk_types_refuse_a_malformed_part() -> None:
    """The part check above can fail: an image_url that is not an object is refused."""
    with pytest.raises(ValueError, match="validation error"):
        TypeAdapter(ChatCompletionContentPartParam).validate_python({"type": "image_url", "image_url": "x"})
