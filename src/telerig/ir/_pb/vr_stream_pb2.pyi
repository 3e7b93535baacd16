from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class VrButtonBit(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    VR_BUTTON_BIT_A: _ClassVar[VrButtonBit]
    VR_BUTTON_BIT_B: _ClassVar[VrButtonBit]
    VR_BUTTON_BIT_X: _ClassVar[VrButtonBit]
    VR_BUTTON_BIT_Y: _ClassVar[VrButtonBit]
    VR_BUTTON_BIT_THUMBSTICK: _ClassVar[VrButtonBit]
    VR_BUTTON_BIT_MENU: _ClassVar[VrButtonBit]
VR_BUTTON_BIT_A: VrButtonBit
VR_BUTTON_BIT_B: VrButtonBit
VR_BUTTON_BIT_X: VrButtonBit
VR_BUTTON_BIT_Y: VrButtonBit
VR_BUTTON_BIT_THUMBSTICK: VrButtonBit
VR_BUTTON_BIT_MENU: VrButtonBit

class VrPose(_message.Message):
    __slots__ = ("px", "py", "pz", "qx", "qy", "qz", "qw")
    PX_FIELD_NUMBER: _ClassVar[int]
    PY_FIELD_NUMBER: _ClassVar[int]
    PZ_FIELD_NUMBER: _ClassVar[int]
    QX_FIELD_NUMBER: _ClassVar[int]
    QY_FIELD_NUMBER: _ClassVar[int]
    QZ_FIELD_NUMBER: _ClassVar[int]
    QW_FIELD_NUMBER: _ClassVar[int]
    px: float
    py: float
    pz: float
    qx: float
    qy: float
    qz: float
    qw: float
    def __init__(self, px: _Optional[float] = ..., py: _Optional[float] = ..., pz: _Optional[float] = ..., qx: _Optional[float] = ..., qy: _Optional[float] = ..., qz: _Optional[float] = ..., qw: _Optional[float] = ...) -> None: ...

class VrController(_message.Message):
    __slots__ = ("tracked", "grip", "buttons", "trigger", "squeeze", "thumbstick_x", "thumbstick_y")
    TRACKED_FIELD_NUMBER: _ClassVar[int]
    GRIP_FIELD_NUMBER: _ClassVar[int]
    BUTTONS_FIELD_NUMBER: _ClassVar[int]
    TRIGGER_FIELD_NUMBER: _ClassVar[int]
    SQUEEZE_FIELD_NUMBER: _ClassVar[int]
    THUMBSTICK_X_FIELD_NUMBER: _ClassVar[int]
    THUMBSTICK_Y_FIELD_NUMBER: _ClassVar[int]
    tracked: bool
    grip: VrPose
    buttons: int
    trigger: float
    squeeze: float
    thumbstick_x: float
    thumbstick_y: float
    def __init__(self, tracked: _Optional[bool] = ..., grip: _Optional[_Union[VrPose, _Mapping]] = ..., buttons: _Optional[int] = ..., trigger: _Optional[float] = ..., squeeze: _Optional[float] = ..., thumbstick_x: _Optional[float] = ..., thumbstick_y: _Optional[float] = ...) -> None: ...

class VrHand(_message.Message):
    __slots__ = ("tracked", "joint_positions", "joint_orientations", "joint_radii", "joint_invalid_mask")
    TRACKED_FIELD_NUMBER: _ClassVar[int]
    JOINT_POSITIONS_FIELD_NUMBER: _ClassVar[int]
    JOINT_ORIENTATIONS_FIELD_NUMBER: _ClassVar[int]
    JOINT_RADII_FIELD_NUMBER: _ClassVar[int]
    JOINT_INVALID_MASK_FIELD_NUMBER: _ClassVar[int]
    tracked: bool
    joint_positions: _containers.RepeatedScalarFieldContainer[float]
    joint_orientations: _containers.RepeatedScalarFieldContainer[float]
    joint_radii: _containers.RepeatedScalarFieldContainer[float]
    joint_invalid_mask: int
    def __init__(self, tracked: _Optional[bool] = ..., joint_positions: _Optional[_Iterable[float]] = ..., joint_orientations: _Optional[_Iterable[float]] = ..., joint_radii: _Optional[_Iterable[float]] = ..., joint_invalid_mask: _Optional[int] = ...) -> None: ...

class VrFrame(_message.Message):
    __slots__ = ("format_version", "stream_id", "seq", "device_time_ns", "head_tracked", "head", "left", "right", "left_hand", "right_hand", "device")
    FORMAT_VERSION_FIELD_NUMBER: _ClassVar[int]
    STREAM_ID_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    DEVICE_TIME_NS_FIELD_NUMBER: _ClassVar[int]
    HEAD_TRACKED_FIELD_NUMBER: _ClassVar[int]
    HEAD_FIELD_NUMBER: _ClassVar[int]
    LEFT_FIELD_NUMBER: _ClassVar[int]
    RIGHT_FIELD_NUMBER: _ClassVar[int]
    LEFT_HAND_FIELD_NUMBER: _ClassVar[int]
    RIGHT_HAND_FIELD_NUMBER: _ClassVar[int]
    DEVICE_FIELD_NUMBER: _ClassVar[int]
    format_version: int
    stream_id: int
    seq: int
    device_time_ns: int
    head_tracked: bool
    head: VrPose
    left: VrController
    right: VrController
    left_hand: VrHand
    right_hand: VrHand
    device: str
    def __init__(self, format_version: _Optional[int] = ..., stream_id: _Optional[int] = ..., seq: _Optional[int] = ..., device_time_ns: _Optional[int] = ..., head_tracked: _Optional[bool] = ..., head: _Optional[_Union[VrPose, _Mapping]] = ..., left: _Optional[_Union[VrController, _Mapping]] = ..., right: _Optional[_Union[VrController, _Mapping]] = ..., left_hand: _Optional[_Union[VrHand, _Mapping]] = ..., right_hand: _Optional[_Union[VrHand, _Mapping]] = ..., device: _Optional[str] = ...) -> None: ...
