from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class Handedness(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    HANDEDNESS_UNSPECIFIED: _ClassVar[Handedness]
    HANDEDNESS_LEFT: _ClassVar[Handedness]
    HANDEDNESS_RIGHT: _ClassVar[Handedness]

class ControlKind(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    CONTROL_KIND_UNSPECIFIED: _ClassVar[ControlKind]
    CONTROL_KIND_NONE: _ClassVar[ControlKind]
    CONTROL_KIND_POLICY: _ClassVar[ControlKind]
    CONTROL_KIND_OPERATOR: _ClassVar[ControlKind]
    CONTROL_KIND_PAUSED: _ClassVar[ControlKind]
    CONTROL_KIND_HOME: _ClassVar[ControlKind]

class ControlMode(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    CONTROL_MODE_UNSPECIFIED: _ClassVar[ControlMode]
    CONTROL_MODE_AUTO: _ClassVar[ControlMode]
    CONTROL_MODE_OPERATOR: _ClassVar[ControlMode]
    CONTROL_MODE_POLICY: _ClassVar[ControlMode]
HANDEDNESS_UNSPECIFIED: Handedness
HANDEDNESS_LEFT: Handedness
HANDEDNESS_RIGHT: Handedness
CONTROL_KIND_UNSPECIFIED: ControlKind
CONTROL_KIND_NONE: ControlKind
CONTROL_KIND_POLICY: ControlKind
CONTROL_KIND_OPERATOR: ControlKind
CONTROL_KIND_PAUSED: ControlKind
CONTROL_KIND_HOME: ControlKind
CONTROL_MODE_UNSPECIFIED: ControlMode
CONTROL_MODE_AUTO: ControlMode
CONTROL_MODE_OPERATOR: ControlMode
CONTROL_MODE_POLICY: ControlMode

class Stamp(_message.Message):
    __slots__ = ("source_id", "seq", "device_ns", "capture_ns", "arrival_ns", "confidence")
    SOURCE_ID_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    DEVICE_NS_FIELD_NUMBER: _ClassVar[int]
    CAPTURE_NS_FIELD_NUMBER: _ClassVar[int]
    ARRIVAL_NS_FIELD_NUMBER: _ClassVar[int]
    CONFIDENCE_FIELD_NUMBER: _ClassVar[int]
    source_id: str
    seq: int
    device_ns: int
    capture_ns: int
    arrival_ns: int
    confidence: float
    def __init__(self, source_id: _Optional[str] = ..., seq: _Optional[int] = ..., device_ns: _Optional[int] = ..., capture_ns: _Optional[int] = ..., arrival_ns: _Optional[int] = ..., confidence: _Optional[float] = ...) -> None: ...

class Pose(_message.Message):
    __slots__ = ("position", "orientation", "frame_id")
    POSITION_FIELD_NUMBER: _ClassVar[int]
    ORIENTATION_FIELD_NUMBER: _ClassVar[int]
    FRAME_ID_FIELD_NUMBER: _ClassVar[int]
    position: _containers.RepeatedScalarFieldContainer[float]
    orientation: _containers.RepeatedScalarFieldContainer[float]
    frame_id: str
    def __init__(self, position: _Optional[_Iterable[float]] = ..., orientation: _Optional[_Iterable[float]] = ..., frame_id: _Optional[str] = ...) -> None: ...

class HandPose(_message.Message):
    __slots__ = ("handedness", "wrist_position", "wrist_orientation", "keypoints", "keypoint_confidence", "frame_id")
    HANDEDNESS_FIELD_NUMBER: _ClassVar[int]
    WRIST_POSITION_FIELD_NUMBER: _ClassVar[int]
    WRIST_ORIENTATION_FIELD_NUMBER: _ClassVar[int]
    KEYPOINTS_FIELD_NUMBER: _ClassVar[int]
    KEYPOINT_CONFIDENCE_FIELD_NUMBER: _ClassVar[int]
    FRAME_ID_FIELD_NUMBER: _ClassVar[int]
    handedness: Handedness
    wrist_position: _containers.RepeatedScalarFieldContainer[float]
    wrist_orientation: _containers.RepeatedScalarFieldContainer[float]
    keypoints: _containers.RepeatedScalarFieldContainer[float]
    keypoint_confidence: _containers.RepeatedScalarFieldContainer[float]
    frame_id: str
    def __init__(self, handedness: _Optional[_Union[Handedness, str]] = ..., wrist_position: _Optional[_Iterable[float]] = ..., wrist_orientation: _Optional[_Iterable[float]] = ..., keypoints: _Optional[_Iterable[float]] = ..., keypoint_confidence: _Optional[_Iterable[float]] = ..., frame_id: _Optional[str] = ...) -> None: ...

class BodySkeleton(_message.Message):
    __slots__ = ("joint_names", "positions", "orientations", "frame_id")
    JOINT_NAMES_FIELD_NUMBER: _ClassVar[int]
    POSITIONS_FIELD_NUMBER: _ClassVar[int]
    ORIENTATIONS_FIELD_NUMBER: _ClassVar[int]
    FRAME_ID_FIELD_NUMBER: _ClassVar[int]
    joint_names: _containers.RepeatedScalarFieldContainer[str]
    positions: _containers.RepeatedScalarFieldContainer[float]
    orientations: _containers.RepeatedScalarFieldContainer[float]
    frame_id: str
    def __init__(self, joint_names: _Optional[_Iterable[str]] = ..., positions: _Optional[_Iterable[float]] = ..., orientations: _Optional[_Iterable[float]] = ..., frame_id: _Optional[str] = ...) -> None: ...

class ControllerState(_message.Message):
    __slots__ = ("hand", "position", "orientation", "frame_id", "buttons", "trigger", "grip", "joystick")
    HAND_FIELD_NUMBER: _ClassVar[int]
    POSITION_FIELD_NUMBER: _ClassVar[int]
    ORIENTATION_FIELD_NUMBER: _ClassVar[int]
    FRAME_ID_FIELD_NUMBER: _ClassVar[int]
    BUTTONS_FIELD_NUMBER: _ClassVar[int]
    TRIGGER_FIELD_NUMBER: _ClassVar[int]
    GRIP_FIELD_NUMBER: _ClassVar[int]
    JOYSTICK_FIELD_NUMBER: _ClassVar[int]
    hand: Handedness
    position: _containers.RepeatedScalarFieldContainer[float]
    orientation: _containers.RepeatedScalarFieldContainer[float]
    frame_id: str
    buttons: _containers.RepeatedScalarFieldContainer[str]
    trigger: float
    grip: float
    joystick: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, hand: _Optional[_Union[Handedness, str]] = ..., position: _Optional[_Iterable[float]] = ..., orientation: _Optional[_Iterable[float]] = ..., frame_id: _Optional[str] = ..., buttons: _Optional[_Iterable[str]] = ..., trigger: _Optional[float] = ..., grip: _Optional[float] = ..., joystick: _Optional[_Iterable[float]] = ...) -> None: ...

class Twist(_message.Message):
    __slots__ = ("linear", "angular", "frame_id")
    LINEAR_FIELD_NUMBER: _ClassVar[int]
    ANGULAR_FIELD_NUMBER: _ClassVar[int]
    FRAME_ID_FIELD_NUMBER: _ClassVar[int]
    linear: _containers.RepeatedScalarFieldContainer[float]
    angular: _containers.RepeatedScalarFieldContainer[float]
    frame_id: str
    def __init__(self, linear: _Optional[_Iterable[float]] = ..., angular: _Optional[_Iterable[float]] = ..., frame_id: _Optional[str] = ...) -> None: ...

class JointCommand(_message.Message):
    __slots__ = ("names", "positions", "velocities")
    NAMES_FIELD_NUMBER: _ClassVar[int]
    POSITIONS_FIELD_NUMBER: _ClassVar[int]
    VELOCITIES_FIELD_NUMBER: _ClassVar[int]
    names: _containers.RepeatedScalarFieldContainer[str]
    positions: _containers.RepeatedScalarFieldContainer[float]
    velocities: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, names: _Optional[_Iterable[str]] = ..., positions: _Optional[_Iterable[float]] = ..., velocities: _Optional[_Iterable[float]] = ...) -> None: ...

class GripperCommand(_message.Message):
    __slots__ = ("opening", "max_force")
    OPENING_FIELD_NUMBER: _ClassVar[int]
    MAX_FORCE_FIELD_NUMBER: _ClassVar[int]
    opening: float
    max_force: float
    def __init__(self, opening: _Optional[float] = ..., max_force: _Optional[float] = ...) -> None: ...

class BaseVelocity(_message.Message):
    __slots__ = ("vx", "vy", "wz")
    VX_FIELD_NUMBER: _ClassVar[int]
    VY_FIELD_NUMBER: _ClassVar[int]
    WZ_FIELD_NUMBER: _ClassVar[int]
    vx: float
    vy: float
    wz: float
    def __init__(self, vx: _Optional[float] = ..., vy: _Optional[float] = ..., wz: _Optional[float] = ...) -> None: ...

class JointState(_message.Message):
    __slots__ = ("names", "positions", "velocities", "efforts")
    NAMES_FIELD_NUMBER: _ClassVar[int]
    POSITIONS_FIELD_NUMBER: _ClassVar[int]
    VELOCITIES_FIELD_NUMBER: _ClassVar[int]
    EFFORTS_FIELD_NUMBER: _ClassVar[int]
    names: _containers.RepeatedScalarFieldContainer[str]
    positions: _containers.RepeatedScalarFieldContainer[float]
    velocities: _containers.RepeatedScalarFieldContainer[float]
    efforts: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, names: _Optional[_Iterable[str]] = ..., positions: _Optional[_Iterable[float]] = ..., velocities: _Optional[_Iterable[float]] = ..., efforts: _Optional[_Iterable[float]] = ...) -> None: ...

