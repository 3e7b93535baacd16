"""telerig: teleoperation and robot-data platform.

The curated public API lives here; everything else is importable from its
module but may change without notice.
"""

from telerig.config import RigConfig, load_rig
from telerig.errors import (
    BusError,
    ConfigError,
    DependencyError,
    DeviceError,
    RecordingError,
    RobotError,
    SafetyError,
    TelerigError,
    WireError,
)
from telerig.ir.types import (
    BaseVelocity,
    BodySkeleton,
    CameraFrame,
    ControllerState,
    GripperCommand,
    HandPose,
    JointCommand,
    JointState,
    Pose,
    Stamp,
    Twist,
    Wrench,
)

__version__ = "0.1.0"

__all__ = [
    "BaseVelocity",
    "BodySkeleton",
    "BusError",
    "CameraFrame",
    "ConfigError",
    "ControllerState",
    "DependencyError",
    "DeviceError",
    "GripperCommand",
    "HandPose",
    "JointCommand",
    "JointState",
    "Pose",
    "RecordingError",
    "RigConfig",
    "RobotError",
    "SafetyError",
    "Stamp",
    "TelerigError",
    "Twist",
    "WireError",
    "Wrench",
    "__version__",
    "load_rig",
]
