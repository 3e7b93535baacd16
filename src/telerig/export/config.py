"""Exporter configs: one per dataset format, registered by ``type`` in ``telerig.registry.EXPORTERS``.

A config is the format's options as data. :func:`telerig.export.run.build_exporter` builds the
exporter of a built-in config (the writers import their config, so the configs import no writer:
listing formats never loads PyAV, pyarrow or h5py). A third-party format registers its config
under the ``telerig.exporters`` entry point group and gives it a ``build()`` returning its
:class:`~telerig.export.base.Exporter`.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from telerig.registry import EXPORTERS

__all__ = ["Hdf5ExportConfig", "LeRobotExportConfig", "RldsExportConfig", "RobomimicExportConfig"]


class _ExportConfig(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


@EXPORTERS.register
class LeRobotExportConfig(_ExportConfig):
    """LeRobot dataset format v3.0 (parquet + MP4), loadable by ``lerobot.LeRobotDataset``.

    Attributes:
        data_files_size_in_mb: A new data parquet file starts past this size [MiB] (LeRobot: 100).
        video_files_size_in_mb: A new MP4 file starts past this size [MiB] (LeRobot: 200).
        copy_video: Copy the recorded H.264 packets when a camera recorded one frame per dataset
            frame (fast; keeps the recording's keyframe interval). False re-encodes every episode
            with a keyframe every 2 frames, as LeRobot does, for cheaper random access in training.
    """

    type: Literal["lerobot"] = "lerobot"
    data_files_size_in_mb: float = Field(default=100.0, gt=0)
    video_files_size_in_mb: float = Field(default=200.0, gt=0)
    copy_video: bool = True


@EXPORTERS.register
class Hdf5ExportConfig(_ExportConfig):
    """One HDF5 file per episode: /observations, /actions, /metadata, /debug (seed 004)."""

    type: Literal["hdf5"] = "hdf5"


@EXPORTERS.register
class RobomimicExportConfig(_ExportConfig):
    """One robomimic HDF5 file: /data/demo_i with /mask filter keys."""

    type: Literal["robomimic"] = "robomimic"


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