class CameraFrame(_message.Message):
    __slots__ = ("camera_id", "frame_index", "width", "height")
    CAMERA_ID_FIELD_NUMBER: _ClassVar[int]
    FRAME_INDEX_FIELD_NUMBER: _ClassVar[int]
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    camera_id: str
    frame_index: int
    width: int
    height: int
    def __init__(self, camera_id: _Optional[str] = ..., frame_index: _Optional[int] = ..., width: _Optional[int] = ..., height: _Optional[int] = ...) -> None: ...

class Wrench(_message.Message):
    __slots__ = ("force", "torque", "frame_id")
    FORCE_FIELD_NUMBER: _ClassVar[int]
    TORQUE_FIELD_NUMBER: _ClassVar[int]
    FRAME_ID_FIELD_NUMBER: _ClassVar[int]
    force: _containers.RepeatedScalarFieldContainer[float]
    torque: _containers.RepeatedScalarFieldContainer[float]
    frame_id: str
    def __init__(self, force: _Optional[_Iterable[float]] = ..., torque: _Optional[_Iterable[float]] = ..., frame_id: _Optional[str] = ...) -> None: ...

class ControlSource(_message.Message):
    __slots__ = ("source", "kind", "mode")
    SOURCE_FIELD_NUMBER: _ClassVar[int]
    KIND_FIELD_NUMBER: _ClassVar[int]
    MODE_FIELD_NUMBER: _ClassVar[int]
    source: str
    kind: ControlKind
    mode: ControlMode
    def __init__(self, source: _Optional[str] = ..., kind: _Optional[_Union[ControlKind, str]] = ..., mode: _Optional[_Union[ControlMode, str]] = ...) -> None: ...

