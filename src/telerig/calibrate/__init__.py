"""Operator calibration: neutral-pose rotation, arm length and scale, stored as per-operator profiles."""

from telerig.calibrate.neutral import (
    FORWARD_TOP_UP,
    CalibrationError,
    CalibrationSettings,
    Role,
    role_from_source,
    run_calibration,
)
from telerig.calibrate.profile import (
    DEFAULT_DATA_ROOT,
    PROFILE_VERSION,
    CalibrationProfile,
    alignment_for,
    load_profile,
    profile_path,
    save_profile,
)
from telerig.calibrate.rotations import cube_rotations
from telerig.calibrate.session import ProgressCallback, calibrate_from_device

__all__ = [
    "DEFAULT_DATA_ROOT",
    "FORWARD_TOP_UP",
    "PROFILE_VERSION",
    "CalibrationError",
    "CalibrationProfile",
    "CalibrationSettings",
    "ProgressCallback",
    "Role",
    "alignment_for",
    "calibrate_from_device",
    "cube_rotations",
    "load_profile",
    "profile_path",
    "role_from_source",
    "run_calibration",
    "save_profile",
]
