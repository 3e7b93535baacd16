"""The telerig exception hierarchy.

Every error telerig raises on purpose derives from :class:`TelerigError`, so a
caller can catch one root. Expected failures (bad rig file, missing model,
malformed packet) carry a one-line message that says what to fix; the CLI
prints that line and exits non-zero instead of showing a traceback.

::

    TelerigError
    ├── ConfigError          rig file invalid or names something that does not exist
    ├── DependencyError      an optional dependency or system tool is missing
    ├── WireError            a wire message could not be decoded
    ├── BusError             broker unreachable, embedded broker failed to start
    ├── DeviceError          an input device failed
    ├── RobotError           a robot driver failed (model, connection, fault)
    ├── SafetyError          the safety chain refused to continue (e-stop latched)
    ├── RecordingError       an episode could not be written, committed or read
    │   └── UploadError      an episode could not be uploaded or its remote copy checked
    │       └── ChecksumMismatchError  a file or object does not match the manifest sha256
    ├── CalibrationError     an operator calibration was rejected (hands moving, not level, ...)
    ├── ExportError          a dataset could not be exported, appended to or validated
    ├── ProcessError         the annotation pipeline could not read an input or its own outputs
    ├── PolicyError          a policy checkpoint or training dataset could not be read, or training failed
    └── SessionError         a session command is not allowed in the current state
"""

from __future__ import annotations

__all__ = [
    "BusError",
    "CalibrationError",
    "ChecksumMismatchError",
    "ConfigError",
    "DependencyError",
    "DeviceError",
    "ExportError",
    "PolicyError",
    "ProcessError",
    "RecordingError",
    "RobotError",
    "SafetyError",
    "SessionError",
    "TelerigError",
    "UploadError",
    "WireError",
]


class TelerigError(Exception):
    """Root of every error telerig raises on purpose."""


class ConfigError(TelerigError):
    """A rig file or config value is invalid; the message names the field and the fix."""


class DependencyError(TelerigError):
    """An optional Python dependency or system program is missing; the message says how to install it."""


class WireError(TelerigError):
    """A wire message could not be decoded (truncated, wrong version, unknown body)."""


class BusError(TelerigError):
    """The message bus could not be reached or the embedded broker failed."""


class DeviceError(TelerigError):
    """An input device failed to open or produce samples."""


class RobotError(TelerigError):
    """A robot driver failed: missing model, lost connection, hardware fault."""


class SafetyError(TelerigError):
    """The safety chain refused a command and latched a stop."""


class RecordingError(TelerigError):
    """An episode could not be written, committed or read."""


class CalibrationError(TelerigError):
    """An operator calibration was rejected; the message says why and what the operator should do."""


class ExportError(TelerigError):
    """A dataset could not be exported, appended to or validated; the message names the fix."""


class ProcessError(TelerigError):
    """The annotation pipeline (``telerig process``) refused an input, a query or one of its outputs."""


class PolicyError(TelerigError):
    """A policy checkpoint, a training dataset or a training run was refused; the message names the fix."""


class SessionError(TelerigError):
    """A session command is not allowed in the current state; the message names the allowed ones."""


class UploadError(RecordingError):
    """An episode could not be uploaded or its remote copy could not be checked."""


class ChecksumMismatchError(UploadError):
    """A local file or a remote object does not match the sha256 in the episode manifest."""