class RetargetResidual(_message.Message):
    __slots__ = ("flagged", "names", "values")
    FLAGGED_FIELD_NUMBER: _ClassVar[int]
    NAMES_FIELD_NUMBER: _ClassVar[int]
    VALUES_FIELD_NUMBER: _ClassVar[int]
    flagged: bool
    names: _containers.RepeatedScalarFieldContainer[str]
    values: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, flagged: _Optional[bool] = ..., names: _Optional[_Iterable[str]] = ..., values: _Optional[_Iterable[float]] = ...) -> None: ...

class Envelope(_message.Message):
    __slots__ = ("schema_version", "stamp", "pose", "hand_pose", "body_skeleton", "controller_state", "twist", "joint_command", "gripper_command", "base_velocity", "joint_state", "camera_frame", "wrench", "control_source", "retarget_residual")
    SCHEMA_VERSION_FIELD_NUMBER: _ClassVar[int]
    STAMP_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    HAND_POSE_FIELD_NUMBER: _ClassVar[int]
    BODY_SKELETON_FIELD_NUMBER: _ClassVar[int]
    CONTROLLER_STATE_FIELD_NUMBER: _ClassVar[int]
    TWIST_FIELD_NUMBER: _ClassVar[int]
    JOINT_COMMAND_FIELD_NUMBER: _ClassVar[int]
    GRIPPER_COMMAND_FIELD_NUMBER: _ClassVar[int]
    BASE_VELOCITY_FIELD_NUMBER: _ClassVar[int]
    JOINT_STATE_FIELD_NUMBER: _ClassVar[int]
    CAMERA_FRAME_FIELD_NUMBER: _ClassVar[int]
    WRENCH_FIELD_NUMBER: _ClassVar[int]
    CONTROL_SOURCE_FIELD_NUMBER: _ClassVar[int]
    RETARGET_RESIDUAL_FIELD_NUMBER: _ClassVar[int]
    schema_version: int
    stamp: Stamp
    pose: Pose
    hand_pose: HandPose
    body_skeleton: BodySkeleton
    controller_state: ControllerState
    twist: Twist
    joint_command: JointCommand
    gripper_command: GripperCommand
    base_velocity: BaseVelocity
    joint_state: JointState
    camera_frame: CameraFrame
    wrench: Wrench
    control_source: ControlSource
    retarget_residual: RetargetResidual
    def __init__(self, schema_version: _Optional[int] = ..., stamp: _Optional[_Union[Stamp, _Mapping]] = ..., pose: _Optional[_Union[Pose, _Mapping]] = ..., hand_pose: _Optional[_Union[HandPose, _Mapping]] = ..., body_skeleton: _Optional[_Union[BodySkeleton, _Mapping]] = ..., controller_state: _Optional[_Union[ControllerState, _Mapping]] = ..., twist: _Optional[_Union[Twist, _Mapping]] = ..., joint_command: _Optional[_Union[JointCommand, _Mapping]] = ..., gripper_command: _Optional[_Union[GripperCommand, _Mapping]] = ..., base_velocity: _Optional[_Union[BaseVelocity, _Mapping]] = ..., joint_state: _Optional[_Union[JointState, _Mapping]] = ..., camera_frame: _Optional[_Union[CameraFrame, _Mapping]] = ..., wrench: _Optional[_Union[Wrench, _Mapping]] = ..., control_source: _Optional[_Union[ControlSource, _Mapping]] = ..., retarget_residual: _Optional[_Union[RetargetResidual, _Mapping]] = ...) -> None: ...

class Bundle(_message.Message):
    __slots__ = ("schema_version", "parts")
    SCHEMA_VERSION_FIELD_NUMBER: _ClassVar[int]
    PARTS_FIELD_NUMBER: _ClassVar[int]
    schema_version: int
    parts: _containers.RepeatedCompositeFieldContainer[BundlePart]
    def __init__(self, schema_version: _Optional[int] = ..., parts: _Optional[_Iterable[_Union[BundlePart, _Mapping]]] = ...) -> None: ...

class BundlePart(_message.Message):
    __slots__ = ("stream", "envelope")
    STREAM_FIELD_NUMBER: _ClassVar[int]
    ENVELOPE_FIELD_NUMBER: _ClassVar[int]
    stream: str
    envelope: bytes
    def __init__(self, stream: _Optional[str] = ..., envelope: _Optional[bytes] = ...) -> None: ...
