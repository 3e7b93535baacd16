"""Annotation pipeline settings of a rig file (``process:``): one settings object per stage.

Data only; :mod:`telerig.process` runs the stages with them. Every field has a default, so a rig
without a ``process:`` section (and ``telerig process`` without ``--rig``) works. A stage's settings
are hashed into its outputs' provenance: changing one redoes that stage and the stages after it.
Secrets (API keys) are never fields here: they come from the environment, so a new key redoes
nothing. Each stage owner keeps its class below; :class:`ProcessSettings` holds them.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

__all__ = [
    "AnnotateSettings",
    "ClipSettings",
    "FilterSettings",
    "LayoutSettings",
    "ProcessSettings",
    "SegmentSettings",
]


class FilterSettings(BaseModel):
    """Stage 1, frame filtering (motion heuristics, hand detection): see :mod:`telerig.process.filter`."""

    model_config = ConfigDict(frozen=True, extra="forbid")


class SegmentSettings(BaseModel):
    """Stage 2, temporal action segmentation: see :mod:`telerig.process.segment`."""

    model_config = ConfigDict(frozen=True, extra="forbid")


class ClipSettings(BaseModel):
    """Stage 3, clip extraction: see :mod:`telerig.process.clips`."""

    model_config = ConfigDict(frozen=True, extra="forbid")


class AnnotateSettings(BaseModel):
    """Stage 4, vision-language annotation: see :mod:`telerig.process.annotate`."""

    model_config = ConfigDict(frozen=True, extra="forbid")


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
