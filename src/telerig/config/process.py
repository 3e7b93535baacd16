"""Annotation pipeline settings of a rig file (``process:``): one settings object per stage.

Data only; :mod:`telerig.process` runs the stages with them. Every field has a default, so a rig
without a ``process:`` section (and ``telerig process`` without ``--rig``) works. A stage's settings
are hashed into its outputs' provenance: changing one redoes that stage and the stages after it.
Secrets (API keys) are never fields here: they come from the environment, so a new key redoes
nothing. Each stage owner keeps its class below; :class:`ProcessSettings` holds them.
"""

from __future__ import annotations

import os
import typing
import urllib.parse
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator, model_validator

__all__ = [
    "SCENE_TYPES",
    "AnnotateSettings",
    "ClipSettings",
    "FilterSettings",
    "LayoutSettings",
    "ProcessSettings",
    "SceneType",
    "SegmentSettings",
]


class FilterSettings(BaseModel):
    """Stage 1, frame filtering (motion heuristics, hand detection): see :mod:`telerig.process.filter`.

    Frames are sampled at ``sample_hz``; each sample is judged on a gray copy ``analysis_width``
    px wide (gray levels 0-255) and sent to the hand detector. A sample is kept when it has a hand
    and is neither blurred, shaken nor badly exposed; kept samples become spans, short gaps merge.

    Attributes:
        sample_hz: Frames judged per second of video [Hz] (2 keeps recall: hands stay in view for
            seconds; each sample stands for the 1 / sample_hz s around it).
        analysis_width: Width of the gray frame the heuristics see [px] (aspect kept).
        blur_min_var: A sample whose variance of the Laplacian is below this is blurred [levels^2].
        shake_pixel_delta: A pixel changed between the sample and the frame before it when its
            gray level moved by more than this [levels].
        shake_max_fraction: A sample is shaken (camera motion, not a moving hand) when more than
            this fraction of its pixels changed [1].
        static_max_diff: Mean absolute difference from the previous sample below which the frame
            is static and the previous sample's hands are reused without running the detector
            [levels].
        dark_max_mean: A sample whose mean gray level is below this is too dark [levels].
        bright_max_fraction: A sample with more than this fraction of pixels at 250 or more is
            blown out [1].
        merge_gap_s: Kept spans closer than this merge (a missed detection, a moment of blur) [s].
        pad_s: Each kept span grows by this on both sides before cutting [s].
        min_span_s: Kept spans shorter than this (after merging and padding) are dropped [s].
        batch_frames: Frames per detector call [1].
        detector: The hand detector: a ``type`` registered in ``telerig.registry.HAND_DETECTORS``
            (``mediapipe``: the markerless tracker's MediaPipe Hands, bundled models) and its fields.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    sample_hz: float = Field(default=2.0, gt=0, le=60)
    analysis_width: int = Field(default=160, ge=32, le=1920)
    blur_min_var: float = Field(default=15.0, ge=0)
    shake_pixel_delta: float = Field(default=30.0, ge=0, le=255)
    shake_max_fraction: float = Field(default=0.6, ge=0, le=1)
    static_max_diff: float = Field(default=0.5, ge=0, le=255)
    dark_max_mean: float = Field(default=20.0, ge=0, le=255)
    bright_max_fraction: float = Field(default=0.5, ge=0, le=1)
    merge_gap_s: float = Field(default=1.0, ge=0, le=3600)
    pad_s: float = Field(default=0.25, ge=0, le=60)
    min_span_s: float = Field(default=0.0, ge=0, le=3600)
    batch_frames: int = Field(default=16, ge=1, le=256)
    detector: Any = Field(default_factory=lambda: {"type": "mediapipe"}, validate_default=True)

    @field_validator("detector", mode="before")
    @classmethod
    def _resolve_detector(cls, value: Any) -> Any:
        from telerig.registry import HAND_DETECTORS

        # `detector: mediapipe` is short for `detector: {type: mediapipe}`.
        return HAND_DETECTORS.parse_config({"type": value} if isinstance(value, str) else value, "detector")


class SegmentSettings(BaseModel):
    """Stage 2, temporal action segmentation: see :mod:`telerig.process.segment`.

    Attributes:
        robot: Segmenter of episodes whose robots recorded their streams: a ``type`` registered in
            ``telerig.registry.SEGMENTERS`` (``robot_streams``: gripper events, end-effector speed
            and pauses, wrench changes) and its fields.
        video: Segmenter of plain video and of episodes without robot streams (``motion_energy``:
            the filter's hand motion, else frame difference) and its fields.
        episode_sidecar: Also write an episode's ``segments.json`` beside its files (the exports
            and ``telerig episodes show`` read it there); a person's reviewed segments in it are kept.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    robot: Any = Field(default_factory=lambda: {"type": "robot_streams"}, validate_default=True)
    video: Any = Field(default_factory=lambda: {"type": "motion_energy"}, validate_default=True)
    episode_sidecar: bool = True

    @field_validator("robot", "video", mode="before")
    @classmethod
    def _resolve_segmenter(cls, value: Any, info: ValidationInfo) -> Any:
        from telerig.registry import SEGMENTERS

        return SEGMENTERS.parse_config(value, str(info.field_name))


