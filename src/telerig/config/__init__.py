"""Rig files: schema, loading and validation."""

from telerig.config.load import load_rig, parse_rig, shipped_rig_path, shipped_rigs
from telerig.config.schema import (
    AlignmentConfig,
    BindingConfig,
    CameraConfig,
    DeviceConfig,
    EmbeddedBrokerConfig,
    ExternalBrokerConfig,
    RecordingConfig,
    RetargeterConfig,
    RigConfig,
    RobotConfig,
    SafetyConfig,
    StationConfig,
)

__all__ = [
    "AlignmentConfig",
    "BindingConfig",
    "CameraConfig",
    "DeviceConfig",
    "EmbeddedBrokerConfig",
    "ExternalBrokerConfig",
    "RecordingConfig",
    "RetargeterConfig",
    "RigConfig",
    "RobotConfig",
    "SafetyConfig",
    "StationConfig",
    "load_rig",
    "parse_rig",
    "shipped_rig_path",
    "shipped_rigs",
]
