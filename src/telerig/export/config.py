"""Exporter configs: one per dataset format, registered by ``type`` in ``telerig.registry.EXPORTERS``.

Each config holds its format's options and builds its exporter; the writer modules (PyAV, pyarrow,
h5py...) are imported only when an exporter is built, so listing formats stays cheap. A
third-party format registers its config under the ``telerig.exporters`` entry point group.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal

from pydantic import BaseModel, ConfigDict, Field

from telerig.registry import EXPORTERS

if TYPE_CHECKING:
    from telerig.export.base import Exporter

__all__ = ["Hdf5ExportConfig", "LeRobotExportConfig", "RldsExportConfig", "RobomimicExportConfig"]


class _ExportConfig(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


@EXPORTERS.register
class LeRobotExportConfig(_ExportConfig):
    """LeRobot dataset format v3.0 (parquet + MP4), loadable by ``lerobot.LeRobotDataset``."""

    type: Literal["lerobot"] = "lerobot"

    def build(self) -> Exporter:
        from telerig.export.lerobot import LeRobotExporter

        return LeRobotExporter(self)


@EXPORTERS.register
class Hdf5ExportConfig(_ExportConfig):
    """One HDF5 file per episode: /observations, /actions, /metadata, /debug (seed 004)."""

    type: Literal["hdf5"] = "hdf5"

    def build(self) -> Exporter:
        from telerig.export.hdf5 import Hdf5Exporter

        return Hdf5Exporter(self)


@EXPORTERS.register
class RobomimicExportConfig(_ExportConfig):
    """One robomimic HDF5 file: /data/demo_i with /mask filter keys."""

    type: Literal["robomimic"] = "robomimic"

    def build(self) -> Exporter:
        from telerig.export.robomimic import RobomimicExporter

        return RobomimicExporter(self)


@EXPORTERS.register
class RldsExportConfig(_ExportConfig):
    """RLDS / Open X-Embodiment TFRecord shards readable by ``tfds.builder_from_directory``.

    Attributes:
        name: TFDS dataset name (``<out>/<name>/1.0.0``); the rig name when ``None``.
        image_format: Step images as ``jpeg`` (what OXE datasets hold) or lossless ``png``.
        jpeg_quality: JPEG quality, 1..100 (95: TensorFlow's ``encode_jpeg`` default in TFDS).
        shard_mb: A shard is closed once it holds this many MiB (each run appends new shards).
    """

    type: Literal["rlds"] = "rlds"
    name: str | None = Field(default=None, pattern=r"^[a-z][a-z0-9_]*$")
    image_format: Literal["jpeg", "png"] = "jpeg"
    jpeg_quality: int = Field(default=95, ge=1, le=100)
    shard_mb: int = Field(default=256, ge=1)

    def build(self) -> Exporter:
        from telerig.export.rlds import RldsExporter

        return RldsExporter(self)
