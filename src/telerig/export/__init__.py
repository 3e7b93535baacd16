"""Datasets from recorded episodes: one resampling policy, one joint-order schema, four formats.

- :mod:`~telerig.export.schema`: :class:`DatasetSchema`, the joint order, limits and cameras every
  export writes as ``robot_schema.json``.
- :mod:`~telerig.export.frames`: :func:`load_episode`, an episode resampled at the dataset grid.
- :mod:`~telerig.export.base`: the :class:`Exporter` protocol and its reports.
- :mod:`~telerig.export.run`: :func:`export`, the run every format shares (select, refuse mixed
  rigs, append, validate).
- :mod:`~telerig.export.config`: the registered formats (``lerobot``, ``hdf5``, ``robomimic``,
  ``rlds``) and their options.
"""

from telerig.export.base import Exporter, ExportSummary, ValidationReport
from telerig.export.frames import CameraTrack, EpisodeFrames, load_episode
from telerig.export.run import EpisodeFilter, export
from telerig.export.schema import CameraSpec, DatasetSchema, JointSpec

__all__ = [
    "CameraSpec",
    "CameraTrack",
    "DatasetSchema",
    "EpisodeFilter",
    "EpisodeFrames",
    "ExportSummary",
    "Exporter",
    "JointSpec",
    "ValidationReport",
    "export",
    "load_episode",
]
