"""The curated public API: names exported from each package are pinned, and all resolve."""

from __future__ import annotations

import importlib

import pytest

PUBLIC = {
    "telerig": {
        "BaseVelocity", "BodySkeleton", "BusError", "CameraFrame", "ConfigError", "ControllerState",
        "DependencyError", "DeviceError", "GripperCommand", "HandPose", "JointCommand", "JointState", "Pose",
        "RecordingError", "RigConfig", "RobotError", "SafetyError", "Stamp", "TelerigError", "Twist",
        "WireError", "Wrench", "__version__", "load_rig",
    },
    "telerig.bus": {
        "Bus", "BusStats", "InMemoryBus", "Inbox", "Message", "MosquittoBroker", "MqttBus", "Subscription",
        "Topic", "connect_bus", "qos_for",
    },
    "telerig.devices": {"ButtonPress", "Device", "ReplayDevice", "SampleSink", "ScriptedVRController"},
    "telerig.robots": {"JointLimits", "RobotDriver"},
    "telerig.robots.dobot": {"CR5_LIMITS", "DobotRobot", "FakeDobot", "FeedbackPacket", "Reply", "RobotMode"},
    "telerig.robots.modbus": {
        "DHGripper", "DHStatus", "FakeDHGripper", "FakeInspireHand", "InspireHand", "InspireHealth",
        "LinkStats",
    },
    "telerig.robots.ur": {
        "ROBOTIQ_PORT", "UR_JOINT_NAMES", "UR_MODELS", "ClockMapper", "FakeURController", "RobotiqSocket",
        "ServoProgram", "URRobot", "URStats", "URStatus", "stop_program", "ur_limits",
    },
    "telerig.robots.rosbridge": {"CommandType", "FakeRosbridge", "JointStateMsg", "RosbridgeRobot"},
    "telerig.robots.models": {
        "ARM_MODELS", "GRIPPER_MODELS", "ArmModel", "GripperModel", "ModelledRobot", "arm_kinematics_of",
        "arm_model",
    },
    "telerig.store": {
        "EpisodeDraft", "EpisodeIndex", "EpisodeManifest", "EpisodeRecord", "EpisodeStore", "EpisodeSummary",
        "EpisodeUploader", "IndexStatus", "RemoteConfig", "StationLoad", "UploadPolicy", "UploadQueue",
        "UploadResult", "open_store",
    },
    "telerig.record": {"LogEntry", "McapLog", "Recorder", "read_log"},
    "telerig.qa": {"GATES", "GateName", "GateVerdict", "QaReport", "QaThresholds", "evaluate"},
    "telerig.safety": {
        "FAULT_CODES", "POLICIES", "SAFETY_CODES", "SEVERITY", "AccelerationLimit", "Box",
        "ConfigurationCheck", "ConfigurationGuard", "Deadman", "FaultPolicy", "Freshness", "InputCheck",
        "InputWatchdog",
        "KinematicsModel", "Limit", "PositionClamp", "PositionRangeCheck", "RobotSafety", "RobotSafetyConfig",
        "SafetyAlert", "SafetyAlerts", "SafetyChain", "SafetyCode", "SafetyEvent", "SafetyOutput",
        "SafetyStatus", "SafetySupervisor", "SelfCollision", "Severity", "Sphere", "StartupRamp", "Tick",
        "VelocityLimit", "Violation", "WorkspaceBounds", "arm_guard",
    },
}  # fmt: skip


@pytest.mark.parametrize("module", sorted(PUBLIC))
def test_public_names_are_pinned(module: str) -> None:
    assert set(importlib.import_module(module).__all__) == PUBLIC[module]


@pytest.mark.parametrize("module", sorted(PUBLIC))
def test_every_public_name_resolves(module: str) -> None:
    mod = importlib.import_module(module)
    for name in mod.__all__:
        assert getattr(mod, name) is not None


def test_every_error_derives_from_the_root() -> None:
    import telerig

    for name in telerig.__all__:
        obj = getattr(telerig, name)
        if isinstance(obj, type) and issubclass(obj, Exception):
            assert issubclass(obj, telerig.TelerigError)