class ClipSettings(BaseModel):
    """Stage 3, clip extraction: see :mod:`telerig.process.clips`.

    A segment whose start lies at most ``keyframe_tolerance_s`` after a keyframe is cut by stream
    copy from that keyframe (no re-encode, the clip starts up to that much early); any other is
    re-encoded (libx264) from its exact start.

    Attributes:
        keyframe_tolerance_s: Largest lead-in a copied clip may carry before its segment [s].
        min_clip_s: Segments shorter than this get no clip [s].
        include_rejected: Cut clips of segments a reviewer rejected too.
        skip_labels: Segments with these labels get no clip (``idle``: nothing happens in it, and
            every clip costs an annotation).
        crf: x264 constant rate factor of re-encoded clips (0 lossless .. 51; 18 looks lossless).
        preset: x264 speed preset of re-encoded clips.
        verify: Decode every clip after writing it and check its frames and duration.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    keyframe_tolerance_s: float = Field(default=0.5, ge=0.0, le=60.0)
    min_clip_s: float = Field(default=0.2, ge=0.0, le=3600.0)
    include_rejected: bool = False
    skip_labels: tuple[str, ...] = Field(default=("idle",), max_length=64)
    crf: int = Field(default=18, ge=0, le=51)
    preset: Literal["ultrafast", "superfast", "veryfast", "faster", "fast", "medium", "slow"] = "veryfast"
    verify: bool = True


#: Scene classes a vision-language annotation may name (stage 4; the dataset layout's folders).
SceneType = Literal["lab", "factory_floor", "assembly_station", "kitchen", "office", "outdoor", "other"]
SCENE_TYPES: tuple[SceneType, ...] = typing.get_args(SceneType)


def _env_or_none(name: str) -> str | None:
    value = os.environ.get(name, "").strip()
    return value or None


class AnnotateSettings(BaseModel):
    """Stage 4, vision-language annotation: which model describes each clip, and how hard to push it.

    The endpoint speaks the OpenAI chat-completions API (vLLM, Ollama, Qwen-VL's compatible mode).
    ``url`` and ``model`` default to ``TELERIG_VLM_URL`` / ``TELERIG_VLM_MODEL`` when the rig file
    leaves them out; with no model the offline annotator fills what episode metadata and the
    segment label tell (marked ``offline: true``). The API key is never a setting: it is read from
    the environment variable named by ``api_key_env`` at run time, so it is neither hashed into
    provenance nor written anywhere.

    Attributes:
        url: Base URL of the API, up to ``/v1`` (``http://127.0.0.1:8000/v1``); no credentials in it.
        model: Model name the server knows (``Qwen/Qwen2.5-VL-7B-Instruct``); ``None``: offline.
        api_key_env: Environment variable holding the bearer token (unset: no Authorization header).
        input: ``frames``: ``frames`` JPEG stills per clip as ``image_url`` parts; ``video``: the
            clip file itself as a base64 ``video_url`` part (vLLM / Qwen-VL), frames when it is
            larger than ``max_video_mb``.
        frames: Stills sampled per clip, evenly spaced in time [1].
        max_side_px: Stills are scaled down so their longer side is at most this [px].
        jpeg_qscale: JPEG quantizer of the stills, 2 (best) to 31 (smallest) [1].
        max_video_mb: Largest clip sent as video [MiB].
        response_format: ``auto`` asks for a JSON-schema ``response_format`` and falls back to
            ``json_object``, then to the prompt alone, when the server answers 400 to it.
        max_tokens: Completion budget per request [tokens].
        temperature: Sampling temperature (0: most repeatable answers).
        timeout_s: Per-request timeout (connect, read, write) [s].
        max_retries: Retries of one request on 429/500/502/503/504, timeouts and dropped
            connections, with exponential backoff and jitter [1].
        backoff_base_s: First backoff; doubles per retry, jittered to 50-100 % [s].
        backoff_max_s: Longest single backoff, and the longest ``Retry-After`` honoured [s].
        invalid_retries: Extra tries of a clip whose answer is not valid JSON of the schema [1].
        max_response_mb: Larger answers are cut off and count as invalid [MiB].
        concurrency: Requests in flight at once to one endpoint from this host, across the
            pipeline's worker processes (file locks under the processed root) [1].
        requests_per_minute: Request rate to one endpoint from this host (evenly spaced) [1/min].
        price_prompt_per_1k: Price of 1000 prompt tokens, for the cost totals [USD].
        price_completion_per_1k: Price of 1000 completion tokens [USD].
        cache: Reuse earlier answers for the same clip bytes, model and prompt (``<processed>/cache``).
    """

    # A refused URL may carry a password: errors name the field, never echo its value.
    model_config = ConfigDict(frozen=True, extra="forbid", hide_input_in_errors=True)

    # validate_default: a URL from the environment is checked like one from the rig file.
    url: str | None = Field(
        default_factory=lambda: _env_or_none("TELERIG_VLM_URL"), max_length=2000, validate_default=True
    )
    model: str | None = Field(
        default_factory=lambda: _env_or_none("TELERIG_VLM_MODEL"),
        min_length=1,
        max_length=200,
        validate_default=True,
    )
    api_key_env: str = Field(default="TELERIG_VLM_API_KEY", pattern=r"^[A-Za-z_][A-Za-z0-9_]{0,127}$")
    input: Literal["frames", "video"] = "frames"
    frames: int = Field(default=8, ge=1, le=64)
    max_side_px: int = Field(default=448, ge=32, le=4096)
    jpeg_qscale: int = Field(default=4, ge=2, le=31)
    max_video_mb: float = Field(default=20.0, gt=0, le=1024)
    response_format: Literal["auto", "json_schema", "json_object", "none"] = "auto"
    max_tokens: int = Field(default=1024, ge=16, le=65536)
    temperature: float = Field(default=0.0, ge=0, le=2)
    timeout_s: float = Field(default=120.0, gt=0, le=3600)
    max_retries: int = Field(default=5, ge=0, le=20)
    backoff_base_s: float = Field(default=1.0, ge=0, le=600)
    backoff_max_s: float = Field(default=60.0, ge=0, le=3600)
    invalid_retries: int = Field(default=1, ge=0, le=10)
    max_response_mb: float = Field(default=1.0, gt=0, le=64)
    concurrency: int = Field(default=4, ge=1, le=256)
    requests_per_minute: float = Field(default=60.0, gt=0, le=100_000)
    price_prompt_per_1k: float = Field(default=0.0, ge=0, le=1000)
    price_completion_per_1k: float = Field(default=0.0, ge=0, le=1000)
    cache: bool = True

    @field_validator("url")
    @classmethod
    def _plain_http_url(cls, value: str | None) -> str | None:
        if value is None:
            return None
        # Messages start with "url:" and never quote the value: the rig loader then adds no
        # "(got ...)", and a URL may carry a password or a key in its query.
        try:
            parts = urllib.parse.urlsplit(value.strip())
            host = parts.hostname
        except ValueError:
            raise ValueError("url: is not a URL (e.g. http://127.0.0.1:8000/v1)") from None
        if parts.username or parts.password:
            raise ValueError("url: carries a user name or password; put the API key in TELERIG_VLM_API_KEY")
        if parts.query or parts.fragment:
            raise ValueError("url: has a query or fragment; give the base URL up to /v1")
        if parts.scheme not in ("http", "https") or not host:
            raise ValueError("url: must be http(s) with a host (e.g. http://127.0.0.1:8000/v1)")
        return value.strip().rstrip("/")

    @model_validator(mode="after")
    def _url_for_model(self) -> AnnotateSettings:
        if self.model is not None and self.url is None:
            raise ValueError(f"model {self.model!r} is set but no url (annotate.url or TELERIG_VLM_URL)")
        return self


class LayoutSettings(BaseModel):
    """Stage 5, the dataset layout: see :mod:`telerig.process.layout`.

    Attributes:
        streams: Write each episode clip's recorded streams (cut to the clip's span) beside it.
        stream_margin_s: Extra time [s] kept before and after a clip's span in its streams, so a
            resampler has a sample on each side of the first and last frame.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    streams: bool = True
    stream_margin_s: float = Field(default=0.1, ge=0.0, le=10.0)


class ProcessSettings(BaseModel):
    """The ``process:`` section: the stages' settings and how many items run at once.

    Attributes:
        workers: Items processed at once on the local process pool; ``None``: one per CPU core.
            ``telerig process --workers`` overrides it.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    workers: int | None = Field(default=None, ge=1, le=256)
    filter: FilterSettings = Field(default_factory=FilterSettings)
    segment: SegmentSettings = Field(default_factory=SegmentSettings)
    clips: ClipSettings = Field(default_factory=ClipSettings)
    annotate: AnnotateSettings = Field(default_factory=AnnotateSettings)
    layout: LayoutSettings = Field(default_factory=LayoutSettings)

    def for_stage(self, name: str) -> BaseModel | None:
        """The settings object of stage ``name``; ``None`` for a stage without settings (plug-ins)."""
        stages: dict[str, BaseModel] = {
            "filter": self.filter,
            "segment": self.segment,
            "clips": self.clips,
            "annotate": self.annotate,
            "layout": self.layout,
        }
        return stages.get(name)
